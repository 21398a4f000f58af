"""FMA counts against sample count: the layer paper's figure 10 as a function.

Counts are analytic from each model's convolution layers (``Denoiser.fmas_per_pixel``: 1x1 fully
connected parts, the 3x3 U-net at its resolutions, kernel taps); pooling, upsampling and activations
are not counted, as in the paper.
"""
from __future__ import annotations

FIGURE10_MODELS = ("pixelgather", "samplesplat", "layer", "layer-optimized")
FIGURE10_SPP = (2, 4, 8, 16, 32)


def figure10(spps=FIGURE10_SPP, models=FIGURE10_MODELS, width: int = 1920, height: int = 1080,
             configs: dict | None = None) -> list[dict]:
    """Rows ``{"model", "spp", "fmas_per_pixel", "gfmas_per_frame"}`` for the paper's default
    models (or ``configs[name]`` settings) at a ``width x height`` frame (1080p as in the paper)."""
    from .models import build

    rows = []
    for name in models:
        m = build(name, **(configs or {}).get(name, {}))
        for spp in spps:
            f = float(m.fmas_per_pixel(spp))
            rows.append({"model": name, "spp": int(spp), "fmas_per_pixel": f,
                         "gfmas_per_frame": f * width * height / 1e9})
    return rows


def figure10_markdown(rows: list[dict]) -> str:
    models = list(dict.fromkeys(r["model"] for r in rows))
    spps = sorted({r["spp"] for r in rows})
    val = {(r["model"], r["spp"]): r["gfmas_per_frame"] for r in rows}
    lines = ["| model | " + " | ".join(f"{s} spp" for s in spps) + " |",
             "|---|" + "---|" * len(spps)]
    for m in models:
        lines.append(f"| {m} | " + " | ".join(f"{val[(m, s)]:.0f}" for s in spps) + " |")
    return "\n".join(lines)
