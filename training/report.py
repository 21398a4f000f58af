"""Markdown report of trained runs against the noisy input and OIDN on held-out frames.

``report(runs, store, out)`` writes ``out/report.md`` (quality/speed table, figure-10 FMA table,
training budgets), ``out/speed_vs_error.png`` (ms per megapixel, log scale, against relMSE),
``out/crops.png`` (input / each model / OIDN / reference, tone-mapped), ``out/sample_map-<run>.png``
for adaptive samplers (where the samples went) and ``out/eval-<name>.json``. Figures: matplotlib.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .errors import DataError
from .evaluate import FIREFLY_RATIO, FIREFLY_SHARE, evaluate, write_json
from .fma import figure10, figure10_markdown
from .tonemap import tonemap

COLUMNS = (("relmse", "relMSE ↓", "{:.4f}"), ("smape", "SMAPE ↓", "{:.4f}"), ("psnr", "PSNR ↑", "{:.2f}"),
           ("ssim", "SSIM ↑", "{:.4f}"), ("flip", "FLIP ↓", "{:.4f}"), ("tpsnr", "tPSNR ↑", "{:.2f}"),
           ("spp", "spp", "{:.2f}"), ("ms_per_megapixel", "ms/MP ↓", "{:.0f}"))


def find_runs(runs) -> list[Path]:
    """Run directories holding a ``checkpoint.pt`` (globs that matched nothing are skipped)."""
    found = []
    for r in runs:
        p = Path(r)
        if (p / "checkpoint.pt").is_file():
            found.append(p)
        elif p.is_file() and p.suffix == ".pt":
            found.append(p.parent)
    return found


def _fmt(v, f):
    return "–" if v is None or (isinstance(v, float) and math.isnan(v)) else f.format(v)


def table_markdown(results: list[dict]) -> str:
    head = "| method | " + " | ".join(c[1] for c in COLUMNS) + " | params | FMAs/pixel |"
    lines = [head, "|---|" + "---|" * (len(COLUMNS) + 2)]
    for r in results:
        m = r["mean"]
        cells = [_fmt(m.get(k), f) for k, _, f in COLUMNS]
        fm = r.get("fmas_per_pixel")
        lines.append(f"| {r['label']} | " + " | ".join(cells) +
                     f" | {r.get('params', 0):,} | {'–' if fm is None else f'{fm / 1e3:.0f}k'} |")
    return "\n".join(lines)


def kinds_markdown(results: list[dict], key: str = "relmse", fmt: str = "{:.4f}") -> str:
    """Mean ``key`` per method over the frames of each kind (defocus, motion, fireflies, plain; a frame
    may have several kinds), with the frame counts in the header."""
    from .evaluate import KINDS
    kinds = [k for k in KINDS if k in results[0].get("by_kind", {})]
    counts = {k: results[0]["by_kind"][k]["frames"] for k in kinds}
    head = "| method | all | " + " | ".join(f"{k} ({counts[k]})" for k in kinds) + " |"
    lines = [head, "|---|---|" + "---|" * len(kinds)]
    for r in results:
        cells = [_fmt(r["mean"].get(key), fmt)] + [_fmt(r["by_kind"][k].get(key), fmt) for k in kinds]
        lines.append(f"| {r['label']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _pyplot():
    import matplotlib
    matplotlib.use("Agg")                       # files only, no display
    import matplotlib.pyplot as plt
    return plt


def plot_speed_vs_error(results: list[dict], path) -> None:
    """Scatter of ms per megapixel (log x) against relMSE (y), one labelled point per method."""
    plt = _pyplot()
    pts = [(r["label"], r["mean"]["ms_per_megapixel"], r["mean"]["relmse"]) for r in results
           if (r["mean"].get("ms_per_megapixel") or 0) > 0]
    from matplotlib.ticker import NullFormatter
    fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=100)
    markers = "osD^v<>p*hX"
    for i, (label, x, y) in enumerate(pts):            # a legend, not annotations: close points stay legible
        ax.scatter([x], [y], s=36, marker=markers[i % len(markers)], label=label)
    ax.set_xscale("log")
    ax.xaxis.set_minor_formatter(NullFormatter())
    if pts:
        ax.legend(fontsize=8, loc="best")
    ax.set_xlabel("ms per megapixel (this machine)")
    ax.set_ylabel("relMSE")
    ax.set_ylim(bottom=0)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def crops_image(panels: list[tuple[str, np.ndarray]], path, crop: int = 64) -> None:
    """Side-by-side tone-mapped centre crops (``crop`` px, nearest-neighbour) with labels."""
    plt = _pyplot()
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
    plt = _pyplot()
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


def report(runs, store, out, split: str = "test", spp: int | None = None, max_frames: int = 0,
           with_flip: bool = True, progress: bool = True, skip_bad_frames: bool = False) -> dict:
    """Evaluate every run and the baselines; write the report files. Returns the results.

    Each run is evaluated at ``spp`` (None: the spp it was trained at, e.g. 8 for the layer family and 1
    for nbg/wskpn) and the noisy input and OIDN at every spp among the runs, so each model stands next
    to the baselines at its own sample count (labels gain ``@N spp`` when there are several)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    run_dirs = find_runs(runs)
    if not run_dirs:
        raise DataError(f"no run directory with a checkpoint.pt among {list(runs)}")

    def one(label, m, at):
        if progress:
            print(f"evaluating {label} on {split} ...", flush=True)
        r = evaluate(m, store, split=split, spp=at, max_frames=max_frames, with_flip=with_flip, keep=(0,),
                     skip_bad_frames=skip_bad_frames)
        r["label"] = label
        write_json(r, out / f"eval-{label.replace(' ', '')}.json")
        return r

    models = [one(d.name, d / "checkpoint.pt", spp) for d in run_dirs]
    # baselines at each run's spp, from what the run reads: per-pixel means of stored samples, or (for a
    # sampler) uniform counts composed from the sample layers
    base_of = lambda r: "sampled-layers" if r.get("input_kind") == "sampled-layers" else "pixels"   # noqa: E731
    groups = sorted({(r["spp"], base_of(r)) for r in models})
    spps = sorted({n for n, _ in groups})
    several_bases = len({b for _, b in groups}) > 1

    def tag(n, base):
        t = f" @{n}spp" if len(spps) > 1 else ""
        return t + (" layers" if several_bases and base == "sampled-layers" else "")

    def base_one(label, method, n, base):
        if progress:
            print(f"evaluating {label} on {split} ...", flush=True)
        r = evaluate(method, store, split=split, spp=n, max_frames=max_frames, with_flip=with_flip, keep=(0,),
                     skip_bad_frames=skip_bad_frames, baseline_input=base)
        r["label"] = label
        write_json(r, out / f"eval-{label.replace(' ', '')}.json")
        return r

    inputs = [base_one(f"input{tag(n, b)}", "input", n, b) for n, b in groups]
    oidns = [base_one(f"oidn{tag(n, b)}", "oidn", n, b) for n, b in groups]
    results = inputs + models + oidns

    # the reference of the frame the crops show (the first evaluated frame of every method)
    first = {r["frames"][0]["index"] for r in results}
    if len(first) != 1:
        raise DataError(f"the methods' first evaluated frames differ ({sorted(first)}); cannot compare crops")
    from .data import open_store
    ref = open_store(store).read_array("reference/radiance", first.pop()).transpose(1, 2, 0)
    crops_image([(r["label"], r["images"][0]) for r in results] + [("reference", ref)], out / "crops.png")
    plot_speed_vs_error(results, out / "speed_vs_error.png")
    maps = []
    for r in models:                      # adaptive samplers: where the samples went
        sm = r.get("sample_map")
        if sm is not None and float(np.ptp(sm["counts"])) > 0:
            name = f"sample_map-{r['label'].replace(' ', '')}.png"
            frame_ref = open_store(store).read_array("reference/radiance", sm["index"]).transpose(1, 2, 0)
            sample_map_image(sm["counts"], frame_ref, out / name, f"{r['label']}: frame {sm['index']}")
            maps.append((r["label"], name, sm["index"]))
    fig10 = figure10()

    at = ", ".join(f"{n}" for n in spps)
    lines = [f"# Denoiser report: {split} split of `{store}` at {at} spp", "",
             f"{len(results[0]['frames'])} held-out frames (split by scene). relMSE and SMAPE on linear radiance; "
             "PSNR and SSIM on tone-mapped values (sRGB(log(x+1)), eq. 7); FLIP is HDR-FLIP. "
             f"Times are wall-clock per frame on this machine ({results[0]['torch_threads']} torch threads), "
             "after one warm-up frame. Each model is evaluated at the samples per pixel it was trained at; "
             "the noisy input and OIDN at each of those counts.", "", table_markdown(results), "",
             "![speed against error](speed_vs_error.png)", "",
             f"relMSE by kind of frame (frame counts in brackets; defocus and motion from the scene, "
             f"fireflies: at least {FIREFLY_SHARE:.1%} of the pixels hold a sample {FIREFLY_RATIO:g}x brighter "
             "than the reference; plain: none of these):", "", kinds_markdown(results), "",
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
    lines += ["## Training budgets", ""]
    for r in results:
        if "train_config" in r:
            tc = r["train_config"]
            lines.append(f"- {r['label']}: model `{r['method']}` {r.get('model_config')}, {r['train_steps']} steps of "
                         f"batch {tc['batch']}, crop {tc['crop']}, {tc['spp']} spp, loss {tc['loss']}, lr {tc['lr']}")
    lines += ["", "## FMAs against samples per pixel (figure 10, billions per 1920x1080 frame, paper defaults)", "",
              figure10_markdown(fig10), ""]
    (out / "report.md").write_text("\n".join(lines))
    return {"results": [{k: v for k, v in r.items() if k != "images"} for r in results], "figure10": fig10}
