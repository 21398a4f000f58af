"""The realism axis of a scaling study: what each property of real scenes, added to the training data, buys
on the held-out real-scene suite and costs on held-out ordinary frames.

Each model of ``realism`` trained on the training config's own frames (level ``none``) and on the same
scenes with one property added (a level: ``scene_gen`` and ``render`` settings, :func:`studies.scaling.
ScalingConfig.level_configs`), at the same steps, several seeds. Every run, and the noisy input and OIDN
at the model's spp, was evaluated on the held-out ordinary frames and on every frame of the real-scene
suite rendered with each pixel filter (:mod:`studies.scaling_run`). :func:`analyse_realism` turns those
records into, per model:

- **ordinary frames**, per level: the mean of each metric over the seeds with its 95% interval and the
  paired difference from ``none`` (:func:`studies.hard_share._ordinary_cell`);
- **the suite**, per filter, scene (and all its frames, ``(all)``) and level: a
  :func:`training.hardcases.case_cell` of the seeds-averaged per-frame values, the paired difference from
  ``none`` (relMSE and PSNR), the verdict against the model's own noisy input and the comparison with OIDN
  at the same spp (:func:`training.realscenes.against`: paired differences and the relMSE ratio);
- a one-line verdict per model and level: what the level does on the whole suite under each filter
  (better / worse / not shown against ``none``, by both relMSE and PSNR) and to the ordinary frames' PSNR.

:func:`realism_markdown` writes the section of ``scaling.md``.
"""
from __future__ import annotations

import math

from training import stats

from .hard_share import METRICS, _baseline_rows, _diff, _mean_ci, _ordinary_cell, _rows
from .scaling import REALISM_NONE

ALL = "(all)"


def _by_scene(rows: list[dict], scenes: list[str]) -> dict:
    out: dict = {ALL: list(rows)}
    for r in rows:
        out.setdefault(scenes[int(r["index"])], []).append(r)
    return out


def _vs(rows: list[dict], base: list[dict]) -> dict:
    """Paired per-frame differences ``rows - base`` of relMSE and PSNR, and a verdict: ``better`` (both
    intervals exclude 0 on the right side), ``worse`` (one excludes 0 on the wrong side) or ``not shown``."""
    ref = {int(r["index"]): r for r in base}
    mine = [r for r in rows if int(r["index"]) in ref]
    groups = {int(r["index"]): r.get("clip", r["index"]) for r in mine}
    out = {m: stats.paired_difference({i: ref[i][m] for i in groups}, {int(r["index"]): r[m] for r in mine}, groups)
           for m in METRICS}
    ds = [(out["relmse"], -1.0), (out["psnr"], 1.0)]
    out["verdict"] = ("better" if all(d and d["shown"] and s * d["mean"] > 0 for d, s in ds) else
                      "worse" if any(d and d["shown"] and s * d["mean"] < 0 for d, s in ds) else "not shown")
    return out


def model_levels(label: str, cfg, jobs, records: dict, scenes: dict) -> dict:
    """One model's results on the realism axis (module docstring); ``scenes``: filter -> each suite frame's
    scene name (``training.realscenes.frame_scenes``)."""
    from training.hardcases import against_input, case_cell
    from training.inputs import KINDS
    from training.models import get
    from training.realscenes import against
    sel = [j for j in jobs if j.kind == "realism" and j.label == label and j.name in records
           and "real_evaluation" in records[j.name]]
    levels = [lv for lv in dict.fromkeys(j.level for j in jobs if j.kind == "realism" and j.label == label)
              if any(j.level == lv for j in sel)]
    b_input = KINDS[get(cfg.model).inputs.kind].baseline_input
    ordinary_base = _baseline_rows(jobs, records, cfg.spp, b_input, "evaluation")
    ordinary = {lv: _rows([records[j.name]["evaluation"] for j in sel if j.level == lv]) for lv in levels}
    none = ordinary.get(REALISM_NONE)
    out = {"model": label, "spp": cfg.spp, "baseline_input": b_input, "levels": levels,
           "seeds": {lv: sorted(j.seed for j in sel if j.level == lv) for lv in levels},
           "ordinary": {lv: _ordinary_cell(ordinary[lv], none if none is not None and lv != REALISM_NONE else None)
                        for lv in levels},
           "baselines_ordinary": {m: _ordinary_cell(r, None) for m, r in ordinary_base.items()},
           "suite": {}}
    for f, names in scenes.items():
        base = {}
        for j in jobs:
            if j.kind == "baseline" and j.spp == cfg.spp and j.baseline_input == b_input and j.name in records:
                ev = records[j.name].get("real_evaluation", {}).get(f)
                if ev is not None:
                    base[j.method] = _by_scene(_rows([ev]), names)
        runs = {lv: _by_scene(_rows([records[j.name]["real_evaluation"][f] for j in sel if j.level == lv]), names)
                for lv in levels}
        table: dict = {}
        for lv, by in runs.items():
            for scene, rows in by.items():
                cell = case_cell(rows)
                if scene in base.get("input", {}):
                    cell["vs_input"] = against_input(rows, base["input"][scene], f"input @{cfg.spp}spp")
                if scene in base.get("oidn", {}):
                    cell["vs_oidn"] = against(rows, base["oidn"][scene], f"oidn @{cfg.spp}spp")
                if lv != REALISM_NONE and REALISM_NONE in runs:
                    cell["vs_none"] = _vs(rows, runs[REALISM_NONE][scene])
                table.setdefault(scene, {})[lv] = cell
        for m, by in base.items():
            for scene, rows in by.items():
                table.setdefault(scene, {})[m] = case_cell(rows)
        out["suite"][f] = table
    out["verdicts"] = level_verdicts(out)
    return out


def level_verdicts(res: dict) -> list[str]:
    """One line per level above ``none``: its effect on the whole suite under each filter and on the
    ordinary frames' PSNR, with intervals."""
    lines = []
    for lv in res["levels"]:
        if lv == REALISM_NONE:
            continue
        parts = []
        for f, table in res["suite"].items():
            cell = table.get(ALL, {}).get(lv) or {}
            v = cell.get("vs_none")
            if not v:
                continue
            d = v["relmse"]
            base = table[ALL][REALISM_NONE]["relmse"]
            rel = f" ({100 * d['mean'] / base:+.0f}%)" if d and base else ""
            better = [s for s, row in table.items() if s != ALL and (row.get(lv) or {}).get("vs_none", {}).get("verdict") == "better"]
            worse = [s for s, row in table.items() if s != ALL and (row.get(lv) or {}).get("vs_none", {}).get("verdict") == "worse"]
            parts.append(f"{f} filter: {v['verdict']} on the whole suite, relMSE {_diff(d, '+.3g')}{rel}"
                         + (f"; better on {', '.join(better)}" if better else "")
                         + (f"; worse on {', '.join(worse)}" if worse else ""))
        d = res["ordinary"].get(lv, {}).get("psnr", {}).get("vs_none")
        if d:
            parts.append(f"ordinary frames' PSNR {_diff(d, '+.2f')} dB")
        lines.append(f"{res['model']}, {lv} against {REALISM_NONE}: " +
                     ("; ".join(parts) if parts else f"no `{REALISM_NONE}` runs to compare with") + ".")
    return lines


def analyse_realism(scfg, jobs, records: dict, scenes: dict) -> list[dict]:
    """Every model of the realism axis (``scenes``: filter -> suite frame index -> scene name)."""
    r = scfg.realism_plan()
    if not r or not scenes:
        return []
    plans = dict(scfg.model_plans())
    return [model_levels(label, plans[label], jobs, records, scenes) for label in r["models"]]


# --------------------------------------------------------------------------------------------
# scaling.md


def _value(cell: dict | None) -> str:
    if not cell:
        return "–"
    p = cell["psnr"]
    text = f"{cell['relmse']:.3g} / " + ("inf" if math.isinf(p) else f"{p:.1f}")
    ratio = (cell.get("vs_oidn") or {}).get("relmse_ratio")
    return text + (f" ({ratio:.2g}x OIDN)" if ratio is not None else "")


def _vs_cell(cell: dict | None, key: str) -> str:
    v = (cell or {}).get(key)
    if not v:
        return "–"
    if v.get("verdict") in ("exact", "not exact"):
        return v["verdict"]
    r, p = v.get("relmse"), v.get("psnr")
    return (f"{_diff(r, '+.3g') if r else '–'} / {_diff(p, '+.2f') if p else '–'}: "
            f"{'**' + v['verdict'] + '**' if v['verdict'] in ('worse',) else v['verdict']}")


def realism_markdown(results: list[dict]) -> list[str]:
    """The section of ``scaling.md``: the verdicts, the ordinary frames, and per model and filter the suite
    scene by scene."""
    if not results:
        return []
    lines = ["## Properties of real scenes in the training data", "",
             *[f"- {v}" for r in results for v in r["verdicts"]], "",
             "### Held-out ordinary frames", "",
             f"Mean over the seeds with its 95% interval; Δ: paired per-frame difference from `{REALISM_NONE}` "
             "(the training config's own frames).", "",
             "| model | level | PSNR | Δ PSNR | relMSE | Δ relMSE |", "|---|---|---|---|---|---|"]
    for r in results:
        for lv in r["levels"]:
            c = r["ordinary"][lv]
            lines.append(f"| {r['model']} | {lv} | {_mean_ci(c['psnr'], '.2f')} | {_diff(c['psnr'].get('vs_none'), '+.2f')} "
                         f"| {_mean_ci(c['relmse'], '.4g')} | {_diff(c['relmse'].get('vs_none'), '+.4g')} |")
        for m, c in r["baselines_ordinary"].items():
            lines.append(f"| {m} @{r['spp']}spp | – | {_mean_ci(c['psnr'], '.2f')} | – | {_mean_ci(c['relmse'], '.4g')} | – |")
    for r in results:
        for f, table in r["suite"].items():
            cols = list(r["levels"]) + [m for m in ("input", "oidn") if any(m in row for row in table.values())]
            names = [c if c in r["levels"] else f"{c} @{r['spp']}spp" for c in cols]
            lines += ["", f"### {r['model']} on the real-scene suite, {f} filter", "",
                      "relMSE / PSNR (dB) of the seeds-averaged outputs over the scene's frames, and the relMSE over "
                      "OIDN's at the same spp.", "",
                      "| scene | " + " | ".join(names) + " |", "|---|" + "---|" * len(cols)]
            for scene, row in table.items():
                lines.append(f"| {scene} | " + " | ".join(_value(row.get(c)) for c in cols) + " |")
            above = [lv for lv in r["levels"] if lv != REALISM_NONE]
            lines += ["", f"Against `{REALISM_NONE}` (ΔrelMSE / ΔPSNR, level minus {REALISM_NONE}, 95% intervals) and "
                      "against the model's own noisy input:", "",
                      "| scene | " + " | ".join(f"{lv} vs {REALISM_NONE}" for lv in above) + " | "
                      + " | ".join(f"{lv} vs input" for lv in r["levels"]) + " |",
                      "|---|" + "---|" * (len(above) + len(r["levels"]))]
            for scene, row in table.items():
                lines.append(f"| {scene} | " + " | ".join(_vs_cell(row.get(lv), "vs_none") for lv in above) + " | "
                             + " | ".join(_vs_cell(row.get(lv), "vs_input") for lv in r["levels"]) + " |")
    return lines + [""]
