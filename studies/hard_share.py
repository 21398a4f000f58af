"""The hard-case share axis of a scaling study: what hard-case frames in the training data buy, and cost.

Each model of ``hard_share`` trained at each share of hard-case frames (the same frames and steps, several
seeds; :func:`studies.scaling.hard_subsets`) was evaluated on the held-out ordinary frames and on every frame
of the held-out hard-case suite, and so were the noisy input and OIDN at the model's spp
(:mod:`studies.scaling_run`). :func:`analyse_shares` turns those records into:

- **ordinary frames**, per model and share: the mean of each metric over the seeds with its 95% interval
  (a bootstrap over the held-out clips of the seeds-averaged per-frame values) and the paired difference
  from share 0;
- **the suite**, per model, share and case: a :func:`training.hardcases.case_cell` of the seeds-averaged
  per-frame values, the paired difference from share 0, and the verdict against the model's own noisy
  input (:func:`training.hardcases.against_input`: better where both relMSE and PSNR intervals exclude 0
  on the right side); the input and OIDN beside them;
- a one-line verdict per model.

:func:`share_markdown` writes the section of ``scaling.md``.
"""
from __future__ import annotations

import math

import numpy as np

from training import stats
from training.errors import DataError
from training.hardcases import NO_CASE, against_input, case_cell, vs_input_cell

METRICS = ("relmse", "psnr")


def _rows(evaluations: list[dict]) -> list[dict]:
    """Per-frame rows averaged over several evaluations of the same frames (seeds): index, clip, relmse,
    psnr (inf where every seed's output is exact) and whether the values are finite."""
    first = evaluations[0]["frames"]
    if any([g["index"] for g in ev["frames"]] != [f["index"] for f in first] for ev in evaluations):
        raise DataError("the runs of one share were evaluated on other frames: evaluate them again")
    out = []
    for k, f in enumerate(first):
        row = {"index": int(f["index"]), "clip": int(f.get("clip", f["index"]))}
        for m in METRICS:
            row[m] = float(np.mean([_value(ev["frames"][k], m) for ev in evaluations]))
        row["finite"] = bool(np.isfinite(row["relmse"]) and not np.isnan(row["psnr"]))
        out.append(row)
    return out


def _value(frame: dict, metric: str) -> float:
    """A record's per-frame figure; strict JSON writes a non-finite number as null: a PSNR of null is the
    +inf of an exact output (relMSE 0), anything else null is NaN."""
    v = frame.get(metric)
    if v is not None:
        return float(v)
    return math.inf if metric == "psnr" and frame.get("relmse") == 0.0 else math.nan


def _by_case(rows: list[dict], cases: dict) -> dict:
    out: dict = {}
    for r in rows:
        out.setdefault(cases.get(r["index"]) or NO_CASE, []).append(r)
    return out


def _ordinary_cell(rows: list[dict], base: list[dict] | None) -> dict:
    clips = [r["clip"] for r in rows]
    cell = {m: {"mean": float(np.mean([r[m] for r in rows])), "ci95": stats.mean_ci([r[m] for r in rows], clips)}
            for m in METRICS}
    if base is not None:
        for m in METRICS:
            cell[m]["vs_none"] = stats.paired_difference({r["index"]: r[m] for r in base},
                                                         {r["index"]: r[m] for r in rows},
                                                         {r["index"]: r["clip"] for r in rows})
    return cell


def _baseline_rows(jobs, records: dict, spp: int, baseline_input: str, key: str) -> dict:
    """``{method: rows}`` of the input and OIDN evaluations at ``spp`` and ``baseline_input`` (``key``: the
    record's evaluation, ordinary or suite)."""
    out = {}
    for j in jobs:
        if j.kind == "baseline" and j.spp == spp and j.baseline_input == baseline_input and j.name in records \
                and key in records[j.name]:
            out[j.method] = _rows([records[j.name][key]])
    return out


def model_shares(label: str, cfg, jobs, records: dict, cases: dict) -> dict:
    """One model's results on the share axis (module docstring)."""
    from training.inputs import KINDS
    from training.models import get
    sel = [j for j in jobs if j.kind == "hard" and j.label == label and j.name in records
           and "hard_evaluation" in records[j.name]]
    shares = sorted({j.share for j in sel})
    b_input = KINDS[get(cfg.model).inputs.kind].baseline_input
    base = {k: _baseline_rows(jobs, records, cfg.spp, b_input, k) for k in ("evaluation", "hard_evaluation")}
    ordinary, suite = {}, {}
    for share in shares:
        runs = [records[j.name] for j in sel if j.share == share]
        ordinary[share] = _rows([r["evaluation"] for r in runs])
        suite[share] = _rows([r["hard_evaluation"] for r in runs])
    none = shares[0] if shares and shares[0] == 0 else None
    inputs = _by_case(base["hard_evaluation"].get("input", []), cases)
    out = {"model": label, "spp": cfg.spp, "baseline_input": b_input, "shares": shares,
           "seeds": {str(s): sorted(j.seed for j in sel if j.share == s) for s in shares},
           "ordinary": {str(s): _ordinary_cell(ordinary[s], ordinary[none] if none is not None and s != none else None)
                        for s in shares},
           "baselines_ordinary": {m: _ordinary_cell(r, None) for m, r in base["evaluation"].items()},
           "cases": {}}
    for share in shares:
        for c, rows in _by_case(suite[share], cases).items():
            cell = case_cell(rows)
            if c in inputs:
                cell["vs_input"] = against_input(rows, inputs[c], f"input @{cfg.spp}spp")
            if none is not None and share != none:
                ref = {r["index"]: r for r in _by_case(suite[none], cases)[c]}
                cell["vs_none"] = {m: stats.paired_difference({i: ref[i][m] for i in ref}, {r["index"]: r[m] for r in rows},
                                                              {r["index"]: r["clip"] for r in rows}) for m in METRICS}
            out["cases"].setdefault(c, {})[str(share)] = cell
    for m, rows in base["hard_evaluation"].items():
        for c, rs in _by_case(rows, cases).items():
            cell = case_cell(rs)
            if m != "input" and c in inputs:
                cell["vs_input"] = against_input(rs, inputs[c], f"input @{cfg.spp}spp")
            out["cases"].setdefault(c, {})[m] = cell
    out["verdict"] = share_verdict(out)
    return out


def _pct(share: float) -> str:
    return f"{100 * share:g}%"


def share_verdict(res: dict) -> str:
    """One line: at each share above 0, on how many cases the model beats its own noisy input (and which it
    does not), and the ordinary frames' PSNR against share 0."""
    parts = []
    for share in res["shares"]:
        key = str(share)
        verdicts = {c: row[key].get("vs_input", {}).get("verdict") for c, row in res["cases"].items() if key in row}
        good = [c for c, v in verdicts.items() if v in ("beats", "exact")]
        bad = [f"{c} ({v})" for c, v in verdicts.items() if v not in ("beats", "exact")]
        text = f"at {_pct(share)} hard frames it beats its noisy input on {len(good)} of {len(verdicts)} cases"
        text += f" (not on {', '.join(bad)})" if bad else ""
        d = res["ordinary"][key]["psnr"].get("vs_none")
        if d:
            lo, hi = d["ci95"] or (math.nan, math.nan)
            text += f", ordinary PSNR {d['mean']:+.2f} dB [{lo:+.2f}, {hi:+.2f}] against 0%"
        parts.append(text)
    return f"{res['model']}: " + "; ".join(parts) + "."


def analyse_shares(scfg, jobs, records: dict, cases: dict) -> list[dict]:
    """Every model of the share axis (``cases``: suite frame index -> case tag)."""
    h = scfg.hard_share_plan()
    if not h:
        return []
    plans = dict(scfg.model_plans())
    return [model_shares(label, plans[label], jobs, records, cases) for label in h["models"]]


# --------------------------------------------------------------------------------------------
# scaling.md


def _mean_ci(cell: dict, f: str) -> str:
    ci = cell.get("ci95")
    return f"{cell['mean']:{f}}" + (f" [{ci[0]:{f}}, {ci[1]:{f}}]" if ci else "")


def _diff(d: dict | None, f: str) -> str:
    if not d:
        return "–"
    ci = d.get("ci95")
    return f"{d['mean']:{f}}" + (f" [{ci[0]:{f}}, {ci[1]:{f}}]" if ci else "") + ("" if d.get("shown") else " (none shown)")


def _suite_cell(cell: dict | None) -> str:
    if not cell:
        return "–"
    p = cell["psnr"]
    return f"{cell['relmse']:.3g} / " + ("inf" if math.isinf(p) else f"{p:.1f}")


def share_markdown(results: list[dict]) -> list[str]:
    """The section of ``scaling.md``: the verdicts, the ordinary frames, and per model the suite case by case."""
    if not results:
        return []
    lines = ["## Hard cases in the training data", "", *[f"- {r['verdict']}" for r in results], "",
             "### Held-out ordinary frames", "",
             "Mean over the seeds with its 95% interval; Δ: paired per-frame difference from 0% hard frames.", "",
             "| model | hard frames | PSNR | Δ PSNR | relMSE | Δ relMSE |", "|---|---|---|---|---|---|"]
    for r in results:
        for share in r["shares"]:
            c = r["ordinary"][str(share)]
            lines.append(f"| {r['model']} | {_pct(share)} | {_mean_ci(c['psnr'], '.2f')} | "
                         f"{_diff(c['psnr'].get('vs_none'), '+.2f')} | {_mean_ci(c['relmse'], '.4g')} | "
                         f"{_diff(c['relmse'].get('vs_none'), '+.4g')} |")
        for m, c in r["baselines_ordinary"].items():
            lines.append(f"| {m} @{r['spp']}spp | – | {_mean_ci(c['psnr'], '.2f')} | – | {_mean_ci(c['relmse'], '.4g')} | – |")
    for r in results:
        cols = [str(s) for s in r["shares"]] + [m for m in ("input", "oidn") if any(m in row for row in r["cases"].values())]
        names = [_pct(float(c)) if c[0].isdigit() else f"{c} @{r['spp']}spp" for c in cols]
        lines += ["", f"### {r['model']} on the held-out hard-case suite", "",
                  "relMSE / PSNR (dB) of the seeds-averaged outputs over the case's frames.", "",
                  "| case | " + " | ".join(names) + " |", "|---|" + "---|" * len(cols)]
        for case, row in r["cases"].items():
            lines.append(f"| {case} | " + " | ".join(_suite_cell(row.get(c)) for c in cols) + " |")
        vs = [c for c in cols if c != "input"]
        lines += ["", "Against its own noisy input (ΔrelMSE / ΔPSNR, method minus input, 95% intervals):", "",
                  "| case | " + " | ".join(n for c, n in zip(cols, names) if c != "input") + " |",
                  "|---|" + "---|" * len(vs)]
        for case, row in r["cases"].items():
            lines.append(f"| {case} | " + " | ".join(vs_input_cell(row.get(c)) for c in vs) + " |")
    return lines + [""]
