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

``time_model`` and ``time_oidn`` also take a frame of ``(height, width)`` (``ms_per_frame``: the
time of that frame, e.g. 1280x720). Training steps a second (``python -m training bench --train``,
:func:`train_run`): :func:`time_training` times the step that ``python -m training train`` runs
(``training.loop.device_train_step`` with ``training.accel.adam``, the loss read from the device every
``log_every`` steps) on a random batch at each family's paper crop and batch (:data:`PAPER_TRAINING`).
``scripts/device_check.py`` calls these same functions on a GPU.
"""
from __future__ import annotations

import time

import numpy as np
import torch

MP_720P = 1280 * 720 / 1e6
# the papers' training crops and batches, and the spp (frames: a sequence's length for temporal):
# layer 128 px x 4 at 8 spp (Munkberg sec. 4); nbg 128 x 20 (Meng sec. 5); wskpn 128 x 64 (Fan sec. 5);
# temporal 128 x 4 sequences of 5 frames at 4 spp (Hasselgren sec. 2.4)
PAPER_TRAINING = {"layer": (128, 4, 8), "temporal": (128, 4, 4), "nbg": (128, 20, 1), "wskpn": (128, 64, 1)}


def frame_shape(size) -> tuple[int, int]:
    """``size`` (an edge, or ``(height, width)``) as ``(height, width)``."""
    if isinstance(size, (tuple, list)):
        h, w = size
        return int(h), int(w)
    return int(size), int(size)


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


def others_busy(seconds: float = 0.5) -> float:
    """The cores other processes kept busy over ``seconds`` while this one slept (0 to the CPU count). On a
    shared CPU the timings mean little when this is high: a model of many small operations then ran up to
    35x slower here (nbg at 128x128, 2 threads, with two other busy processes on 2 cores: 870 ms a call
    for several seconds against 24 ms; its threads spin at each operation's barrier for a core another
    process holds), beyond what a best of three outlasts."""
    import os

    import psutil
    return psutil.cpu_percent(interval=seconds) / 100.0 * (os.cpu_count() or 1)


def busy_note(busy: float | None) -> str | None:
    """One line that says the CPU timings were taken on a busy machine (``others_busy`` of at least half a
    core), or None."""
    import os
    if busy is None or busy < 0.5:
        return None
    return (f"The machine was busy while timing: other processes kept {busy:.1f} of its {os.cpu_count()} cores "
            "busy, so these CPU times can be many times the quiet figure (nbg: up to 35x); compare them only "
            "with times taken on an idle machine.")


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


def time_model(m, spp: int, size, repeats: int, dev, precision: str, compile: bool = False) -> dict:
    """Inference time of model ``m`` (in any state: random or trained weights) on a random batch of its
    input kind at ``spp`` and ``size`` (an edge: ``size`` x ``size``; or ``(height, width)``)
    (:func:`_row`, with ``size``, ``ms_per_frame`` and, with ``compile``, :func:`_compiled`'s figures
    and ``compiled_ms_per_frame``). A recurrent model is timed on one frame's step with a history."""
    h, w = frame_shape(size)
    spec = m.input_spec()
    stepwise = getattr(m, "stepwise", False)     # recurrent: one frame's step with a history
    frames = 1 if stepwise else spec.frames
    batch = spec.input_kind.example_batch(1, spp, h, w, frames, torch.Generator().manual_seed(0))
    batch = {k: (v.to(dev) if torch.is_tensor(v) else v) for k, v in batch.items()}
    fast = m.to(dev).for_inference()
    state = None
    if stepwise:
        with torch.no_grad():
            state = fast.step(batch, None)[1]
    mp = h * w / 1e6
    s, c = _best(lambda: forward_once(fast, batch, stepwise, state, dev, precision), repeats)
    row = _row(s, c, mp, spp=spp, fmas_per_pixel=float(fast.fmas_per_pixel(spp)), params=m.param_count(),
               device=str(dev), precision=precision, size=size if isinstance(size, int) else [h, w],
               ms_per_frame=s * 1e3)
    if compile:
        row.update(_compiled(fast, batch, stepwise, state, dev, precision, max(4 * repeats, 12), mp))
        row["compiled_ms_per_frame"] = row["compiled_ms_per_mp"] * mp
    return row


def time_training(m, crop: int, batch: int, spp: int, dev, precision: str, seconds: float = 3.0,
                  min_steps: int = 5, max_steps: int = 200, log_every: int = 10, compile: bool = False) -> dict:
    """Training steps a second of model ``m`` (freshly built) on a random batch of its input kind
    (``batch`` crops of ``crop`` x ``crop`` at ``spp``; a sequence model's windows of its frames), the
    step ``python -m training train`` runs: ``training.loop.device_train_step`` with fused Adam
    (``training.accel.adam``), channels-last weights, ``precision`` autocast, the forward pass and loss
    compiled with ``compile``, the loss left on the device and read every ``log_every`` steps
    (``LossReader``). Three steps warm up (the first compiles; ``first_step_s``); then steps run for
    ``seconds`` (at least ``min_steps``, at most ``max_steps``), timed to the device's last step."""
    from .accel import adam, autocast, grad_scaler, prepare
    from .loop import LossReader, device_train_step, forward_loss_fn
    from .losses import build_loss
    model = prepare(m, dev)
    spec = model.input_spec()
    b = spec.input_kind.example_batch(batch, spp, crop, crop, spec.frames, torch.Generator().manual_seed(0))
    b = {k: v.to(dev) if torch.is_tensor(v) else v for k, v in b.items()}
    with torch.no_grad(), autocast(dev, precision):
        b["reference"] = torch.rand_like(model(b).float())
    target = spec.input_kind.target(b)
    opt = adam(model.parameters(), 1e-4)
    loss_fn = build_loss(model.train_defaults.get("loss", "smape"))
    scaler = grad_scaler(dev, precision)
    forward_loss = forward_loss_fn(model, loss_fn, dev, precision, compiled=compile)
    losses = LossReader(log_every)

    def sync():
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)

    def step(i: int):
        losses.add(i, device_train_step(model, opt, loss_fn, b, target=target, precision=precision, scaler=scaler,
                                        forward_loss=forward_loss))
        if i % log_every == 0:
            losses.read()
    t = time.perf_counter()
    step(1)
    sync()
    first = time.perf_counter() - t
    for i in (2, 3):
        step(i)
    losses.read()
    sync()
    t, k = time.perf_counter(), 0
    while k < min_steps or (time.perf_counter() - t < seconds and k < max_steps):
        k += 1
        step(k)
    loss = losses.read()
    sync()
    elapsed = time.perf_counter() - t
    return {"steps_per_s": k / elapsed, "steps": k, "loss": loss, "first_step_s": first, "crop": crop,
            "batch": batch, "spp": spp, "precision": precision, "device": str(dev), "compiled": compile,
            "params": m.param_count()}


def train_run(models=None, seconds: float = 3.0, device: str = "cpu", precisions=("fp32",), crop: int | None = None,
              batch: int | None = None, compile: bool = False, print_table: bool = True) -> dict:
    """Steps a second of each model (default: the four families of :data:`PAPER_TRAINING`) at its paper's
    crop and batch (``crop`` / ``batch``: the same for all, the batch at most the paper's) in each of
    ``precisions`` (:func:`time_training`); ``{name: {precision: row}}`` with ``bf16_speedup`` where both
    ran."""
    from .accel import pick_device, tune_allocator
    from .models import build
    from .models.common import flush_denormals
    flush_denormals()
    tune_allocator()
    dev = pick_device(device)
    res = {}
    for name in models or PAPER_TRAINING:
        c, bsz, spp = PAPER_TRAINING.get(name, (128, 4, None))
        c, bsz = crop or c, min(batch, bsz) if batch else bsz
        row = {}
        for precision in precisions:
            torch.manual_seed(0)
            m = build(name)
            row[precision] = time_training(m, c, bsz, spp or m.input_spec().default_spp, dev, precision, seconds,
                                           compile=compile)
            del m
        if "fp32" in row and "bf16" in row:
            row["bf16_speedup"] = row["bf16"]["steps_per_s"] / row["fp32"]["steps_per_s"]
        res[name] = row
        if print_table:
            print(f"train {name:<16} crop {c} x batch {bsz}: " + ", ".join(
                f"{p} {r['steps_per_s']:.2f} steps/s" for p, r in row.items() if isinstance(r, dict))
                + (" (compiled)" if compile else ""), flush=True)
    return res


def time_oidn(size, repeats: int, dev) -> dict:
    """OIDN's time on a random ``size`` x ``size`` (or ``(height, width)``) image with albedo and normal
    (on CUDA: OIDN's CUDA device, on tensors already on the GPU), as :func:`_row`."""
    from .oidn import oidn_denoise, oidn_denoise_tensor
    h, w = frame_shape(size)
    rng = np.random.default_rng(0)
    color = rng.random((h, w, 3), dtype=np.float32) * 4
    alb = rng.random((h, w, 3), dtype=np.float32)
    nrm = rng.uniform(-1, 1, (h, w, 3)).astype(np.float32)
    if dev.type == "cuda":
        ct, at, nt = (torch.from_numpy(x).to(dev) for x in (color, alb, nrm))

        def run_oidn():
            oidn_denoise_tensor(ct, at, nt)
            torch.cuda.synchronize(dev)
    else:
        def run_oidn():
            oidn_denoise(color, alb, nrm)
    s, c = _best(run_oidn, repeats)
    return _row(s, c, h * w / 1e6, spp=None, fmas_per_pixel=None, params=None, device=str(dev),
                size=size if isinstance(size, int) else [h, w], ms_per_frame=s * 1e3)


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
    busy = others_busy() if dev.type == "cpu" else None
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
        note = busy_note(busy)
        if note:
            print(note)
    return res


if __name__ == "__main__":
    run()
