"""Markdown report of trained runs against the noisy input and OIDN on held-out frames.

``report(runs, store, out)`` writes ``out/report.md`` (quality/speed table, figure-10 FMA table,
training budgets), ``out/speed_vs_error.png`` (ms per megapixel at 128x128 against relMSE, both log),
``out/crops.png`` (input / each model / OIDN / reference, tone-mapped), ``out/sample_map-<run>.png``
for adaptive samplers (where the samples went), ``out/eval-<name>.json`` and ``out/comparisons.json``.
Every method is compared with its own noisy input (at its spp and input kind), or with one method
(``--baseline``), as a paired per-frame difference with its 95% interval (a bootstrap over clips, :mod:`training.stats`), "no difference shown"
where the interval holds 0 and "no interval (one clip)" where it cannot be known; runs that differ only
in their training seed get their spread. Figures: matplotlib.
"""
from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from . import checkpoint as ckpt
from . import stats
from .checkpoint import find_runs
from .errors import DataError
from .data import open_store
from .evaluate import FIREFLY_RATIO, FIREFLY_SHARE, baseline_groups, evaluate, frame_kinds, write_json
from .fma import figure10, figure10_markdown
from .hardcases import baselines_of, hard_case_report
from .jsonio import write as write_strict
from core.images import tonemap

# Inference is timed on one BENCH_SIZE x BENCH_SIZE frame, the size of `python -m training bench`: on a
# store's own small frames (32x32 for the default dataset) fixed costs per call dominate (nbg read 9,090
# ms/MP there and OIDN 4,390, while at 128x128 nbg is about twice as fast as OIDN).
BENCH_SIZE = 128
SPEED = "speed_ms_per_mp"           # the table's time column: ``result["speed"]["ms_per_mp"]``
INTERVALS = ("relmse", "smape", "psnr", "ssim", "flip", "tpsnr")     # the figures whose means get an interval
COLUMNS = (("relmse", "relMSE ↓", "{:.4f}"), ("smape", "SMAPE ↓", "{:.4f}"), ("psnr", "PSNR ↑", "{:.2f}"),
           ("ssim", "SSIM ↑", "{:.4f}"), ("flip", "FLIP ↓", "{:.4f}"), ("tpsnr", "tPSNR ↑", "{:.2f}"),
           ("spp", "spp", "{:.2f}"), (SPEED, f"ms/MP @{BENCH_SIZE}² ↓", "{:.0f}"))


def _fmt(v, f):
    return "–" if v is None or (isinstance(v, float) and math.isnan(v)) else f.format(v)


def _with_ci(v, ci, f) -> str:
    """A mean and, where it has one, its 95% interval: ``0.0123 [0.0101, 0.0150]``."""
    text = _fmt(v, f)
    if not ci or text == "–":
        return text
    return f"{text} [{_fmt(ci[0], f)}, {_fmt(ci[1], f)}]"


def table_markdown(results: list[dict]) -> str:
    head = "| method | " + " | ".join(c[1] for c in COLUMNS) + " | params | FMAs/pixel |"
    lines = [head, "|---|" + "---|" * (len(COLUMNS) + 2)]
    for r in results:
        m = {**r["mean"], SPEED: (r.get("speed") or {}).get("ms_per_mp")}
        ci = r.get("ci95") or {}
        cells = [_with_ci(m.get(k), ci.get(k) if k in INTERVALS else None, f) for k, _, f in COLUMNS]
        fm = r.get("fmas_per_pixel")
        lines.append(f"| {r['label']} | " + " | ".join(cells) +
                     f" | {r.get('params', 0):,} | {'–' if fm is None else f'{fm / 1e3:.0f}k'} |")
    return "\n".join(lines)


def distinct_kinds(by_kind: dict) -> dict[str, list[str]]:
    """The kinds of an evaluation's ``by_kind`` whose frames no earlier kind has exactly, each with the
    kinds that repeat it (defocus and motion where every indoor frame has both): kind -> [repeats]."""
    out: dict[str, list[str]] = {}
    for k, agg in by_kind.items():
        same = agg.get("same_as")
        if same in out:
            out[same].append(k)
        else:
            out[k] = []
    return out


def kinds_markdown(results: list[dict], key: str = "relmse", fmt: str = "{:.4f}") -> str:
    """Mean ``key`` per method, with its 95% interval, over the frames of each kind (defocus, motion,
    fireflies, plain; a frame may have several kinds), with the frame counts in the header; a kind whose
    frames are exactly an earlier one's is named in that one's header, not repeated as a column."""
    kinds = distinct_kinds(results[0].get("by_kind", {}))   # evaluate's order: scene families, then hard parts
    counts = {k: results[0]["by_kind"][k]["frames"] for k in kinds}
    head = "| method | all | " + " | ".join(
        f"{k} ({counts[k]}{'; also ' + ', '.join(rep) if rep else ''})" for k, rep in kinds.items()) + " |"
    lines = [head, "|---|---|" + "---|" * len(kinds)]
    for r in results:
        cells = [_with_ci(r["mean"].get(key), (r.get("ci95") or {}).get(key), fmt)] + [
            _with_ci(r["by_kind"][k].get(key), (r["by_kind"][k].get("ci95") or {}).get(key), fmt) for k in kinds]
        lines.append(f"| {r['label']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def reference_note(results: list[dict]) -> list[str]:
    """A line on what the references' own noise lets the metrics resolve (``evaluate``'s ``reference``)."""
    ref = next((r["reference"] for r in results if r.get("reference")), None)
    if not ref:
        return []
    return [f"The references are Monte Carlo estimates too: scoring the true image against them would give PSNR "
            f"{ref['psnr_ceiling_median']:.1f} dB (median over frames; lowest {ref['psnr_ceiling_lowest']:.1f} dB) "
            f"and relMSE {ref['relmse_floor_median']:.2g} (highest {ref['relmse_floor_highest']:.2g}), from their "
            "stored standard error. Differences near or beyond these limits are not resolved by this data.", ""]


def pyplot():
    import matplotlib
    matplotlib.use("Agg")                       # files only, no display
    import matplotlib.pyplot as plt
    return plt


def plain_log_ticks(axis) -> None:
    """Ticks of a log axis as plain numbers (0.05, 2, 300) at 1, 2 and 5 times the powers of ten."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter
    axis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    axis.set_minor_formatter(NullFormatter())


def speed_of(r: dict) -> float | None:
    """A method's ms per megapixel at :data:`BENCH_SIZE` (:func:`time_at_bench_size`; None: not timed)."""
    v = (r.get("speed") or {}).get("ms_per_mp")
    return float(v) if v is not None and math.isfinite(v) and v > 0 else None


def plot_speed_vs_error(results: list[dict], path, decades: float = 4.0) -> None:
    """ms per megapixel at :data:`BENCH_SIZE` (log x) against relMSE (log y), one marker per method with
    its 95% interval as an error bar; a method without a time (the noisy input) is a horizontal line in a
    band of its interval. The y range spans the methods within
    ``decades`` of the lowest relMSE: one far above (a model early in training) is drawn on the top edge
    as an upward triangle, and one that cannot be drawn on a log axis (NaN, infinite, 0) is named in the
    legend, each with its value."""
    plt = pyplot()
    from matplotlib.lines import Line2D
    vals = [float(r["mean"].get("relmse", math.nan)) for r in results]
    ok = [v for v in vals if math.isfinite(v) and v > 0]
    lo = min(ok) if ok else 1e-3
    top = min(max(ok), lo * 10 ** decades) if ok else 1.0
    fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=100)
    markers, extra = "osDphXP*<>", []       # no "^": an upward triangle marks a method above the plot
    for i, (r, v) in enumerate(zip(results, vals)):
        x, label = speed_of(r), r["label"]
        colour, above = f"C{i % 10}", f"relMSE {v:.3g}: above the plot"
        ci = (r.get("ci95") or {}).get("relmse")
        ci = ci if ci and all(math.isfinite(c) and c > 0 for c in ci) else None
        if not (math.isfinite(v) and v > 0):
            extra.append(Line2D([], [], linestyle="", marker="x", color="grey",
                                label=f"{label} (relMSE {v}: not plotted)"))
        elif x is None:
            ax.axhline(min(v, top), linestyle="--", linewidth=1, color=colour,
                       label=f"{label} (no time{'; ' + above if v > top else ''})")
            if ci and v <= top:
                ax.axhspan(max(ci[0], lo / 1.6), min(ci[1], top * 1.6), color=colour, alpha=0.12, linewidth=0)
        elif v > top:
            ax.scatter([x], [top], s=60, marker="^", color=colour, label=f"{label} ({above})")
        else:
            ax.scatter([x], [v], s=36, marker=markers[i % len(markers)], color=f"C{i % 10}", label=label)
            if ci:                  # its 95% interval (a bootstrap over the held-out clips)
                ax.errorbar([x], [v], yerr=[[v - max(ci[0], lo / 1.6)], [min(ci[1], top * 1.6) - v]], fmt="none",
                            ecolor=colour, elinewidth=1, capsize=3)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_ylim(lo / 1.6, top * 1.6)
    plain_log_ticks(ax.xaxis)
    plain_log_ticks(ax.yaxis)
    handles, labels = ax.get_legend_handles_labels()
    if handles or extra:
        ax.legend(handles=handles + extra, fontsize=7, loc="best")
    ax.set_xlabel(f"ms per megapixel at {BENCH_SIZE}x{BENCH_SIZE} (this machine)")
    ax.set_ylabel("relMSE (log)")
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def time_at_bench_size(results: list[dict], size: int = BENCH_SIZE, repeats: int = 3) -> None:
    """Give every result its ``speed``: inference on one ``size`` x ``size`` frame (``training.bench``, best
    of ``repeats`` after a warm-up, on the device and precision it was evaluated with): a model from its
    checkpoint at its spp, OIDN on a random image of that size (one timing for every spp); the noisy
    input has none. The per-frame times on the store's own frames stay in each result's frames."""
    import torch

    from .bench import others_busy, time_model, time_oidn
    oidn_row = {}
    busy = others_busy() if any(torch.device(r.get("device", "cpu")).type == "cpu" for r in results) else None
    for r in results:
        dev = torch.device(r.get("device", "cpu"))
        if r.get("checkpoint"):
            model = ckpt.build_model(ckpt.load(r["checkpoint"], map_location=str(dev)), str(dev))
            r["speed"] = time_model(model, int(r["spp"]), size, repeats, dev, r.get("precision", "fp32"))
        elif r.get("method") == "oidn":
            if str(dev) not in oidn_row:
                oidn_row[str(dev)] = time_oidn(size, repeats, dev)
            r["speed"] = oidn_row[str(dev)]
        else:
            r["speed"] = None
        if r["speed"] is not None and dev.type == "cpu":
            r["speed"]["others_busy_cores"] = busy


def crops_image(panels: list[tuple[str, np.ndarray]], path, crop: int = 64) -> None:
    """Side-by-side tone-mapped centre crops (``crop`` px, nearest-neighbour) with labels."""
    plt = pyplot()
    fig, axes = plt.subplots(1, len(panels), figsize=(1.9 * len(panels), 2.1), dpi=100, squeeze=False)
    for ax, (label, im) in zip(axes[0], panels):
        h, w = im.shape[:2]
        c = min(crop, h, w)
        y, x = (h - c) // 2, (w - c) // 2
        ax.imshow(np.clip(tonemap(im[y:y + c, x:x + c]), 0, 1), interpolation="nearest")
        ax.set_title(label, fontsize=8)
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def sample_map_image(counts: np.ndarray, reference: np.ndarray, path, title: str = "") -> None:
    """The per-pixel sample counts of an adaptive sampler (heat map, with a colour bar) next to the
    tone-mapped reference of the same frame."""
    plt = pyplot()
    fig, (a, b) = plt.subplots(1, 2, figsize=(7.0, 3.2), dpi=100)
    a.imshow(np.clip(tonemap(reference), 0, 1), interpolation="nearest")
    a.set_title("reference", fontsize=9)
    a.axis("off")
    im = b.imshow(counts, cmap="inferno", interpolation="nearest", vmin=0)
    b.set_title(f"samples per pixel (mean {counts.mean():.2f}, max {int(counts.max())})", fontsize=9)
    b.axis("off")
    fig.colorbar(im, ax=b, fraction=0.046, pad=0.04)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


PACKAGES = ("torch", "numpy", "zarr", "numcodecs", "mitsuba", "drjit", "dask", "distributed", "pyoidn",
            "scikit-image", "flip-evaluator", "matplotlib", "OpenEXR")


def provenance(run_dirs, stores: dict, args: dict) -> dict:
    """What a report's numbers come from: the command, the code (git commit), package versions, the
    machine, each store's dataset config and each run's training config and checkpoint hash."""
    import hashlib
    import platform
    import subprocess
    import sys
    import time
    from importlib import metadata

    import torch

    versions = {"python": platform.python_version()}
    for pkg in PACKAGES:
        try:
            versions[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            versions[pkg] = None
    here = Path(__file__).resolve().parent
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True,
                                timeout=10).stdout.strip() or None
        dirty = bool(subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=here,
                                    capture_output=True, text=True, timeout=10).stdout.strip())
    except (OSError, subprocess.SubprocessError):
        commit, dirty = None, None
    runs = {}
    for d in run_dirs:
        ck = ckpt.load(d / "checkpoint.pt")
        runs[str(d)] = {"model": ck["model"], "model_config": ck["model_config"], "train_config": ck["train_config"],
                        "step": ck["step"], "store": ck.get("store"),
                        "sha256": hashlib.sha256((d / "checkpoint.pt").read_bytes()).hexdigest()}
    st = {}
    for role, path in stores.items():
        if path is None:
            continue
        s = open_store(path)
        st[role] = {"path": str(path), "schema_version": s.schema_version, "config": s.config,
                    "frames": int(s.layout.num_frames)}
    return {"created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "command": list(sys.argv),
            "arguments": args, "git_commit": commit, "git_dirty": dirty, "versions": versions,
            "machine": {"platform": platform.platform(), "processor": platform.processor(),
                        "cpus": os.cpu_count(), "torch_threads": torch.get_num_threads(),
                        "cuda": torch.cuda.is_available()},
            "stores": st, "runs": runs}


def evaluate_methods(run_dirs, store, out, split: str = "test", spp: int | None = None, max_frames: int = 0,
                     with_flip: bool = True, progress: bool = True, skip_bad_frames: bool = False,
                     prefix: str = "") -> tuple[list, list, list, list]:
    """Evaluate every run at ``spp`` (None: its training spp) and the noisy input and OIDN at each
    (spp, input) pair among the runs; write ``out/<prefix>eval-<label>.json``. Returns
    ``(inputs, models, oidns, spps)``."""
    def one(label, m, at, **kw):
        if progress:
            print(f"evaluating {label} on {split} of {store} ...", flush=True)
        r = evaluate(m, store, split=split, spp=at, max_frames=max_frames, with_flip=with_flip, keep=(0,),
                     skip_bad_frames=skip_bad_frames, **kw)
        r["label"] = label
        write_json(r, out / f"{prefix}eval-{label.replace(' ', '')}.json")
        return r

    models = [one(d.name, d / "checkpoint.pt", spp) for d in run_dirs]
    groups = baseline_groups(models, open_store(store).layout.spp)
    inputs = [one(f"input{tag}", "input", n, baseline_input=b) for n, b, tag in groups]
    oidns = [one(f"oidn{tag}", "oidn", n, baseline_input=b) for n, b, tag in groups]
    return inputs, models, oidns, sorted({n for n, _, _ in groups})


# --------------------------------------------------------------------------------------------
# Comparisons with their confidence

COMPARED = (("relmse", "relMSE", "{:+.4f}", -1), ("psnr", "PSNR", "{:+.2f}", 1), ("ssim", "SSIM", "{:+.4f}", 1),
            ("flip", "FLIP", "{:+.4f}", -1), ("tpsnr", "tPSNR", "{:+.2f}", 1))   # (key, name, format, +1: higher is better)


OWN_INPUT = "its own noisy input"


def _paired_row(base: dict, r: dict) -> dict:
    clip = {f["index"]: f.get("clip", f["index"]) for f in base["frames"]}

    def per_frame(x, key):
        return {f["index"]: f[key] for f in x["frames"] if key in f}
    row = {"label": r["label"], "against": base["label"]}
    for key, *_ in COMPARED:
        if base["frames"] and key in base["frames"][0] and r["frames"] and key in r["frames"][0]:
            row[key] = stats.paired_difference(per_frame(base, key), per_frame(r, key), clip)
    if base.get("tpsnr_runs") and r.get("tpsnr_runs"):      # one value a run of a clip's frames, paired by run
        row["tpsnr"] = stats.paired_difference(base["tpsnr_runs"], r["tpsnr_runs"],
                                               {k: clip.get(int(k), int(k)) for k in base["tpsnr_runs"]})
    return row


def comparisons(results: list[dict], baseline: str | None = None) -> dict:
    """Every method against a baseline as the paired per-frame difference (method minus baseline, on the
    frames both were evaluated on) with its 95% interval, a bootstrap over clips
    (:func:`training.stats.paired_difference`): ``baseline`` None (the default): each method against its own
    noisy input (``training.hardcases.baselines_of``: the input at its spp and input kind, never a lower-spp
    one that flatters it; a method without one gets a row whose ``against`` is None); a label: every method
    against that one. ``{"baseline": label or OWN_INPUT, "rows":
    [{"label", "against", key: {"mean", "ci95", "frames", "shown"}}]}``."""
    labels = [r["label"] for r in results]
    by_label = {r["label"]: r for r in results}
    if baseline is not None and baseline not in labels:
        raise DataError(f"--baseline {baseline!r} is not one of the report's methods: {labels}")
    own = baselines_of(results, "input") if baseline is None else {}
    rows = []
    for r in results:
        if r["label"] == baseline or (baseline is None and r.get("method") == "input"):
            continue
        base = by_label.get(baseline if baseline is not None else own.get(r["label"], ""))
        rows.append(_paired_row(base, r) if base is not None else {"label": r["label"], "against": None})
    return {"baseline": baseline if baseline is not None else OWN_INPUT, "rows": rows}


def comparisons_markdown(comp: dict) -> str:
    """The paired differences as a table: ``mean [low, high]``, "no difference shown" where the
    interval holds 0, and "no interval (one clip)" where it cannot be known."""
    keys = [c for c in COMPARED if any(c[0] in r for r in comp["rows"])]
    lines = ["| method | against | " + " | ".join(f"Δ{name} (95%)" for _, name, _, _ in keys) + " |",
             "|---|---|" + "---|" * len(keys)]
    for row in comp["rows"]:
        cells = [difference_cell(row.get(key), f, better) for key, _, f, better in keys]
        against = row.get("against") or "no input at its spp and input kind"
        lines.append(f"| {row['label']} | {against} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def comparisons_by_kind(results: list[dict], baseline: str | None = None, key: str = "relmse") -> dict:
    """:func:`comparisons` of ``key`` over the frames of each kind (``evaluate.frame_kinds``; the kinds
    of the first result's ``by_kind``), each method against the same baseline as there: ``{"baseline",
    "kinds": [(kind, frames)], "rows": [{"label", "against", kind: diff}]}``."""
    comp = comparisons(results, baseline)
    by_label = {r["label"]: r for r in results}
    first = results[0]
    kinds = list(distinct_kinds(first.get("by_kind", {})))
    rows = []
    for c in comp["rows"]:
        if c["against"] is None:
            continue
        base, r = by_label[c["against"]], by_label[c["label"]]
        if not r["frames"] or key not in r["frames"][0]:
            continue
        tags = {f["index"]: frame_kinds(f) for f in base["frames"]}
        clip = {f["index"]: f.get("clip", f["index"]) for f in base["frames"]}
        row = {"label": r["label"], "against": base["label"]}
        for kind in kinds:
            a = {f["index"]: f[key] for f in base["frames"] if kind in tags[f["index"]]}
            b = {f["index"]: f[key] for f in r["frames"] if f["index"] in a}
            row[kind] = stats.paired_difference(a, b, clip)
        rows.append(row)
    return {"baseline": comp["baseline"], "kinds": [(k, first["by_kind"][k]["frames"]) for k in kinds], "rows": rows}


def difference_cell(d, f: str, better: int) -> str:
    if d is None:
        return "–"
    if d["ci95"] is None:               # the frames are of one clip: no spread between clips to see
        return f.format(d["mean"]) + " no interval (one clip)"
    text = f"{f.format(d['mean'])} [{f.format(d['ci95'][0])}, {f.format(d['ci95'][1])}]"
    if not d["shown"]:
        return text + " no difference shown"
    return text + (" better" if d["mean"] * better > 0 else " worse")


def comparisons_section(results: list[dict], baseline: str | None) -> list[str]:
    comp = comparisons(results, baseline)
    if not comp["rows"]:
        return []
    kinds = comparisons_by_kind(results, baseline)
    table = ["| method | against | " + " | ".join(f"{k} ({n})" for k, n in kinds["kinds"]) + " |",
             "|---|---|" + "---|" * len(kinds["kinds"])]
    for row in kinds["rows"]:
        table.append(f"| {row['label']} | {row['against']} | " + " | ".join(difference_cell(row[k], "{:+.4f}", -1)
                                                                           for k, _ in kinds["kinds"]) + " |")
    return [f"Each method against **{comp['baseline']}** (the column *against*), frame by frame on the same frames: "
            "the mean difference (method minus baseline) with its 95% interval, a bootstrap over the held-out clips "
            "(a still is a clip of one frame; the frames of a clip are resampled together). \"better\"/\"worse\" "
            "only where the interval excludes 0, \"no difference shown\" where it holds 0, \"no interval (one "
            "clip)\" where the frames are all of one clip.", "", comparisons_markdown(comp), "",
            f"ΔrelMSE against **{comp['baseline']}** by kind of frame (frame counts in brackets):", "",
            *table, ""]


def seed_spread(results: list[dict]) -> list[dict]:
    """Runs that differ only in their training seed, grouped: ``{"label", "seeds", key: {"mean", "std",
    "min", "max"}}`` of each metric's mean over the frames (``make compare SEEDS=N``)."""
    groups: dict[str, list[dict]] = {}
    for r in results:
        tc = r.get("train_config")
        if tc is None:
            continue
        key = json_key({**{k: v for k, v in tc.items() if k != "seed"}, "method": r["method"], "spp": r["spp"],
                        "model_config": r.get("model_config")})
        groups.setdefault(key, []).append(r)
    out = []
    for runs in groups.values():
        if len(runs) < 2:
            continue
        row = {"label": runs[0]["method"], "runs": [r["label"] for r in runs],
               "seeds": [r["train_config"].get("seed") for r in runs]}
        for key, *_ in COMPARED:
            v = [r["mean"].get(key) for r in runs]
            if all(isinstance(x, float) and math.isfinite(x) for x in v):
                row[key] = {"mean": float(np.mean(v)), "std": float(np.std(v, ddof=1)), "min": min(v), "max": max(v)}
        out.append(row)
    return out


def json_key(d: dict) -> str:
    import json
    return json.dumps(d, sort_keys=True, default=str)


def seed_spread_section(results: list[dict]) -> list[str]:
    rows = seed_spread(results)
    if not rows:
        return []
    keys = [c for c in COMPARED if any(c[0] in r for r in rows)]
    lines = ["Spread across training seeds (runs that differ only in `--seed`): mean ± standard deviation of "
             "each run's mean, and the range.", "",
             "| model | seeds | " + " | ".join(name for _, name, _, _ in keys) + " |",
             "|---|---|" + "---|" * len(keys)]
    for r in rows:
        cells = [f"{r[k]['mean']:.4g} ± {r[k]['std']:.2g} ({r[k]['min']:.4g}–{r[k]['max']:.4g})" if k in r else "–"
                 for k, *_ in keys]
        lines.append(f"| {r['label']} | {', '.join(str(s) for s in r['seeds'])} | " + " | ".join(cells) + " |")
    return lines + [""]


# --------------------------------------------------------------------------------------------
# The report


def report(runs, store, out, split: str = "test", spp: int | None = None, max_frames: int = 0,
           with_flip: bool = True, progress: bool = True, skip_bad_frames: bool = False,
           clips_store: str | None = None, hard_cases: str | None = None, baseline: str | None = None,
           real_scenes=()) -> dict:
    """Evaluate every run and the baselines; write the report files. Returns the results.

    Each run is evaluated at ``spp`` (None: the spp it was trained at, e.g. 8 for the layer family and 1
    for nbg/wskpn) and the noisy input and OIDN at every spp among the runs, so each model stands next
    to the baselines at its own sample count (labels gain ``@N spp`` when there are several).
    Every method is compared with ``baseline`` (a label; None: each with its own noisy input, at its spp
    and input kind) as a paired difference with its 95% interval (:func:`comparisons`); runs that differ
    only in their seed get their spread. :func:`other_stores` adds the sections of the clips, hard-case and
    real-scene stores. ``out/provenance.json`` records the command, code, versions, stores and runs the
    numbers come from."""
    import time
    t_start = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    run_dirs = find_runs(runs)
    if not run_dirs:
        raise DataError(f"no run directory with a checkpoint.pt among {list(runs)}")
    prov = provenance(run_dirs, {"evaluation": store, "clips": clips_store, "hard_cases": hard_cases,
                                 **{f"real_scenes_{i}": s for i, s in enumerate(real_scenes)}},
                      {"runs": [str(r) for r in runs], "store": str(store), "split": split, "spp": spp,
                       "max_frames": max_frames, "with_flip": with_flip, "skip_bad_frames": skip_bad_frames,
                       "clips_store": clips_store, "hard_cases": hard_cases, "baseline": baseline,
                       "real_scenes": [str(s) for s in real_scenes]})
    inputs, models, oidns, spps = evaluate_methods(run_dirs, store, out, split, spp, max_frames, with_flip,
                                                   progress, skip_bad_frames)
    results = inputs + models + oidns
    comparisons(results, baseline)                       # an unknown --baseline fails before the figures
    time_at_bench_size(results)
    maps = write_figures(results, models, store, out)
    lines = main_section(results, store, split, spps, maps, baseline)
    extra = {"comparisons": comparisons(results, baseline), "comparisons_by_kind": comparisons_by_kind(results, baseline),
             "seed_spread": seed_spread(results), "speed": {r["label"]: r["speed"] for r in results}}
    more, found = other_stores(run_dirs, results, out, spp=spp, max_frames=max_frames, with_flip=with_flip,
                               progress=progress, skip_bad_frames=skip_bad_frames, baseline=baseline,
                               clips_store=clips_store, hard_cases=hard_cases, real_scenes=real_scenes)
    lines += more
    extra.update(found)
    fig10 = figure10()
    lines += budgets_section(results) + ["## FMAs against samples per pixel (figure 10, billions per 1920x1080 frame, "
                                         "paper defaults)", "", figure10_markdown(fig10), ""]
    prov["report_seconds"] = round(time.perf_counter() - t_start, 1)
    write_strict(out / "provenance.json", prov)
    lines += provenance_section(prov)
    (out / "report.md").write_text("\n".join(lines))
    write_strict(out / "comparisons.json", extra)
    return {"results": [{k: v for k, v in r.items() if k != "images"} for r in results], "figure10": fig10,
            **extra}


def other_stores(run_dirs, results: list[dict], out: Path, *, spp, max_frames: int, with_flip: bool, progress: bool,
                 skip_bad_frames: bool, baseline, clips_store=None, hard_cases=None, real_scenes=()) -> tuple[list, dict]:
    """The report's sections beyond its store, and their JSON: ``clips_store`` (everything on the ``test``
    split of a store of moving clips: tPSNR), ``hard_cases`` (a store of ``configs/hard-cases.yaml``, case by
    case: :mod:`training.hardcases`), ``real_scenes`` (stores of scene files, scene by scene against each
    method's input and OIDN: :mod:`training.realscenes`)."""
    lines, extra = [], {}
    if clips_store is not None:
        clip_results = sum(evaluate_methods(run_dirs, clips_store, out, "test", spp, max_frames, with_flip, progress,
                                            skip_bad_frames, prefix="clips-")[:3], [])
        speeds = {r["label"]: r["speed"] for r in results}      # the same methods: timed once
        for r in clip_results:
            r["speed"] = speeds.get(r["label"])
        lines += clips_section(clip_results, clips_store, out, baseline)
        extra["clips"] = [{k: v for k, v in r.items() if k != "images"} for r in clip_results]
        extra["clips_comparisons"] = comparisons(clip_results, baseline)
    if hard_cases is not None:
        hc = hard_case_report(run_dirs, hard_cases, out, with_flip=with_flip, progress=progress)
        lines += [f"## Hard cases: `{hard_cases}`", "", hc["markdown"], ""]
        extra["hard_cases"] = {k: v for k, v in hc.items() if k != "markdown"}
    if real_scenes:
        from .realscenes import evaluate_store, section
        found = [evaluate_store(run_dirs, s, max_frames=max_frames, progress=progress) for s in real_scenes]
        lines += [section(r) + "\n" for r in found]
        extra["real_scenes"] = [{k: v for k, v in r.items() if k != "markdown"} for r in found]
    return lines, extra


def write_figures(results: list[dict], models: list[dict], store, out: Path) -> list[tuple[str, str, int]]:
    """crops.png (the first evaluated frame of every method and its reference), speed_vs_error.png and
    each adaptive sampler's sample map; returns the maps' ``(label, file, frame)``."""
    first = {r["frames"][0]["index"] for r in results}
    if len(first) != 1:
        raise DataError(f"the methods' first evaluated frames differ ({sorted(first)}); cannot compare crops")
    st = open_store(store)
    ref = st.read_array("reference/radiance", first.pop()).transpose(1, 2, 0)
    crops_image([(r["label"], r["images"][0]) for r in results] + [("reference", ref)], out / "crops.png")
    plot_speed_vs_error(results, out / "speed_vs_error.png")
    maps = []
    for r in models:                      # adaptive samplers: where the samples went
        sm = r.get("sample_map")
        if sm is not None and float(np.ptp(sm["counts"])) > 0:
            name = f"sample_map-{r['label'].replace(' ', '')}.png"
            frame_ref = st.read_array("reference/radiance", sm["index"]).transpose(1, 2, 0)
            sample_map_image(sm["counts"], frame_ref, out / name, f"{r['label']}: frame {sm['index']}")
            maps.append((r["label"], name, sm["index"]))
    return maps


def _busy_lines(results: list[dict]) -> list[str]:
    """The busy-machine warning of the timings (:func:`training.bench.busy_note`), as report lines."""
    from .bench import busy_note
    busy = max([(r.get("speed") or {}).get("others_busy_cores") or 0.0 for r in results], default=0.0)
    note = busy_note(busy)
    return [f"**{note}**", ""] if note else []


def main_section(results: list[dict], store, split: str, spps, maps, baseline: str | None) -> list[str]:
    at = ", ".join(f"{n}" for n in spps)
    lines = [f"# Denoiser report: {split} split of `{store}` at {at} spp", "",
             f"{len(results[0]['frames'])} held-out frames (split by scene). relMSE and SMAPE on linear radiance; "
             "PSNR and SSIM on tone-mapped values (sRGB(log(x+1)), eq. 7); FLIP is HDR-FLIP. "
             f"ms/MP @{BENCH_SIZE}² is the wall-clock inference time of one {BENCH_SIZE}x{BENCH_SIZE} frame (the size "
             "of `python -m training bench`; best of 3 after a warm-up) on this machine "
             f"({results[0]['torch_threads']} torch threads), a model with its trained weights at its spp; on the "
             "store's own small frames fixed costs per call dominate, and those per-frame times are in each "
             "eval-*.json (`ms_per_megapixel`). Each model is evaluated at the samples per pixel it was trained at; "
             "the noisy input and OIDN at each of those counts. Each mean has its 95% interval in brackets (a "
             "bootstrap over the held-out clips; none over a single clip).", "", *_busy_lines(results), *reference_note(results),
             table_markdown(results), "", *comparisons_section(results, baseline), *seed_spread_section(results),
             "![speed against error](speed_vs_error.png)", "",
             f"relMSE by kind of frame (frame counts in brackets; the scene family, defocus and motion from the "
             f"scene, fireflies: at least {FIREFLY_SHARE:.1%} of the pixels hold a sample {FIREFLY_RATIO:g}x "
             "brighter than the reference; plain: none of these):", "", kinds_markdown(results), "",
             "SMAPE by kind of frame:", "", kinds_markdown(results, "smape"), "",
             "PSNR by kind of frame:", "", kinds_markdown(results, "psnr", "{:.2f}"), "",
             "Crops (inputs / models / OIDN / reference):", "", "![crops](crops.png)", ""]
    if any(r.get("clips") for r in results):
        lines += ["tPSNR is PSNR of the frame-to-frame differences of tone-mapped frames (Hasselgren et al. "
                  "2020, sec. 3), over each held-out clip in order (recurrent models carry their state through "
                  "the clip); spp is the achieved mean samples per pixel.", ""]
    for label, name, idx in maps:
        lines += [f"Sample map of {label} (frame {idx}, the last of the first held-out clip):", "",
                  f"![sample map]({name})", ""]
    return lines


def clips_section(clip_results: list[dict], clips_store, out: Path, baseline: str | None) -> list[str]:
    plot_speed_vs_error(clip_results, out / "clips_speed_vs_error.png")
    n_clips = max(r.get("clips", 0) for r in clip_results)
    return [f"## Moving clips: test split of `{clips_store}`", "",
            f"{len(clip_results[0]['frames'])} frames in {n_clips} held-out clips, in order; recurrent "
            "models carry their state through each clip, the others see one frame at a time.", "",
            *reference_note(clip_results), table_markdown(clip_results), "",
            *comparisons_section(clip_results, baseline),
            "![speed against error on clips](clips_speed_vs_error.png)", "",
            "relMSE by kind of frame:", "", kinds_markdown(clip_results), ""]


def budgets_section(results: list[dict]) -> list[str]:
    lines = ["## Training budgets", ""]
    for r in results:
        if "train_config" in r:
            tc = r["train_config"]
            lines.append(f"- {r['label']}: model `{r['method']}` {r.get('model_config')}, {r['train_steps']} steps of "
                         f"batch {tc['batch']}, crop {tc['crop']}, {tc['spp']} spp, loss {tc['loss']}, lr {tc['lr']}, "
                         f"seed {tc.get('seed')}")
    return lines + [""]


def provenance_section(prov: dict) -> list[str]:
    return ["## Provenance", "",
            f"Every number above was computed by this run of the report ({prov['created']}, "
            f"{prov['report_seconds']:.0f} s, code {prov['git_commit'] or 'outside git'}"
            f"{' with local changes' if prov['git_dirty'] else ''}); the command, package versions, "
            "machine, the stores' dataset configs and each run's training config and checkpoint hash are "
            "in [provenance.json](provenance.json).", ""]
