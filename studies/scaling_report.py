"""A scaling study's results: the analysis of its runs and the three files it writes.

:func:`analyse` turns the runs' evaluations (``studies.scaling_run`` records: per-frame metrics on the
same held-out frames) into the study's numbers: per model and metric the table of training-set sizes
(mean over seeds, the seeds' range, a 95% interval over the held-out clips, the paired change from the
next smaller set), the fit ``a N^(-b) + c`` with intervals or the reason there is none
(:mod:`studies.scaling_fit`), a verdict in one sentence, the cross-family matrix of the variety runs
and the frames a target needs with what rendering them costs. :func:`write_report` writes
``scaling.json`` (all of it), ``scaling.md`` (the tables) and ``scaling.png`` (the curves).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from training import stats
from training.errors import DataError, TargetBelowFloorError
from training.jsonio import write as write_json
from training.report import difference_cell
from .hard_share import analyse_shares, share_markdown
from .realism import analyse_realism, realism_markdown
from .scaling_fit import (bootstrap_fit, by_size, frames_for_target, limit_name, paired, power_law, sign_of,
                          size_table, support)

NAMES = {"relmse": "relMSE", "psnr": "PSNR", "smape": "SMAPE", "ssim": "SSIM", "flip": "FLIP", "tpsnr": "tPSNR"}
FORMATS = {"relmse": "{:.4g}", "psnr": "{:.2f}", "smape": "{:.4g}", "ssim": "{:.4g}", "flip": "{:.4g}",
           "tpsnr": "{:.2f}"}


def frame_values(record: dict, metric: str) -> tuple[list[int], np.ndarray]:
    """``(held-out frame indices, per-frame values of metric)`` of a run's evaluation (non-finite: NaN)."""
    frames = record["evaluation"]["frames"]
    vals = [f.get(metric) for f in frames]
    return [int(f["index"]) for f in frames], np.array([np.nan if v is None else v for v in vals], np.float64)


def heldout_frames(records: dict) -> dict:
    """The held-out frames every run was evaluated on: ``{"index", "clip", "family"}`` lists (the same for
    every record, else DataError)."""
    first = None
    for name, rec in records.items():
        idx = [int(f["index"]) for f in rec["evaluation"]["frames"]]
        if first is None:
            first = (name, idx, rec["evaluation"]["frames"])
        elif idx != first[1]:
            raise DataError(f"{name} was evaluated on other held-out frames than {first[0]}")
    if first is None:
        raise DataError("no evaluated run")
    fr = first[2]
    return {"index": first[1], "clip": [int(f.get("clip", f["index"])) for f in fr],
            "family": [str(f.get("scene_kind", "")) for f in fr]}


def _fmt(v, f: str) -> str:
    return "–" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f.format(v)


def _interval(ci, f: str) -> str:
    return "no interval" if ci is None else f"[{f.format(ci[0])}, {f.format(ci[1])}]"


def model_curve(jobs, records: dict, label: str, metric: str, clips, resamples: int) -> dict:
    """One model's curve in one metric: its sizes (:func:`studies.scaling_fit.size_table` without the
    per-frame values), the paired change from each size to the next, the support and the fit."""
    sel = [j for j in jobs if j.kind == "subset" and j.label == label and j.name in records]
    points = [{"n": j.frames, "seed": j.seed, "values": frame_values(records[j.name], metric)[1]} for j in sel]
    if not points:
        return {"sizes": [], "steps": [], "support": {"supported": False, "reason": "no finished run"}, "fit": None}
    sign = sign_of(metric)
    rows = size_table(points, clips)
    steps = [{"from": a["n"], "to": b["n"], **(paired(a, b, clips) or {})} for a, b in zip(rows, rows[1:])]
    sup = support(points, clips, sign)
    fit = bootstrap_fit(points, clips, sign, resamples=resamples) if len(by_size(points)) >= 3 else None
    return {"sizes": [{k: v for k, v in r.items() if k != "per_frame"} for r in rows], "steps": steps,
            "support": sup, "fit": fit}


def verdict(label: str, metric: str, curve: dict) -> str:
    """One sentence on what more data does for ``label`` in ``metric`` (module docstring)."""
    name, f = NAMES[metric], FORMATS[metric]
    sizes, sup, fit = curve["sizes"], curve["support"], curve["fit"]
    if not sizes:
        return f"{label}: no finished run."
    lo, hi = sizes[0], sizes[-1]
    span = (f"{name} {_fmt(lo['mean'], f)} {_interval(lo['ci95'], f)} at {lo['n']} frames and "
            f"{_fmt(hi['mean'], f)} {_interval(hi['ci95'], f)} at {hi['n']}")
    last = curve["steps"][-1] if curve["steps"] else None
    tail = ""
    if last and last.get("ci95") is not None:
        gain = last["shown"] and last["mean"] * sign_of(metric) < 0
        tail = (f"; from {last['from']} to {last['to']} frames {difference_cell(last, '{:+.4g}', -sign_of(metric))}"
                + (", so more of this data still helps at this size" if gain else
                   ", so at this size more of this data shows no further gain"))
    if not sup["supported"]:
        return f"{label}: the points do not support a fit ({sup['reason']}); {span}{tail}."
    lim = limit_name(metric)
    fit_text = ""
    if fit is not None:
        fit_text = (f"; the fit puts the {lim} at {_fmt(fit['c'], f)} {_interval(fit['ci95']['c'], f)} "
                    f"with exponent b = {fit['b']:.2f} {_interval(fit['ci95']['b'], '{:.2f}')}")
    return f"{label}: more data helps: {span}{fit_text}{tail}."


def variety_matrix(jobs, records: dict, label: str, metric: str, held: dict) -> dict:
    """The cross-family matrix of ``label``: for each training family (and ``both``), over its seeds, the
    mean of ``metric`` on each held-out family and on all frames with its interval (seeds averaged per
    frame, a bootstrap over clips), and the paired difference from training on ``both``."""
    sel = [j for j in jobs if j.kind == "variety" and j.label == label and j.name in records]
    fams = sorted({j.family for j in sel}, key=lambda f: (f == "both", f))
    evals = sorted(set(held["family"])) + ["all"]
    clips = np.asarray(held["clip"])
    avg = {fam: np.mean([frame_values(records[j.name], metric)[1] for j in sel if j.family == fam], axis=0)
           for fam in fams}
    rows = []
    for fam in fams:
        row = {"trained_on": fam, "frames": sorted({j.frames for j in sel if j.family == fam}),
               "seeds": sorted(j.seed for j in sel if j.family == fam), "cells": {}}
        for ev in evals:
            m = np.ones(len(clips), bool) if ev == "all" else np.asarray(held["family"]) == ev
            v = avg[fam][m]
            cell = {"frames": int(m.sum()), "mean": float(v.mean()), "ci95": stats.mean_ci(v, clips[m])}
            if fam != "both" and "both" in avg:
                ids = np.nonzero(m)[0]
                cell["vs_both"] = stats.paired_difference({i: avg["both"][i] for i in ids},
                                                          {i: avg[fam][i] for i in ids}, {i: clips[i] for i in ids})
            row["cells"][ev] = cell
        rows.append(row)
    return {"model": label, "metric": metric, "evaluated_on": evals, "rows": rows}


def target_answer(label: str, metric: str, target: float, curve: dict) -> dict:
    """The frames ``label`` needs for ``target`` of ``metric`` (:func:`price` adds what rendering them costs),
    or why there is no answer (no supported fit; the target beyond the fitted floor, which is named)."""
    out = {"model": label, "metric": metric, "target": float(target)}
    if curve["fit"] is None or not curve["support"]["supported"]:
        return {**out, "refused": f"no fit to invert: {curve['support']['reason']}"}
    try:
        ans = frames_for_target(curve["fit"], target, metric)
    except TargetBelowFloorError as e:
        return {**out, "refused": str(e), limit_name(metric): curve["fit"]["c"]}
    out.update(ans)
    top = max(s["n"] for s in curve["sizes"])
    out["beyond_measured"] = ans["frames"] > top
    return out


def cost_of(frames: float, costs: dict) -> dict:
    """Core-hours, store bytes and wall hours on the costs' workers of rendering ``frames`` frames."""
    core = frames * costs["core_hours_per_frame"]
    return {"frames": frames, "core_hours": core,
            "store_bytes": costs["store_fixed_bytes"] + frames * costs["bytes_per_frame"],
            "wall_hours": core / (costs["workers"] * costs["threads"])}


def price(answers: list[dict], costs: dict) -> None:
    """Add to every answered target what rendering its frames (and its interval's ends) costs (``costs``:
    ``studies.scaling_run.rendering_costs``)."""
    for a in answers:
        if "frames" in a:
            a["cost"] = cost_of(a["frames"], costs)
            a["cost_ci95"] = [cost_of(n, costs) if math.isfinite(n) else None for n in (a["ci95"] or [])]


def baselines(jobs, records: dict, metrics) -> list[dict]:
    """The noisy input's and OIDN's mean and interval in each metric, at each spp the models read."""
    out = []
    for j in jobs:
        if j.kind == "baseline" and j.name in records:
            ev = records[j.name]["evaluation"]
            out.append({"label": j.label, "spp": j.spp, **{m: {"mean": ev["mean"].get(m), "ci95": ev["ci95"].get(m)}
                                                           for m in metrics}})
    return out


def analyse(scfg, jobs, records: dict, targets: dict, costs: dict | None = None,
            suite_cases: dict | None = None, real_scenes: dict | None = None) -> dict:
    """The study's numbers from its jobs and their records (module docstring); ``suite_cases`` (frame index
    -> case tag of the hard-case suite) for the hard-case share axis (:mod:`studies.hard_share`);
    ``real_scenes`` (filter -> each real-scene suite frame's scene) for the realism axis
    (:mod:`studies.realism`)."""
    held = heldout_frames(records)
    clips = held["clip"]
    labels = [lab for lab, _ in scfg.model_plans()] if scfg.subsets else []
    metrics = list(scfg.metrics) + [m for m in targets if m not in scfg.metrics]
    models = {}
    for label in labels:
        curves = {m: model_curve(jobs, records, label, m, clips, scfg.resamples) for m in metrics}
        models[label] = {"curves": curves, "verdict": verdict(label, scfg.metrics[0], curves[scfg.metrics[0]]),
                         "verdicts": {m: verdict(label, m, c) for m, c in curves.items()}}
    v = scfg.variety_plan()
    variety = [variety_matrix(jobs, records, lab, m, held) for lab in (v["models"] if v else []) for m in scfg.metrics]
    answers = [target_answer(lab, m, t, models[lab]["curves"][m]) for m, t in targets.items()
               for lab in labels if m in models[lab]["curves"]]
    if costs:
        price(answers, costs)
    runs = [{"name": j.name, "model": j.label, "kind": j.kind, "seed": j.seed, "frames": j.frames,
             "clips": len(j.clips), "share": j.share, "family": j.family, "level": j.level,
             "seconds": records[j.name].get("seconds"),
             "cpu_seconds": records[j.name].get("cpu_seconds"),
             "mean": records[j.name]["evaluation"]["mean"], "ci95": records[j.name]["evaluation"]["ci95"]}
            for j in jobs if j.name in records]
    return {"heldout": {"frames": len(clips), "clips": len(set(clips)),
                        "families": {f: held["family"].count(f) for f in sorted(set(held["family"]))}},
            "metrics": metrics, "models": models, "variety": variety, "baselines": baselines(jobs, records, metrics),
            "hard_share": analyse_shares(scfg, jobs, records, suite_cases or {}),
            "realism": analyse_realism(scfg, jobs, records, real_scenes or {}),
            "targets": answers, "costs": costs, "runs": runs}


# --------------------------------------------------------------------------------------------
# scaling.md


def _bytes(n: float) -> str:
    for unit, k in (("GiB", 2 ** 30), ("MiB", 2 ** 20), ("KiB", 2 ** 10)):
        if n >= k:
            return f"{n / k:.1f} {unit}"
    return f"{n:.0f} B"


def sizes_markdown(model: dict, metrics) -> list[str]:
    """A model's table: one row a training-set size, per metric the mean over seeds, the seeds' range,
    the 95% interval and the paired change from the next smaller set."""
    head = "| frames | seeds | " + " | ".join(
        f"{NAMES[m]} | seeds' range | 95% | Δ from the smaller set" for m in metrics) + " |"
    lines = [head, "|---|---|" + "---|---|---|---|" * len(metrics)]
    first = model["curves"][metrics[0]]["sizes"]
    for i, row in enumerate(first):
        cells = [str(row["n"]), ", ".join(map(str, row["seeds"]))]
        for m in metrics:
            c = model["curves"][m]
            r, f = c["sizes"][i], FORMATS[m]
            step = c["steps"][i - 1] if i else None
            cells += [_fmt(r["mean"], f), f"{_fmt(r['seed_min'], f)}–{_fmt(r['seed_max'], f)}",
                      _interval(r["ci95"], f),
                      difference_cell(step, "{:+.4g}", -sign_of(m)) if step and "mean" in step else "–"]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def fits_markdown(models: dict, metrics) -> list[str]:
    lines = ["| model | metric | a | b (95%) | c: floor or ceiling (95%) | supported |", "|---|---|---|---|---|---|"]
    for label, mod in models.items():
        for m in metrics:
            c = mod["curves"][m]
            fit, sup, f = c["fit"], c["support"], FORMATS[m]
            if fit is None:
                lines.append(f"| {label} | {NAMES[m]} | – | – | – | no: {sup['reason']} |")
                continue
            b_text = f"{fit['b']:.2f} {_interval(fit['ci95']['b'], '{:.2f}')}"
            lines.append(f"| {label} | {NAMES[m]} | {fit['a']:.4g} | {b_text}"
                         f" | {limit_name(m)} {_fmt(fit['c'], f)} {_interval(fit['ci95']['c'], f)} | "
                         + ("yes" if sup["supported"] else f"no: {sup['reason']}") + " |")
    return lines


def variety_markdown(mat: dict) -> list[str]:
    m, f = mat["metric"], FORMATS[mat["metric"]]
    cols = mat["evaluated_on"]
    counts = {ev: mat["rows"][0]["cells"][ev]["frames"] for ev in cols} if mat["rows"] else {}
    lines = [f"{mat['model']}, {NAMES[m]} (rows: trained on; columns: held-out frames of each family):", "",
             "| trained on | frames | " + " | ".join(f"{ev} ({counts.get(ev, 0)})" for ev in cols) + " |",
             "|---|---|" + "---|" * len(cols)]
    for row in mat["rows"]:
        cells = []
        for ev in cols:
            cell = row["cells"][ev]
            text = f"{_fmt(cell['mean'], f)} {_interval(cell['ci95'], f)}"
            if cell.get("vs_both"):
                text += f"; vs both {difference_cell(cell['vs_both'], '{:+.4g}', -sign_of(m))}"
            cells.append(text)
        lines.append(f"| {row['trained_on']} | {', '.join(map(str, row['frames']))} | " + " | ".join(cells) + " |")
    return lines + [""]


def targets_markdown(answers: list[dict], costs: dict | None) -> list[str]:
    lines = []
    for a in answers:
        head = f"- **{a['model']}**, {NAMES[a['metric']]} {a['target']:g}: "
        if "refused" in a:
            lines.append(head + "refused: " + a["refused"])
            continue
        ci = a["ci95"] or [math.nan, math.nan]
        rng = f"[{ci[0]:.0f}, {'more than any number' if not math.isfinite(ci[1]) else f'{ci[1]:.0f}'}]"
        text = head + f"{a['frames']:.0f} frames {rng}"
        if a.get("beyond_measured"):
            text += " (beyond the largest set measured: an extrapolation of the fit)"
        if a.get("cost"):
            c = a["cost"]
            text += (f"; rendering them: {c['core_hours']:.2f} core-hours ({c['wall_hours']:.2f} h on "
                     f"{costs['workers']} worker(s)), a store of {_bytes(c['store_bytes'])}")
        lines.append(text)
    return lines


def budget_line(label: str, cfg) -> str:
    settings = f" {cfg.model_cfg}" if cfg.model_cfg else ""
    return (f"- **{label}**: model `{cfg.model}`{settings}, {cfg.steps} steps of batch {cfg.batch}, crop "
            f"{cfg.crop or 'default'}, {cfg.spp} spp, loss {cfg.loss}, lr {cfg.lr:g}")


def intro_markdown(result: dict, scfg) -> list[str]:
    """What was run: the stores, the axes and how the figures are made."""
    held, plan = result["heldout"], result["plan"]
    fams = ", ".join(f"{n} {f or 'unknown'}" for f, n in held["families"].items())
    text = (f"Training store `{result['stores']['train']}`: {plan['training_frames']} frames in "
            f"{plan['training_clips']} clips. Held out: `{result['stores']['heldout']}`, {held['frames']} frames in "
            f"{held['clips']} clips ({fams}), rendered from other seeds")
    if result["stores"].get("hard_cases"):
        text += f", and the hard-case suite `{result['stores']['hard_cases']}` (seeds no training config draws)"
    if result["stores"].get("real_scenes"):
        text += (", and the real-scene suite (" + ", ".join(f"`{p}` ({f} filter)" for f, p in
                                                           result["stores"]["real_scenes"].items()) +
                 "; scene files no generator wrote). The realism axis' levels train on the same scenes with one "
                 "property added: " + ", ".join(f"`{lv}` (`{p}`)" for lv, p in result["stores"]["levels"].items()))
    h, rz = scfg.hard_share_plan(), scfg.realism_plan()
    seeds = sorted(set(scfg.seeds if scfg.subsets or scfg.variety else []) | set(h["seeds"] if h else [])
                   | set(rz["seeds"] if rz else []))
    text += (f". Seeds {', '.join(map(str, seeds))}; every run is evaluated on all the held-out frames. A "
             "figure is the mean over its seeds; the 95% interval is a bootstrap over the held-out clips of the "
             "seeds-averaged per-frame values; Δ is a paired per-frame difference (\"better\"/\"worse\" where its "
             "interval excludes 0).")
    if scfg.subsets:
        text += (" The size axis: each model trains for the same steps on nested subsets of the training clips "
                 "(clips whole; each seed draws its own nested order); \"seeds' range\" spans the runs' means and "
                 "Δ is the change from the next smaller set.")
    return [f"# What the data buys: `{scfg.name}`", "", text, ""]


def curves_markdown(result: dict, metrics) -> list[str]:
    """The size axis: verdicts, the figure, each model's table and the fits (nothing without the axis)."""
    if not result["models"]:
        return []
    lines = ["## Verdicts", "", *[f"- {m['verdict']}" for m in result["models"].values()], "",
             "![error against training frames](scaling.png)", ""]
    for label, mod in result["models"].items():
        lines += [f"## {label}", "", *sizes_markdown(mod, metrics), "",
                  *[f"- {mod['verdicts'][m]}" for m in metrics[1:]], ""]
    return lines + ["## The fit: error(N) = a N^(-b) + c", "",
                    "Least squares over every run's mean (N: training frames; for PSNR and SSIM, c - a N^(-b): c is "
                    "a ceiling); 95% intervals from refits on resamples of the held-out clips and of each size's "
                    "seeds. A fit is used only where the largest set is shown better than the smallest.", "",
                    *fits_markdown(result["models"], metrics), ""]


def report_markdown(result: dict, scfg) -> str:
    """``scaling.md``: what was run, the verdicts, the figure, each model's table, the fits, the baselines,
    the hard-case share axis, the cross-family matrix and the targets."""
    metrics = result["metrics"]
    lines = intro_markdown(result, scfg) + ["## Budgets", "", *[budget_line(lab, cfg) for lab, cfg in
                                                                 scfg.model_plans()], ""]
    lines += curves_markdown(result, metrics)
    if result["baselines"]:
        def cell(b, m):
            return f"{_fmt(b[m]['mean'], FORMATS[m])} {_interval(b[m]['ci95'], FORMATS[m])}"
        lines += ["## Baselines on the same held-out frames", "",
                  "| method | " + " | ".join(NAMES[m] + " (95%)" for m in metrics) + " |",
                  "|---|" + "---|" * len(metrics),
                  *[f"| {b['label']} | " + " | ".join(cell(b, m) for m in metrics) + " |" for b in result["baselines"]],
                  ""]
    lines += share_markdown(result.get("hard_share") or [])
    lines += realism_markdown(result.get("realism") or [])
    if result["variety"]:
        lines += ["## Scene variety: one family against both", "",
                  "The same number of training frames from one scene family, or from both (half each), evaluated "
                  "on each family of the held-out frames; \"vs both\" is the paired difference from training on "
                  "both (method minus both).", "", *[ln for mat in result["variety"] for ln in variety_markdown(mat)]]
    if result["targets"]:
        c = result["costs"]
        lines += ["## Frames for a target", ""]
        if c:
            measured = c.get("measured_core_hours_per_frame")
            lines += [f"Rendering cost by `pipeline estimate`'s calibration of `{c['dataset']}` on this machine: "
                      f"{c['core_hours_per_frame'] * 3600:.1f} core-seconds and {_bytes(c['bytes_per_frame'])} a frame"
                      + (f" (the training store's own frames took {measured * 3600:.1f} core-seconds a frame)"
                         if measured else "") + ".", ""]
        lines += targets_markdown(result["targets"], c) + [""]
    run_s = sum(r["seconds"] or 0.0 for r in result["runs"])
    lines += ["## Provenance", "", f"{len(result['runs'])} runs and baseline evaluations ({run_s / 60:.1f} min of "
              f"training and evaluation, summed over the runs); {result['seconds']:.0f} s for the command that wrote "
              "this. The config, "
              "the subsets drawn (clip ids by seed), every run's means and the code's version are in "
              "[scaling.json](scaling.json).", ""]
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# scaling.png and the files


def plot_scaling(result: dict, path) -> None:
    """Error against training frames (log x), one panel a metric, one line a model: the mean over seeds
    with the seeds' range as a band, the fit dashed where the points support one, its floor (ceiling)
    dotted. relMSE on a log axis."""
    from training.report import pyplot
    plt = pyplot()
    metrics = result["metrics"]
    fig, axes = plt.subplots(1, len(metrics), figsize=(5.2 * len(metrics), 4.2), dpi=100, squeeze=False)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, m in zip(axes[0], metrics):
        for k, (label, mod) in enumerate(result["models"].items()):
            c, col = mod["curves"][m], colors[k % len(colors)]
            if not c["sizes"]:
                continue
            n = np.array([s["n"] for s in c["sizes"]], np.float64)
            ax.fill_between(n, [s["seed_min"] for s in c["sizes"]], [s["seed_max"] for s in c["sizes"]], color=col,
                            alpha=0.2, linewidth=0)
            fitted = c["fit"] is not None and c["support"]["supported"]
            ax.plot(n, [s["mean"] for s in c["sizes"]], "o-", color=col, label=label + ("" if fitted else " (no fit)"))
            if fitted:
                f = c["fit"]
                x = np.geomspace(n.min(), n.max() * 4, 100)
                ax.plot(x, power_law(x, f["a"], f["b"], f["c"], sign_of(m)), "--", color=col, linewidth=1)
                ax.axhline(f["c"], color=col, linestyle=":", linewidth=1)
        _plain_log_axes(ax, m == "relmse", sorted({s["n"] for mod in result["models"].values()
                                                    for s in mod["curves"][m]["sizes"]}))
        ax.set_xlabel("training frames")
        ax.set_ylabel(NAMES[m] + (" (lower is better)" if sign_of(m) > 0 else " (higher is better)"))
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8, loc="best")
    fig.suptitle("mean over seeds (band: their range); fit dashed; floor or ceiling dotted", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _plain_log_axes(ax, log_y: bool, ticks) -> None:
    """Log x with the sizes as plain-number ticks (and log y, plain numbers, for relMSE)."""
    from matplotlib.ticker import FuncFormatter, NullFormatter

    from training.report import plain_log_ticks
    ax.set_xscale("log")
    if ticks:
        ax.set_xticks(ticks)
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.xaxis.set_minor_formatter(NullFormatter())
    if log_y:
        ax.set_yscale("log")
        plain_log_ticks(ax.yaxis)


def _plain_result(result: dict) -> dict:
    """``result`` without the bootstrap samples (kept in memory only)."""
    out = dict(result)
    out["models"] = {lab: {**mod, "curves": {m: {**c, "fit": None if c["fit"] is None else
                                                 {k: v for k, v in c["fit"].items() if k != "samples"}}
                                             for m, c in mod["curves"].items()}}
                     for lab, mod in result["models"].items()}
    return out


def write_report(out, result: dict, scfg) -> None:
    """``scaling.json``, ``scaling.md`` and ``scaling.png`` in ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if result["models"]:                        # the size axis' curves (a study of other axes has none)
        plot_scaling(result, out / "scaling.png")
    (out / "scaling.md").write_text(report_markdown(result, scfg))
    write_json(out / "scaling.json", _plain_result(result))
