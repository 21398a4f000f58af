"""Where and in what precision a model runs: ``--device auto`` and ``--precision``, one place for both.

``auto`` devices are CUDA when PyTorch sees one, else the CPU. ``auto`` precision is bf16 on a GPU that
has it (``torch.cuda.is_bf16_supported``), else fp32. Reduced precision is autocast: the weights (and
Adam's state) stay fp32, the convolutions and matrix products run in bf16 or fp16, and fp16 training
scales the loss (``torch.amp.GradScaler``: a step whose gradients overflow is skipped and the scale
lowered). Every loss and metric is computed in fp32 from the model's output.
"""
from __future__ import annotations

from contextlib import nullcontext

import torch

from core.checks import need

from .errors import ConfigError

DEVICES = ("auto", "cpu", "cuda")
PRECISIONS = ("auto", "bf16", "fp16", "fp32")
DTYPES = {"bf16": torch.bfloat16, "fp16": torch.float16}


def check_device(name) -> None:
    """ConfigError unless ``name`` is auto, cpu, cuda or cuda:N."""
    ok = isinstance(name, str) and (name in DEVICES or (name.startswith("cuda:") and name[5:].isdigit()))
    need(ok, '"device"', '"auto", "cpu" or "cuda[:N]"', name, ConfigError)


def check_precision(name) -> None:
    need(name in PRECISIONS, '"precision"', f"one of {', '.join(PRECISIONS)}", name, ConfigError)


def device_name(name: str) -> str:
    """``auto`` as ``cuda`` where PyTorch sees a CUDA device, else ``cpu``; other names unchanged."""
    check_device(name)
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    return name


def pick_device(name: str) -> torch.device:
    """The torch device of ``name`` (``auto`` resolved); ConfigError for CUDA where there is none."""
    dev = torch.device(device_name(name))
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f'"device" is {name!r} but no CUDA device is available (--device auto or cpu)')
    if dev.type == "cuda" and dev.index is not None and dev.index >= torch.cuda.device_count():
        raise ConfigError(f'"device" is {name!r} but this machine has {torch.cuda.device_count()} CUDA '
                          "device(s)")
    return dev


def precision_for(name: str, device: torch.device) -> str:
    """``auto`` as bf16 on a CUDA device that has it, else fp32; an explicit precision unchanged (bf16 and
    fp16 run on the CPU too, through its autocast, slower than fp32 on most CPUs)."""
    check_precision(name)
    if name != "auto":
        return name
    if device.type == "cuda" and torch.cuda.is_bf16_supported():
        return "bf16"
    return "fp32"


def autocast(device: torch.device, precision: str):
    """The forward pass's context: autocast to bf16/fp16, or nothing for fp32."""
    if precision == "fp32":
        return nullcontext()
    return torch.autocast(device.type, dtype=DTYPES[precision])


def grad_scaler(device: torch.device, precision: str) -> torch.amp.GradScaler:
    """Loss scaling for fp16 (a disabled scaler, which passes every call through, otherwise)."""
    return torch.amp.GradScaler(device.type, enabled=precision == "fp16")


def describe(device: torch.device, precision: str) -> str:
    """One line: the device (with the GPU's name) and the precision."""
    what = str(device)
    if device.type == "cuda":
        what += f" ({torch.cuda.get_device_name(device)})"
    return f"device {what}, precision {precision}"


# Adam's update as one fused kernel over every parameter (``fused=True``) where PyTorch has one for the
# device (CUDA, and the CPU since torch 2.4). Measured on 2 CPU threads, one optimiser step, median of 7:
# layer (17.3M parameters) 43 ms for-loop / 51 ms foreach / 23 ms fused; nppd (14.9M) 21 / 26 / 14 ms;
# temporal-small (0.31M) 1.5 / 1.1 / 0.56 ms. The fused kernel is the fastest on both devices.
FUSED_FLAGS = ("fused", "foreach")


def adam(params, lr: float) -> torch.optim.Adam:
    """Adam at ``lr``, fused where the parameters' device has the fused kernel, else PyTorch's default."""
    params = list(params)
    try:
        return torch.optim.Adam(params, lr=lr, fused=True)
    except RuntimeError:                 # a device without the fused kernel
        return torch.optim.Adam(params, lr=lr)


def load_optimizer_state(optimizer: torch.optim.Optimizer, state: dict) -> None:
    """Load a saved optimiser ``state`` keeping this optimiser's own kernel choice (:data:`FUSED_FLAGS`): a run
    saved on one device resumes fused or not as its new device allows (the step counts then live where
    that kernel wants them)."""
    flags = {k: optimizer.defaults.get(k) for k in FUSED_FLAGS}
    state = {**state, "param_groups": [{**g, **flags} for g in state["param_groups"]]}
    optimizer.load_state_dict(state)


# glibc's malloc serves blocks above its mmap threshold (128 KiB, raised only after a large block is
# freed) with fresh pages and hands freed heap tops back at once (trim threshold 128 KiB): an eager
# forward pass on the CPU, whose activations are 0.1-30 MiB each, then page-faults on every call.
# Measured at 128x128 on 2 threads, one model in a fresh process, two runs each: eager nppd 10.5-10.8
# -> 8.9-9.3 s/MP, temporal-small 1.6-2.2 -> 1.3-1.5 s/MP, layer-optimized 7.9 -> 7.0 s/MP; compiled
# layer-optimized 6.3-7.2 -> 5.6 s/MP, nppd 8.6 -> 7.9-8.0 s/MP; training steps unchanged within noise.
ALLOCATOR = {"mmap_threshold": 32 << 20, "trim_threshold": 1 << 30}
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3


def tune_allocator() -> bool:
    """Keep freed memory in the process for reuse (glibc's ``mallopt``: :data:`ALLOCATOR`), so that CPU
    passes reuse pages instead of faulting fresh ones in; RSS stays at its peak instead of falling back.
    Called at the start of ``python -m training`` (again: no change). False (nothing changed) off glibc,
    or where ``MALLOC_MMAP_THRESHOLD_``, ``MALLOC_TRIM_THRESHOLD_`` or ``GLIBC_TUNABLES`` in the
    environment chooses for itself."""
    import ctypes
    import os
    if any(k in os.environ for k in ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "GLIBC_TUNABLES")):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt      # the process's own libc, without a library search
    except (OSError, AttributeError):
        return False
    return bool(mallopt(_M_MMAP_THRESHOLD, ALLOCATOR["mmap_threshold"])) and \
        bool(mallopt(_M_TRIM_THRESHOLD, ALLOCATOR["trim_threshold"]))


def prepare(model: torch.nn.Module, device: torch.device) -> torch.nn.Module:
    """``model`` on ``device`` with channels-last weights (the layout cuDNN's and oneDNN's convolutions
    prefer, and the one the models' inputs are given in)."""
    return model.to(device=device, memory_format=torch.channels_last)


# Inductor's freezing folds the weights into the graph as constants (inference only: the weights may
# not change after compiling). Measured at 128x128 on 2 CPU threads, compiled against eager: nbg 1.10x
# -> 2.12x with it, wskpn 1.07x -> 1.31x, temporal-small 0.97x -> 1.70x, layer-optimized 1.20x -> 1.31x
# (best-of-5 ratios, before tune_allocator; docs/training.md has the paired medians since).
COMPILE_OPTIONS = {"freezing": True}


def compile_options(model: torch.nn.Module, device: torch.device | None = None) -> dict:
    """Inductor's options for ``model``'s inference: :data:`COMPILE_OPTIONS`, plus CUDA graphs
    (``triton.cudagraphs``, what ``mode="reduce-overhead"`` turns on) for a real-time model
    (``model.realtime``: nbg, wskpn, the temporal family) whose weights are on a CUDA device: each frame
    is then one graph launch instead of one launch a kernel. A graph is recorded per input shape, so
    this pays where frames keep their size (evaluation, a stream of frames, ``bench``). ``device``: where
    the model runs (default: where its weights are)."""
    opts = dict(COMPILE_OPTIONS)
    if device is None:
        weight = next(model.parameters(), None)
        device = torch.device("cpu") if weight is None else weight.device
    if device.type == "cuda" and getattr(model, "realtime", False):
        opts["triton.cudagraphs"] = True
    return opts


def _owned(fn):
    """``fn`` (compiled with CUDA graphs) returning copies of its tensors: the next replay of a graph
    writes its outputs into the same memory, which would change a frame's output or a recurrent state
    still held by the caller. Each call starts a new step of the graphs (inference only)."""
    from torch.utils._pytree import tree_map_only

    def call(*args, **kwargs):
        torch.compiler.cudagraph_mark_step_begin()
        return tree_map_only(torch.Tensor, torch.clone, fn(*args, **kwargs))
    return call


def compile_model(model: torch.nn.Module) -> torch.nn.Module:
    """``model`` (the same object, for inference: under ``torch.no_grad``, its weights fixed) with its
    forward pass, and a recurrent model's ``step``, compiled by ``torch.compile`` (Inductor: C++/OpenMP
    kernels on the CPU, Triton on CUDA; :func:`compile_options`: CUDA graphs for the real-time models on
    a GPU). The first call of each input shape compiles (tens of seconds on a CPU); later calls run the
    compiled code. With CUDA graphs the second call of a shape records its graph, and only the third
    replays it: ``model.warmup_calls`` says how many calls of a shape to leave untimed (1, or 2)."""
    opts = compile_options(model)
    model.warmup_calls = 2 if opts.get("triton.cudagraphs") else 1
    if not opts.get("triton.cudagraphs"):
        model.compile(options=opts)
        if getattr(model, "stepwise", False):
            model.step = torch.compile(model.step, options=opts)
        return model
    model.forward = _owned(torch.compile(model.forward, options=opts))
    if getattr(model, "stepwise", False):
        model.step = _owned(torch.compile(model.step, options=opts))
    return model
