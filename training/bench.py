"""Inference speed of every registered model (paper widths) and OIDN on this machine, in one run.

``run()`` returns and prints ``{name: {"ms_per_mp", "cpu_ms_per_mp", "ms_per_720p", "spp",
"fmas_per_pixel", "params"}}`` with an ``"oidn"`` entry. Each model gets a random batch of its
declared input kind (per-sample frames for the layer family, per-pixel frames for nbg and wskpn) at its
own default spp unless ``spp`` is given, and runs in its inference form (``for_inference``: WSKPN's
RepVGG blocks fused). Speed does not depend on content. Times are the best of ``repeats`` forward
passes under ``torch.no_grad`` after a warm-up; ``ms_per_720p`` scales ms/MP to a 1280x720 frame, the
real-time papers' unit.
"""
from __future__ import annotations

import time

import numpy as np
import torch

MP_720P = 1280 * 720 / 1e6


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


def _row(wall: float, cpu: float, mp: float, **extra) -> dict:
    ms = wall * 1e3 / mp
    return {"ms_per_mp": ms, "cpu_ms_per_mp": cpu * 1e3 / mp, "ms_per_720p": ms * MP_720P, **extra}


def run(size: int = 128, spp: int | None = None, repeats: int = 3, models=None, oidn: bool = True,
        print_table: bool = True) -> dict:
    from .models import build, names
    from .models.common import flush_denormals
    from .oidn import oidn_denoise

    flush_denormals()
    models = list(models) if models else names()
    mp = size * size / 1e6
    res = {}
    for name in models:
        torch.manual_seed(0)
        m = build(name)
        spec = m.input_spec()
        n = spec.default_spp if spp is None else int(spp)
        stepwise = getattr(m, "stepwise", False)     # recurrent: one frame's step with a history
        frames = 1 if stepwise else spec.frames
        batch = spec.input_kind.example_batch(1, n, size, size, frames, torch.Generator().manual_seed(0))
        fast = m.for_inference()
        with torch.no_grad():
            if stepwise:
                state = fast.step(batch, None)[1]
                s, c = _best(lambda f=fast, st=state: f.step(batch, st), repeats)
            else:
                s, c = _best(lambda f=fast: f(batch), repeats)
        res[name] = _row(s, c, mp, spp=n, fmas_per_pixel=float(fast.fmas_per_pixel(n)), params=m.param_count())
        del m, fast
    if oidn:
        rng = np.random.default_rng(0)
        color = rng.random((size, size, 3), dtype=np.float32) * 4
        alb = rng.random((size, size, 3), dtype=np.float32)
        nrm = rng.uniform(-1, 1, (size, size, 3)).astype(np.float32)
        s, c = _best(lambda: oidn_denoise(color, alb, nrm), repeats)
        res["oidn"] = _row(s, c, mp, spp=None, fmas_per_pixel=None, params=None)
    if print_table:
        print(f"inference at {size}x{size}, {torch.get_num_threads()} threads (best of {repeats})")
        print(f"{'model':<16} {'spp':>4} {'ms/MP':>10} {'cpu ms/MP':>10} {'ms/720p':>9} {'kFMA/px':>8} {'params':>11}"
              f" {'/ oidn':>7}")
        ref = res.get("oidn", {}).get("ms_per_mp")
        for k, v in res.items():
            fm = "-" if v["fmas_per_pixel"] is None else f"{v['fmas_per_pixel'] / 1e3:.1f}"
            pc = "-" if v["params"] is None else f"{v['params']:,}"
            rel = f"{v['ms_per_mp'] / ref:.3f}" if ref else "-"
            print(f"{k:<16} {v['spp'] or '-':>4} {v['ms_per_mp']:>10.0f} {v['cpu_ms_per_mp']:>10.0f} "
                  f"{v['ms_per_720p']:>9.1f} {fm:>8} {pc:>11} {rel:>7}")
        if "layer" in res and "layer-optimized" in res:
            r = {k: res["layer"][k] / res["layer-optimized"][k] for k in ("ms_per_mp", "cpu_ms_per_mp")}
            f = res["layer"]["fmas_per_pixel"] / res["layer-optimized"]["fmas_per_pixel"]
            print(f"layer / layer-optimized: wall {r['ms_per_mp']:.1f}x, cpu {r['cpu_ms_per_mp']:.1f}x "
                  f"(FMAs {f:.1f}x: the bound where convolutions are compute-bound, as on a CPU)")
    return res


if __name__ == "__main__":
    run()
