"""Inference speed of every registered model (paper widths) and OIDN on this machine, in one run.

``run()`` returns and prints ``{name: {"ms_per_mp", "cpu_ms_per_mp", "ms_per_720p", "spp",
"fmas_per_pixel", "params"}}`` with an ``"oidn"`` entry. Each model gets a random batch of its
declared input kind (per-sample frames for the layer family, per-pixel frames for nbg and wskpn) at its
own default spp unless ``spp`` is given, and runs in its inference form (``for_inference``: WSKPN's
RepVGG blocks fused). Speed does not depend on content. Times are the best of ``repeats`` forward
passes under ``torch.no_grad`` after a warm-up; ``ms_per_720p`` scales ms/MP to a 1280x720 frame, the
real-time papers' unit. ``device`` (``auto``: CUDA where present) and ``precision`` (autocast; ``auto``:
bf16 on a GPU that has it, else fp32) choose where and how; on CUDA each timed pass ends with a
synchronisation. ``compile``: each model is also timed through ``torch.compile``, alternating with its eager passes
(:func:`_compiled`), adding ``compiled_ms_per_mp``, ``eager_ms_per_mp_paired`` (the best of each),
``compile_speedup`` (the median ratio of the paired passes), ``compile_speedup_iqr``, ``compile_pairs``
and ``compile_max_rel_diff`` (largest difference of the outputs over the eager output's
largest value).
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


def forward_once(model, batch, stepwise: bool, state, device, precision: str):
    """One timed call: a recurrent model's step with ``state``, else the forward pass."""
    from .accel import autocast
    with torch.no_grad(), autocast(device, precision):
        out = model.step(batch, state)[0] if stepwise else model(batch)
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return out


def _compiled(model, batch, stepwise: bool, state, dev, precision: str, repeats: int, mp: float) -> dict:
    """``model`` compiled (:func:`training.accel.compile_model`) against itself eager: ``repeats`` pairs
    of passes, alternating, so the load of a shared machine hits both alike (best-of-3 eager figures
    moved by 40% from run to run here); the best of each, the median ratio of the pairs (the speed-up)
    with its quartiles; and the largest difference of the outputs."""
    from .accel import compile_model
    eager_step, eager_forward = (model.step if stepwise else None), model.forward
    eager = forward_once(model, batch, stepwise, state, dev, precision).float()
    # models of one class share their forward's code: dynamo guards each on its instance, and past its
    # recompile limit (8) it runs the code eagerly, unsaid; so each model starts afresh
    torch._dynamo.reset()
    compile_model(model)
    out = forward_once(model, batch, stepwise, state, dev, precision).float()         # compiles
    diff = float((out - eager).abs().max() / eager.abs().max().clamp_min(1e-12))

    def run_eager():
        from .accel import autocast
        with torch.no_grad(), autocast(dev, precision):
            eager_step(batch, state) if stepwise else eager_forward(batch)
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)
    te, tc = [], []
    for _ in range(repeats):
        t = time.perf_counter()
        run_eager()
        te.append(time.perf_counter() - t)
        t = time.perf_counter()
        forward_once(model, batch, stepwise, state, dev, precision)
        tc.append(time.perf_counter() - t)
    # the speed-up is the median of the pairs' ratios: a ratio of two best-ofs moved by +-15% from run to
    # run here (temporal 1.12x and 1.43x), the median of 40 pairs by +-3%
    ratio = np.asarray(te) / np.asarray(tc)
    return {"compiled_ms_per_mp": min(tc) * 1e3 / mp, "eager_ms_per_mp_paired": min(te) * 1e3 / mp,
            "compile_speedup": float(np.median(ratio)),
            "compile_speedup_iqr": [float(np.quantile(ratio, 0.25)), float(np.quantile(ratio, 0.75))],
            "compile_max_rel_diff": diff, "compile_pairs": len(ratio)}


def time_model(m, spp: int, size: int, repeats: int, dev, precision: str, compile: bool = False) -> dict:
    """Inference time of model ``m`` (in any state: random or trained weights) on a random batch of its
    input kind at ``spp`` and ``size`` x ``size`` (:func:`_row`, with ``size`` and, with ``compile``,
    :func:`_compiled`'s figures). A recurrent model is timed on one frame's step with a history."""
    spec = m.input_spec()
    stepwise = getattr(m, "stepwise", False)     # recurrent: one frame's step with a history
    frames = 1 if stepwise else spec.frames
    batch = spec.input_kind.example_batch(1, spp, size, size, frames, torch.Generator().manual_seed(0))
    batch = {k: (v.to(dev) if torch.is_tensor(v) else v) for k, v in batch.items()}
    fast = m.to(dev).for_inference()
    state = None
    if stepwise:
        with torch.no_grad():
            state = fast.step(batch, None)[1]
    mp = size * size / 1e6
    s, c = _best(lambda: forward_once(fast, batch, stepwise, state, dev, precision), repeats)
    row = _row(s, c, mp, spp=spp, fmas_per_pixel=float(fast.fmas_per_pixel(spp)), params=m.param_count(),
               device=str(dev), precision=precision, size=size)
    if compile:
        row.update(_compiled(fast, batch, stepwise, state, dev, precision, max(4 * repeats, 12), mp))
    return row


def time_oidn(size: int, repeats: int, dev) -> dict:
    """OIDN's time on a random ``size`` x ``size`` image with albedo and normal (on CUDA: OIDN's CUDA
    device, on tensors already on the GPU), as :func:`_row`."""
    from .oidn import oidn_denoise, oidn_denoise_tensor
    rng = np.random.default_rng(0)
    color = rng.random((size, size, 3), dtype=np.float32) * 4
    alb = rng.random((size, size, 3), dtype=np.float32)
    nrm = rng.uniform(-1, 1, (size, size, 3)).astype(np.float32)
    if dev.type == "cuda":
        ct, at, nt = (torch.from_numpy(x).to(dev) for x in (color, alb, nrm))

        def run_oidn():
            oidn_denoise_tensor(ct, at, nt)
            torch.cuda.synchronize(dev)
    else:
        def run_oidn():
            oidn_denoise(color, alb, nrm)
    s, c = _best(run_oidn, repeats)
    return _row(s, c, size * size / 1e6, spp=None, fmas_per_pixel=None, params=None, device=str(dev), size=size)


def run(size: int = 128, spp: int | None = None, repeats: int = 3, models=None, oidn: bool = True,
        print_table: bool = True, device: str = "cpu", precision: str = "fp32", compile: bool = False) -> dict:
    from .accel import pick_device, precision_for, tune_allocator
    from .models import build, names
    from .models.common import flush_denormals

    flush_denormals()
    tune_allocator()                  # as `python -m training` runs (also when `make bench` calls this)
    dev = pick_device(device)
    precision = precision_for(precision, dev)
    models = list(models) if models else names()
    res = {}
    for name in models:
        torch.manual_seed(0)
        m = build(name)
        n = m.input_spec().default_spp if spp is None else int(spp)
        res[name] = time_model(m, n, size, repeats, dev, precision, compile)
        del m
    if oidn:
        res["oidn"] = time_oidn(size, repeats, dev)
    if print_table:
        where = f"{torch.get_num_threads()} CPU threads" if dev.type == "cpu" else str(dev)
        print(f"inference at {size}x{size}, {where}, {precision} (best of {repeats})")
        print(f"{'model':<16} {'spp':>4} {'ms/MP':>10} {'cpu ms/MP':>10} {'ms/720p':>9} {'kFMA/px':>8} {'params':>11}"
              f" {'/ oidn':>7}" + (f" {'compiled':>9} {'speedup':>8} {'rel diff':>9}" if compile else ""))
        ref = res.get("oidn", {}).get("ms_per_mp")
        for k, v in res.items():
            fm = "-" if v["fmas_per_pixel"] is None else f"{v['fmas_per_pixel'] / 1e3:.1f}"
            pc = "-" if v["params"] is None else f"{v['params']:,}"
            rel = f"{v['ms_per_mp'] / ref:.3f}" if ref else "-"
            cm = (f" {v['compiled_ms_per_mp']:>9.0f} {v['compile_speedup']:>7.2f}x {v['compile_max_rel_diff']:>9.1e}"
                  if "compiled_ms_per_mp" in v else "")
            print(f"{k:<16} {v['spp'] or '-':>4} {v['ms_per_mp']:>10.0f} {v['cpu_ms_per_mp']:>10.0f} "
                  f"{v['ms_per_720p']:>9.1f} {fm:>8} {pc:>11} {rel:>7}" + cm)
        if "layer" in res and "layer-optimized" in res:
            r = {k: res["layer"][k] / res["layer-optimized"][k] for k in ("ms_per_mp", "cpu_ms_per_mp")}
            f = res["layer"]["fmas_per_pixel"] / res["layer-optimized"]["fmas_per_pixel"]
            print(f"layer / layer-optimized: wall {r['ms_per_mp']:.1f}x, cpu {r['cpu_ms_per_mp']:.1f}x "
                  f"(FMAs {f:.1f}x: the bound where convolutions are compute-bound, as on a CPU)")
    return res


if __name__ == "__main__":
    run()
