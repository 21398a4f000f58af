"""Markdown report of trained runs against the noisy input and OIDN on held-out frames.

``report(runs, store, out)`` writes ``out/report.md`` (quality/speed table, figure-10 FMA table,
training budgets), ``out/speed_vs_error.png`` (ms per megapixel, log scale, against relMSE),
``out/crops.png`` (input / each model / OIDN / reference, tone-mapped) and ``out/eval-<name>.json``.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from .errors import DataError
from .evaluate import FIREFLY_RATIO, FIREFLY_SHARE, evaluate, write_json
from .fma import figure10, figure10_markdown
from .tonemap import tonemap

COLUMNS = (("relmse", "relMSE ↓", "{:.4f}"), ("smape", "SMAPE ↓", "{:.4f}"), ("psnr", "PSNR ↑", "{:.2f}"),
           ("ssim", "SSIM ↑", "{:.4f}"), ("flip", "FLIP ↓", "{:.4f}"), ("ms_per_megapixel", "ms/MP ↓", "{:.0f}"))


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


def plot_speed_vs_error(results: list[dict], path, size=(640, 440)) -> None:
    """Scatter of ms per megapixel (log10 x) against relMSE (y), one labelled point per method (PIL)."""
    w, h = size
    left, right, top, bottom = 70, 20, 20, 50
    img = Image.new("RGB", size, "white")
    d = ImageDraw.Draw(img)
    pts = [(r["label"], r["mean"]["ms_per_megapixel"], r["mean"]["relmse"]) for r in results
           if r["mean"].get("ms_per_megapixel", 0) > 0]
    if not pts:
        img.save(path)
        return
    xs = [math.log10(p[1]) for p in pts]
    ys = [p[2] for p in pts]
    x0, x1 = math.floor(min(xs)), math.ceil(max(xs) + 1e-9)
    x1 = max(x1, x0 + 1)
    y0, y1 = 0.0, max(ys) * 1.15 or 1.0
    X = lambda v: left + (v - x0) / (x1 - x0) * (w - left - right)          # noqa: E731
    Y = lambda v: h - bottom - (v - y0) / (y1 - y0) * (h - top - bottom)    # noqa: E731
    d.line([(left, top), (left, h - bottom), (w - right, h - bottom)], fill="black")
    for e in range(x0, x1 + 1):
        d.line([(X(e), h - bottom), (X(e), h - bottom + 4)], fill="black")
        d.text((X(e) - 12, h - bottom + 6), f"1e{e}", fill="black")
    for i in range(5):
        v = y0 + (y1 - y0) * i / 4
        d.line([(left - 4, Y(v)), (left, Y(v))], fill="black")
        d.text((4, Y(v) - 6), f"{v:.3g}", fill="black")
    d.text(((w - left) // 2, h - 18), "ms per megapixel (log)", fill="black")
    d.text((left + 4, 4), "relMSE", fill="black")
    colors = ["#d62728", "#1f77b4", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf"]
    for i, ((label, _, yv), xv) in enumerate(zip(pts, xs)):
        c = colors[i % len(colors)]
        cx, cy = X(xv), Y(yv)
        d.ellipse([cx - 4, cy - 4, cx + 4, cy + 4], fill=c)
        d.text((cx + 6, cy - 6), label, fill=c)
    img.save(path)


def crops_image(panels: list[tuple[str, np.ndarray]], path, crop: int = 64, scale: int = 3) -> None:
    """Side-by-side tone-mapped centre crops (``crop`` px, upscaled ``scale``x) with labels."""
    tiles = []
    for label, im in panels:
        h, w = im.shape[:2]
        c = min(crop, h, w)
        y, x = (h - c) // 2, (w - c) // 2
        t = np.clip(tonemap(im[y:y + c, x:x + c]), 0, 1)
        t = Image.fromarray((t * 255 + 0.5).astype(np.uint8)).resize((c * scale, c * scale), Image.NEAREST)
        tiles.append((label, t))
    tw = max(t.width for _, t in tiles)
    th = max(t.height for _, t in tiles)
    img = Image.new("RGB", (len(tiles) * (tw + 4), th + 16), "white")
    d = ImageDraw.Draw(img)
    for i, (label, t) in enumerate(tiles):
        img.paste(t, (i * (tw + 4), 16))
        d.text((i * (tw + 4) + 2, 2), label, fill="black")
    img.save(path)


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
    spps = sorted({r["spp"] for r in models})
    tag = (lambda n: f" @{n}spp") if len(spps) > 1 else (lambda n: "")
    inputs = [one(f"input{tag(n)}", "input", n) for n in spps]
    oidns = [one(f"oidn{tag(n)}", "oidn", n) for n in spps]
    results = inputs + models + oidns

    # the reference of the frame the crops show (the first evaluated frame of every method)
    first = {r["frames"][0]["index"] for r in results}
    if len(first) != 1:
        raise DataError(f"the methods' first evaluated frames differ ({sorted(first)}); cannot compare crops")
    from .data import open_store
    ref = open_store(store).read_array("reference/radiance", first.pop()).transpose(1, 2, 0)
    crops_image([(r["label"], r["images"][0]) for r in results] + [("reference", ref)], out / "crops.png")
    plot_speed_vs_error(results, out / "speed_vs_error.png")
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
             "Crops (inputs / models / OIDN / reference):", "", "![crops](crops.png)", "", "## Training budgets", ""]
    for r in results:
        if "train_config" in r:
            tc = r["train_config"]
            lines.append(f"- {r['label']}: model `{r['method']}` {r.get('model_config')}, {r['train_steps']} steps of "
                         f"batch {tc['batch']}, crop {tc['crop']}, {tc['spp']} spp, loss {tc['loss']}, lr {tc['lr']}")
    lines += ["", "## FMAs against samples per pixel (figure 10, billions per 1920x1080 frame, paper defaults)", "",
              figure10_markdown(fig10), ""]
    (out / "report.md").write_text("\n".join(lines))
    return {"results": [{k: v for k, v in r.items() if k != "images"} for r in results], "figure10": fig10}
