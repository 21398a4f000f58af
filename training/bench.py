"""Inference speed of every paper model (default widths) and OIDN at 8 spp on this machine, in one run.

``run()`` returns and prints ``{name: {"ms_per_megapixel", "cpu_ms_per_megapixel", "fmas_per_pixel",
"params"}}``. Inputs are
random per-sample frames of ``size x size`` pixels (speed does not depend on content); times are the
best of ``repeats`` forward passes under ``torch.no_grad`` after a warm-up.
"""
from __future__ import annotations

import time

import numpy as np
import torch

from stores.contract import NUM_FEATURES

BENCH_MODELS = ("pixelgather", "samplesplat", "layer", "layer-w", "layer-optimized")


def _best(fn, repeats: int) -> tuple[float, float]:
    """Best wall-clock and best process-CPU seconds of ``repeats`` calls after a warm-up. CPU time
    (all threads) is the steadier figure on a shared machine: it does not count waiting for cores."""
    fn()
    wall = cpu = float("inf")
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        fn()
        wall = min(wall, time.perf_counter() - t)
        cpu = min(cpu, time.process_time() - c)
    return wall, cpu


def run(size: int = 128, spp: int = 8, repeats: int = 3, models=BENCH_MODELS, oidn: bool = True,
        print_table: bool = True) -> dict:
    from .models import build
    from .models.common import flush_denormals
    from .oidn import oidn_denoise

    flush_denormals()
    g = torch.Generator().manual_seed(0)
    batch = {"radiance": torch.rand(1, spp, 3, size, size, generator=g) * 4,
             "features": torch.rand(1, spp, NUM_FEATURES, size, size, generator=g)}
    mp = size * size / 1e6
    res = {}
    for name in models:
        torch.manual_seed(0)
        m = build(name).eval()
        with torch.no_grad():
            s, c = _best(lambda: m(batch), repeats)
        res[name] = {"ms_per_megapixel": s * 1e3 / mp, "cpu_ms_per_megapixel": c * 1e3 / mp,
                     "fmas_per_pixel": float(m.fmas_per_pixel(spp)),
                     "params": m.param_count()}
        del m
    if oidn:
        rng = np.random.default_rng(0)
        color = rng.random((size, size, 3), dtype=np.float32) * 4
        alb = rng.random((size, size, 3), dtype=np.float32)
        nrm = rng.uniform(-1, 1, (size, size, 3)).astype(np.float32)
        s, c = _best(lambda: oidn_denoise(color, alb, nrm), repeats)
        res["oidn"] = {"ms_per_megapixel": s * 1e3 / mp, "cpu_ms_per_megapixel": c * 1e3 / mp,
                       "fmas_per_pixel": None, "params": None}
    if print_table:
        print(f"inference at {spp} spp, {size}x{size}, {torch.get_num_threads()} threads (best of {repeats})")
        print(f"{'model':<16} {'ms/MP':>12} {'cpu ms/MP':>12} {'kFMA/px':>10} {'params':>12}")
        for k, v in res.items():
            fm = "-" if v["fmas_per_pixel"] is None else f"{v['fmas_per_pixel'] / 1e3:.0f}"
            pc = "-" if v["params"] is None else f"{v['params']:,}"
            print(f"{k:<16} {v['ms_per_megapixel']:>12.0f} {v['cpu_ms_per_megapixel']:>12.0f} {fm:>10} {pc:>12}")
        if "layer" in res and "layer-optimized" in res:
            r = {k: res["layer"][k] / res["layer-optimized"][k] for k in ("ms_per_megapixel", "cpu_ms_per_megapixel")}
            f = res["layer"]["fmas_per_pixel"] / res["layer-optimized"]["fmas_per_pixel"]
            print(f"layer / layer-optimized: wall {r['ms_per_megapixel']:.1f}x, cpu {r['cpu_ms_per_megapixel']:.1f}x "
                  f"(FMAs {f:.1f}x: the bound where convolutions are compute-bound, as on a CPU)")
    return res


if __name__ == "__main__":
    run()
