"""The real-scene table: every trained run, its own noisy input and OIDN on stores of scene files no one
here generated (the held-out suite of ``configs/real-scenes.yaml``, or a user's folder).

``python -m training real-scenes --store STORE [--store STORE ...] --runs RUN... --out DIR`` (``make
real-scenes``) and ``python -m training report ... --real-scenes STORE`` evaluate each run (at its training
spp and input kind, recurrent models clip by clip: ``training.hardcases.evaluate_frames``), and the noisy
``input`` and ``oidn`` at each (spp, input kind) the runs use, on every frame of each store. Per scene
(the file a frame was rendered from, ``stores.protocol.scene_files``) and over all of the store's frames:

- each method's mean relMSE and PSNR (tone-mapped) with 95% intervals (a bootstrap over the frames'
  views, each view a clip);
- each method against **its own noisy input** (the ``input`` at its spp and input kind) and against
  **OIDN at the same spp and input**: paired differences of relMSE and PSNR with their intervals and a
  verdict (better / worse / no difference shown), and the ratio of its mean relMSE to OIDN's;
- each method's mean radiance over the reference's (``mean_ratio``), with its interval: a denoiser that
  darkens or brightens the image shows here.

It writes ``DIR/real-scenes.md`` and ``DIR/real-scenes.json`` (``real-scenes-<store name>`` with several
stores share the folder).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from . import stats
from .checkpoint import find_runs
from .data import open_store
from .errors import ConfigError
from .evaluate import baseline_groups
from .hardcases import VERDICT_MARK, against_input, baselines_of, case_cell, evaluate_frames, link_inputs
from .jsonio import write

ALL = "(all)"


def frame_scenes(st) -> list[str]:
    """Each frame's scene: its file's name without the folder and ``.xml`` (a generated scene: its family)."""
    from stores.protocol import scene_files, scene_kinds
    files, kinds = scene_files(st), scene_kinds(st)
    return [Path(f).stem if f else (k or "generated") for f, k in zip(files, kinds)]


def link_oidn(evals: list[dict]) -> None:
    """Each model's ``oidn_label``: the ``oidn`` evaluation at its spp and baseline input."""
    oidn = baselines_of(evals, "oidn")
    for e in evals:
        if e.get("method") not in ("input", "oidn"):
            e["oidn_label"] = oidn.get(e["label"])


def against(rows: list[dict], base: list[dict], label: str) -> dict:
    """:func:`training.hardcases.against_input` against any baseline's rows, with the ratio of the mean
    relMSEs (method over baseline) on the shared frames."""
    out = against_input(rows, base, label)
    by = {int(r["index"]): r["relmse"] for r in base}
    mine = [r["relmse"] for r in rows if int(r["index"]) in by]
    theirs = [by[int(r["index"])] for r in rows if int(r["index"]) in by]
    out["relmse_ratio"] = float(np.mean(mine) / np.mean(theirs)) if mine and np.mean(theirs) > 0 else None
    return out


def _cell(rows: list[dict]) -> dict:
    cell = case_cell(rows)
    clips = [r.get("clip", r["index"]) for r in rows]
    ratios = [r["mean_ratio"] for r in rows if "mean_ratio" in r]
    cell["mean_ratio"] = float(np.mean(ratios)) if ratios else None
    cell["mean_ratio_ci95"] = stats.mean_ci(ratios, clips) if ratios else None
    return cell


def summarize(evals: list[dict], scenes: list[str]) -> dict:
    """Per scene (and ``(all)``) and method: :func:`_cell` (means with intervals, finiteness, mean ratio),
    ``vs_input`` and ``vs_oidn`` (:func:`against`) where the method names its input and OIDN."""
    names = [ALL] + list(dict.fromkeys(scenes))
    table: dict = {n: {} for n in names}
    rows_of: dict = {}
    for ev in evals:
        by: dict = {ALL: list(ev["frames"])}
        for r in ev["frames"]:
            by.setdefault(scenes[int(r["index"])], []).append(r)
        rows_of[ev["label"]] = by
        for n, rows in by.items():
            table[n][ev["label"]] = _cell(rows)
    for ev in evals:
        for key, base in (("vs_input", ev.get("input_label")), ("vs_oidn", ev.get("oidn_label"))):
            for n, rows in rows_of[ev["label"]].items():
                if base and n in rows_of.get(base, {}):
                    table[n][ev["label"]][key] = against(rows, rows_of[base][n], base)
    return {"methods": [e["label"] for e in evals], "scenes": table,
            "methods_info": {e["label"]: {k: e.get(k) for k in ("method", "spp", "input_kind", "input_label",
                                                                  "oidn_label")} for e in evals}}


def _ci(ci, fmt: str) -> str:
    return f" [{ci[0]:{fmt}}, {ci[1]:{fmt}}]" if ci else ""


def _value_cell(v: dict | None) -> str:
    if not v:
        return "–"
    if not v["finite"]:
        return "**non-finite**"
    p = v["psnr"]
    ps = "inf" if not np.isfinite(p) else f"{p:.2f}{_ci(v.get('psnr_ci95'), '.2f')}"
    return f"{v['relmse']:.4g}{_ci(v.get('relmse_ci95'), '.3g')} / {ps}"


def _diff_cell(d: dict | None, ratio: bool = False) -> str:
    if not d:
        return "–"
    if d["verdict"] in ("exact", "not exact"):
        return VERDICT_MARK[d["verdict"]]
    r, p = d.get("relmse"), d.get("psnr")
    rs = f"{r['mean']:+.3g}{_ci(r['ci95'], '+.3g')}" if r else "–"
    ps = f"{p['mean']:+.2f}{_ci(p['ci95'], '+.2f')}" if p else "–"
    extra = f" ({d['relmse_ratio']:.2f}x)" if ratio and d.get("relmse_ratio") is not None else ""
    return f"{rs} / {ps}{extra}: {VERDICT_MARK[d['verdict']]}"


def markdown(res: dict) -> str:
    """The tables: values per scene and method; each model against its input and against OIDN; mean ratios."""
    methods, scenes = res["methods"], res["scenes"]
    models = [m for m in methods if res["methods_info"][m].get("input_label")]
    lines = ["| scene | " + " | ".join(methods) + " |", "|---|" + "---|" * len(methods)]
    for n, row in scenes.items():
        lines.append(f"| {n} | " + " | ".join(_value_cell(row.get(m)) for m in methods) + " |")
    lines += ["", "Cells: mean relMSE / PSNR (dB, tone-mapped) with 95% intervals (a bootstrap over the views).", ""]
    for key, what, ratio in (("vs_input", "its own noisy input (the `input` at its spp and input kind)", False),
                             ("vs_oidn", "OIDN at its spp and input kind; in brackets its relMSE over OIDN's", True)):
        shown = [m for m in models if any(key in scenes[n].get(m, {}) for n in scenes)]
        if not shown:
            continue
        lines += [f"Against {what}: ΔrelMSE / ΔPSNR, method minus baseline, with 95% intervals; better: relMSE "
                  "lower and PSNR higher, both intervals excluding 0.", "",
                  "| scene | " + " | ".join(shown) + " |", "|---|" + "---|" * len(shown)]
        for n, row in scenes.items():
            lines.append(f"| {n} | " + " | ".join(_diff_cell((row.get(m) or {}).get(key), ratio) for m in shown) + " |")
        lines.append("")
    lines += ["Mean radiance over the reference's (1: the image keeps its energy), with 95% intervals:", "",
              "| scene | " + " | ".join(methods) + " |", "|---|" + "---|" * len(methods)]
    for n, row in scenes.items():
        cells = [f"{v['mean_ratio']:.3f}{_ci(v.get('mean_ratio_ci95'), '.3f')}" if v and v.get("mean_ratio") is not None
                 else "–"
                 for v in (row.get(m) for m in methods)]
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def evaluate_store(run_dirs, store, *, oidn: bool = True, max_frames: int = 0, progress: bool = True) -> dict:
    """Every run, the input and OIDN (at each spp and input kind the runs use) on ``store``:
    :func:`summarize` plus the store's path, render settings (the pixel filter) and ``markdown``."""
    st = open_store(store)
    evals = [evaluate_frames(d / "checkpoint.pt", st, label=d.name, max_frames=max_frames, progress=progress)
             for d in run_dirs]
    for name in ("input",) + (("oidn",) if oidn else ()):
        for n, b, tag in baseline_groups(evals, st.layout.spp):
            evals.append(evaluate_frames(name, st, label=name + tag, spp=n, baseline_input=b, max_frames=max_frames,
                                         progress=progress))
    link_inputs(evals)
    link_oidn(evals)
    res = summarize(evals, frame_scenes(st))
    render = (st.config or {}).get("render") or {}
    res.update(store=str(st.path), filter=render.get("filter", "box"), frames={e["label"]: e["frames"] for e in evals})
    res["markdown"] = markdown(res)
    return res


def real_scene_report(runs, stores, out, *, oidn: bool = True, max_frames: int = 0, progress: bool = True) -> list:
    """:func:`evaluate_store` of every store in ``stores``; writes ``out/real-scenes.md`` and ``.json``."""
    run_dirs = find_runs(runs)
    if runs and not run_dirs:
        raise ConfigError(f"none of the runs {list(map(str, runs))} holds a checkpoint.pt")
    results = [evaluate_store(run_dirs, s, oidn=oidn, max_frames=max_frames, progress=progress) for s in stores]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "real-scenes.md").write_text("\n\n".join(section(r) for r in results) + "\n")
    write(out / "real-scenes.json", [{k: v for k, v in r.items() if k != "markdown"} for r in results])
    return results


def section(r: dict) -> str:
    return f"## Real scenes: `{r['store']}` ({r['filter']} pixel filter)\n\n{r['markdown']}"


def real_scenes_cli(a) -> int:
    """``python -m training real-scenes`` (arguments from ``training.__main__``)."""
    if a.frames is not None and a.frames < 0:
        raise ConfigError(f"--frames must be >= 0, got {a.frames}")
    results = real_scene_report(a.runs or [], a.store, a.out, oidn=not a.no_oidn, max_frames=a.frames or 0)
    for r in results:
        print(section(r) + "\n")
    print(f"wrote {a.out}/real-scenes.md and {a.out}/real-scenes.json")
    return 0
