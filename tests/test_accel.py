"""The GPU path as far as a CPU can test it (training.accel): ``--device auto``, ``--precision``
(autocast with fp32 weights, fp16 loss scaling), the loader's rate against the steps', and
``--compile`` giving the eager outputs. Tests marked ``gpu`` run the same on a CUDA device."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from training import accel
from training import checkpoint as ckpt
from training.config import TrainConfig
from training.errors import ConfigError
from training.loop import train, train_step
from training.losses import build_loss
from training.models import build, get, names

from test_training import make_store

ROOT = Path(__file__).resolve().parent.parent
CUDA = torch.cuda.is_available()


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return make_store(tmp_path_factory.mktemp("store") / "tiny.zarr")


def test_auto_device_and_precision_follow_the_machine(monkeypatch):
    assert accel.device_name("auto") == ("cuda" if CUDA else "cpu")
    assert accel.device_name("cuda:1") == "cuda:1" and accel.device_name("cpu") == "cpu"
    assert accel.precision_for("auto", torch.device("cpu")) == "fp32"
    assert accel.precision_for("bf16", torch.device("cpu")) == "bf16"
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda *a, **k: True)
    assert accel.precision_for("auto", torch.device("cuda")) == "bf16"
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda *a, **k: False)
    assert accel.precision_for("auto", torch.device("cuda")) == "fp32"
    assert TrainConfig().device == "auto" and TrainConfig().precision == "auto"


@pytest.mark.parametrize("bad", ["gpu", "cuda:x", "", 3, "tpu:0"])
def test_bad_devices_and_precisions_are_config_errors(bad):
    with pytest.raises(ConfigError, match='"device" must be'):
        TrainConfig(device=bad)
    with pytest.raises(ConfigError, match='"precision" must be one of auto, bf16, fp16, fp32'):
        TrainConfig(precision=str(bad) or "fp8")


@pytest.mark.skipif(CUDA, reason="this machine has a GPU")
def test_cuda_without_a_gpu_is_a_one_line_error(store, tmp_path):
    r = subprocess.run([sys.executable, "-m", "training", "train", "--model", "nbg", "--store", store, "--out",
                        str(tmp_path / "run"), "--steps", "1", "--device", "cuda", "--no-progress"],
                       cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 2, r.stderr
    err = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert err == ["error: \"device\" is 'cuda' but no CUDA device is available (--device auto or cpu)"]


def _conv_dtypes(model) -> list:
    seen = []
    for m in model.modules():
        if isinstance(m, torch.nn.Conv2d):
            m.register_forward_hook(lambda mod, inp, out: seen.append(out.dtype))
    return seen


@pytest.mark.parametrize("name", names())
@pytest.mark.parametrize("precision", ["bf16", "fp16"])
def test_every_family_trains_a_step_in_reduced_precision_with_fp32_weights(name, precision):
    """The convolutions run in the reduced precision, the loss is finite, the weights stay fp32 and move
    (fp16: through the loss scaler)."""
    torch.manual_seed(0)
    model = accel.prepare(build(name, **get(name).tiny), torch.device("cpu"))
    spec = model.input_spec()
    batch = spec.input_kind.example_batch(2, 2, 16, 16, spec.frames, torch.Generator().manual_seed(1))
    with torch.no_grad():
        batch["reference"] = torch.rand_like(model(batch).float())
    before = {k: v.clone() for k, v in model.state_dict().items()}
    seen = _conv_dtypes(model)
    dev = torch.device("cpu")
    scaler = accel.grad_scaler(dev, precision)
    assert scaler.is_enabled() == (precision == "fp16")
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    loss = train_step(model, opt, build_loss(model.train_defaults.get("loss", "smape")), batch,
                      target=spec.input_kind.target(batch), precision=precision, scaler=scaler)
    assert torch.isfinite(torch.tensor(loss))
    if seen:                                           # every family convolves; its convs ran reduced
        assert set(seen) == {accel.DTYPES[precision]}, seen
    assert all(p.dtype == torch.float32 for p in model.parameters())
    moved = [k for k, v in model.state_dict().items() if v.is_floating_point() and not torch.equal(v, before[k])]
    if precision == "bf16" or scaler.get_scale() == 65536.0:     # fp16's first steps may be skipped (overflow)
        assert moved, "no weight moved"


def test_fp16_training_checkpoints_its_loss_scale_and_resumes_exactly(store, tmp_path):
    c = TrainConfig(model="nbg", steps=4, batch=2, crop=16, val_every=2, val_frames=1, val_crop=16,
                    checkpoint_every=100, seed=1, precision="fp16", workers=0)
    train(c, store, tmp_path / "a", progress=False)
    train(c, store, tmp_path / "b", progress=False, stop_after=2)
    assert "scaler" in ckpt.load(tmp_path / "b" / "checkpoint.pt")
    train(c, store, tmp_path / "b", progress=False)
    wa, wb = (ckpt.load(tmp_path / r / "checkpoint.pt") for r in "ab")
    assert wa["scaler"] == wb["scaler"] and wa["scaler"]["scale"] > 0
    assert all(torch.equal(wa["state_dict"][k], wb["state_dict"][k]) for k in wa["state_dict"])
    # the precision may change on resumption (a GPU run finished on a CPU): it is not part of the identity
    train(c.replace(precision="fp32", steps=6), store, tmp_path / "b", progress=False)
    assert ckpt.load(tmp_path / "b" / "checkpoint.pt")["step"] == 6


def test_train_says_where_it_runs_and_whether_the_loader_keeps_up(store, tmp_path):
    r = subprocess.run([sys.executable, "-m", "training", "train", "--model", "nbg", "--store", store, "--out",
                        str(tmp_path / "run"), "--steps", "14", "--batch", "2", "--crop", "16", "--workers", "0",
                        "--precision", "bf16", "--val-every", "0", "--no-progress"],
                       cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "train nbg: device cpu, precision bf16" in r.stdout, r.stdout
    line = next(ln for ln in (r.stdout + r.stderr).splitlines() if "data: the loader makes" in ln)
    assert "crops/s (the training process (--workers 0)); the steps consume" in line, line
    assert "% of the time waiting for data" in line
    assert ckpt.load(tmp_path / "run" / "checkpoint.pt")["train_config"]["precision"] == "bf16"


def test_compiled_inference_gives_the_eager_outputs(tmp_path):
    """``bench --compile`` times each model compiled and states its largest difference from eager;
    ``evaluate --compile`` writes the eager metrics (one model here; every family: the slow test)."""
    from training.bench import run
    res = run(size=32, repeats=1, models=["nbg"], oidn=False, print_table=False, device="cpu", compile=True)
    r = res["nbg"]
    assert r["compile_max_rel_diff"] < 1e-4 and r["compiled_ms_per_mp"] > 0 and r["compile_speedup"] > 0


@pytest.mark.parametrize("name", ["temporal-small", "temporal-uniform"])
def test_the_temporal_step_compiles_to_one_graph(name):
    """The sampler's checks and water-filling branch on values only when eager: a compiled step is one
    graph (its 8 graph breaks held ``--compile`` to 1.07-1.22x), and still gives the eager outputs."""
    from training.adaptive import compose
    from stores.errors import SampleCountError
    torch.manual_seed(0)
    m = build(name, **get(name).tiny).for_inference()
    spec = m.input_spec()
    batch = spec.input_kind.example_batch(1, spec.default_spp, 16, 16, 1, torch.Generator().manual_seed(0))
    with torch.no_grad():
        state = m.step(batch, None)[1]
        eager = m.step(batch, state)[0]
        explained = torch._dynamo.explain(m.step)(batch, state)
    assert explained.graph_count == 1 and explained.graph_break_count == 0, explained.break_reasons
    with pytest.raises(SampleCountError, match="must be in 0..3"):       # eager still checks
        compose(torch.zeros(1, 2, 3, 4, 4), torch.full((1, 1, 4, 4), 4))
    torch._dynamo.reset()
    compiled = torch.compile(m.step, options=accel.COMPILE_OPTIONS)
    with torch.no_grad():
        out = compiled(batch, state)[0]
    assert float((out - eager).abs().max() / eager.abs().max()) < 1e-4


@pytest.mark.slow
@pytest.mark.parametrize("name", names())
def test_every_family_compiles_to_its_eager_outputs(name):
    from training.bench import run
    r = run(size=32, repeats=1, models=[name], oidn=False, print_table=False, device="cpu", compile=True)[name]
    assert r["compile_max_rel_diff"] < 1e-4, r


def test_evaluate_and_denoise_take_device_precision_and_compile(store, tmp_path):
    run = tmp_path / "run"
    c = TrainConfig(model="nbg", steps=2, batch=2, crop=16, val_every=0, seed=1, workers=0)
    train(c, store, run, progress=False)
    outs = {}
    for tag, extra in (("eager", []), ("compiled", ["--compile"])):
        r = subprocess.run([sys.executable, "-m", "training", "evaluate", "--checkpoint", str(run / "checkpoint.pt"),
                            "--store", store, "--out", str(tmp_path / f"{tag}.json"), "--no-flip",
                            "--frames", "2", *extra], cwd=ROOT, capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, r.stderr
        outs[tag] = json.loads((tmp_path / f"{tag}.json").read_text())
    assert outs["eager"]["device"] == "cpu" and outs["eager"]["precision"] == "fp32"
    assert outs["compiled"]["compiled"] is True and outs["eager"]["compiled"] is False
    for k in ("psnr", "relmse", "smape"):
        assert outs["compiled"]["mean"][k] == pytest.approx(outs["eager"]["mean"][k], rel=1e-4), k
    r = subprocess.run([sys.executable, "-m", "training", "denoise", "--checkpoint", str(run / "checkpoint.pt"),
                        "--store", store, "--frame", "0", "--out", str(tmp_path / "d.exr"), "--precision", "bf16"],
                       cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and (tmp_path / "d.exr").exists(), r.stderr


@pytest.mark.gpu
def test_cuda_training_in_bf16_matches_fp32_within_noise(store, tmp_path):
    losses = {}
    for p in ("fp32", "bf16"):
        c = TrainConfig(model="nbg", steps=20, batch=2, crop=16, val_every=20, val_frames=2, val_crop=16, seed=1,
                        device="cuda", precision=p, workers=0)
        losses[p] = train(c, store, tmp_path / p, progress=False)["val"]["loss"]
    assert abs(losses["bf16"] - losses["fp32"]) < 0.05 * losses["fp32"] + 1e-3, losses


_FAULTS = """
import resource, sys, numpy as np
if sys.argv[1] == "tuned":
    from training.accel import tune_allocator
    assert tune_allocator()
def faults(n=16 << 20):
    a = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    x = np.ones(n, np.uint8)
    del x
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - a
print(faults(), faults())
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_the_tuned_allocator_reuses_freed_pages():
    """After ``tune_allocator`` a freed 16 MiB block is reused without faulting its pages in again;
    glibc's defaults fault them in twice. A malloc setting in the environment is left to rule."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("MALLOC_", "GLIBC_TUNABLES"))}
    env["PYTHONPATH"] = str(Path(__file__).resolve().parents[1])

    def run(*args, **extra):
        r = subprocess.run([sys.executable, "-c", _FAULTS, *args], env={**env, **extra}, capture_output=True,
                           text=True, check=True)
        return [int(x) for x in r.stdout.split()]
    first, second = run("tuned")
    assert first > 100 and second < first / 20
    first, second = run("default")
    assert second > first / 2                      # the defaults: the same block faulted in again
    r = subprocess.run([sys.executable, "-c", "from training.accel import tune_allocator; print(tune_allocator())"],
                       env={**env, "MALLOC_TRIM_THRESHOLD_": "131072"}, capture_output=True, text=True, check=True)
    assert r.stdout.strip() == "False"


# ------------------------------------------------------------------------------ nothing keeps the device waiting
HOST_READS = ("item", "tolist", "cpu", "numpy", "__float__", "__int__", "__bool__", "__index__")


class _HostReads:
    """Counts every read of a tensor's values on the host while active (each one waits for the device):
    the Tensor methods that convert to Python or to the CPU, and torch's allclose and equal."""

    def __init__(self, monkeypatch):
        self.seen: list[str] = []
        self.on = False
        for name in HOST_READS:
            monkeypatch.setattr(torch.Tensor, name, self._spy(getattr(torch.Tensor, name), name))
        for name in ("allclose", "equal"):
            monkeypatch.setattr(torch, name, self._spy(getattr(torch, name), name))

    def _spy(self, real, name):
        def spy(*args, **kwargs):
            if self.on:
                self.seen.append(name)
            return real(*args, **kwargs)
        return spy


FAMILIES = ["layer", "nbg", "wskpn", "temporal", "nppd"]


@pytest.fixture
def one_thread():
    """One thread and denormals flushed, as training runs (tiny steps: OpenMP's threads only wait on a
    busy machine)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    torch.set_flush_denormal(True)
    yield
    torch.set_num_threads(threads)


@pytest.mark.parametrize("name", FAMILIES)
def test_training_steps_read_the_device_only_when_the_loss_is_read(name, monkeypatch, one_thread):
    """K optimiser steps as the training loop runs them (``device_train_step``, fused Adam, the losses
    read by ``LossReader`` every N steps) read values back at most K/N + 1 times: no per-step host sync
    (the temporal family's sampler and water-filling included)."""
    from training.loop import LossReader, device_train_step, forward_loss_fn
    torch.manual_seed(0)
    model = build(name, **get(name).tiny)
    spec = model.input_spec()
    batch = spec.input_kind.example_batch(2, spec.default_spp, 16, 16, spec.frames, torch.Generator().manual_seed(0))
    with torch.no_grad():
        batch["reference"] = torch.rand_like(model(batch).float())
    opt = accel.adam(model.parameters(), 1e-4)
    loss_fn = build_loss(model.train_defaults.get("loss", "smape"))
    forward_loss = forward_loss_fn(model, loss_fn, torch.device("cpu"))
    target = spec.input_kind.target(batch)
    k, n = 12, 4
    reader, reads = LossReader(n), _HostReads(monkeypatch)
    reads.on = True
    for step in range(1, k + 1):
        reader.add(step, device_train_step(model, opt, loss_fn, batch, target=target, forward_loss=forward_loss))
        if step % n == 0:
            value = reader.read()
    reads.on = False
    assert len(reads.seen) <= k // n + 1, reads.seen
    with torch.no_grad():
        assert value == pytest.approx(float(loss_fn(model(batch).float(), target)), rel=0.5)


class _Items(torch.utils.data.Dataset):
    """Held-out items of a model's input kind (the kind's example batch, one item each), with references."""

    def __init__(self, model, n: int, size: int = 16):
        spec = model.input_spec()
        g = torch.Generator().manual_seed(1)
        b = spec.input_kind.example_batch(n, spec.default_spp, size, size, spec.frames, g)
        with torch.no_grad():
            b["reference"] = torch.rand(model(b).float().shape, generator=g)
        self.items = [{k: v[i] for k, v in b.items()} for i in range(n)]

    def __len__(self):
        return len(self.items)

    def __getitem__(self, i):
        return self.items[i]


@pytest.mark.parametrize("name", ["layer", "temporal"])
def test_validation_reads_the_device_once_and_agrees_with_the_metrics(name, monkeypatch, one_thread):
    """A validation pass over 6 items runs them in batches and reads its figures back once (it read five
    values an item); its figures are those of ``training.metrics`` (numpy, float64) and of the loss, item
    by item."""
    import numpy as np

    from training import metrics
    from training.loop import validate
    torch.manual_seed(0)
    model = build(name, **get(name).tiny)
    ds = _Items(model, 6)
    loss_fn = build_loss(model.train_defaults.get("loss", "smape"))
    reads = _HostReads(monkeypatch)
    reads.on = True
    got = validate(model, ds, loss_fn, "cpu", kind=model.input_spec().input_kind)
    reads.on = False
    assert len(reads.seen) <= 2 and reads.seen.count("cpu") == 1, reads.seen        # the .cpu() and its .numpy()
    kind, want = model.input_spec().input_kind, {"loss": [], "relmse": [], "smape": [], "psnr": []}
    for item in ds.items:
        b = {k: v.unsqueeze(0) for k, v in item.items()}
        with torch.no_grad():
            out, ref = model.eval()(b).float(), kind.target(b).float()
        if out.dim() == 5:                     # a window: its last frame is judged
            out, ref = out[:, -1], ref[:, -1]
        want["loss"].append(float(loss_fn(out, ref)))
        d, r = out[0].permute(1, 2, 0).numpy(), ref[0].permute(1, 2, 0).numpy()
        for k in ("relmse", "smape", "psnr"):
            want[k].append(getattr(metrics, k)(d, r))
    for k, v in want.items():
        assert got[k] == pytest.approx(float(np.mean(v)), rel=1e-5), k


def test_the_losses_are_read_together_and_a_nan_names_its_step():
    from training.errors import NonFiniteError
    from training.loop import LossReader
    reader = LossReader(5)
    assert reader.read() != reader.read()                  # NaN before any step
    for step, v in enumerate([0.5, 0.4, float("nan"), 0.3], start=11):
        reader.add(step, torch.tensor(v))
    with pytest.raises(NonFiniteError, match=r"loss is nan \(non-finite\) at step 13; .* every 5 steps "
                                             r"\(--log-every\), here steps 11\.\.14"):
        reader.read()
    reader.add(15, torch.tensor(0.25))
    assert reader.read() == 0.25 and reader.read() == 0.25


def test_adam_is_fused_and_resumes_from_a_state_of_either_kernel():
    """Adam's update is one fused kernel where the device has it (the CPU and CUDA); a state saved by
    the other kernel loads into it (a run moved between devices) and steps on."""
    w = torch.nn.Parameter(torch.ones(3))
    plain = torch.optim.Adam([w], lr=0.1, foreach=False)
    w.grad = torch.ones(3)
    plain.step()
    w2 = torch.nn.Parameter(w.detach().clone())
    fused = accel.adam([w2], 0.1)
    assert fused.defaults["fused"] is True
    accel.load_optimizer_state(fused, plain.state_dict())
    assert fused.param_groups[0]["fused"] is True and fused.param_groups[0]["foreach"] is None
    w.grad, w2.grad = torch.ones(3), torch.ones(3)
    plain.step()
    fused.step()
    torch.testing.assert_close(w2, w)


def test_train_compile_matches_eager(store, tmp_path):
    """``train --compile``: the forward pass and loss through torch.compile give the eager run's weights
    within float rounding (a 1x1-convolution probe, so the compile stays short); a run may resume
    compiled or not."""
    from kind_models import PROBES, register_probes, unregister_probes
    register_probes()
    try:
        c = TrainConfig(model=PROBES["pixels"], steps=2, batch=2, crop=16, val_every=0, seed=1, workers=0,
                        checkpoint_every=100)
        torch._dynamo.reset()
        runs = {tag: train(c.replace(compile=tag == "compiled"), store, tmp_path / tag, progress=False)
                for tag in ("eager", "compiled")}
    finally:
        unregister_probes()
    assert runs["compiled"]["loss"] == pytest.approx(runs["eager"]["loss"], rel=1e-5)
    wa, wb = (ckpt.load(tmp_path / t / "checkpoint.pt")["state_dict"] for t in ("eager", "compiled"))
    for key in wa:
        torch.testing.assert_close(wb[key], wa[key], rtol=1e-5, atol=1e-6)
    assert ckpt.load(tmp_path / "compiled" / "checkpoint.pt")["train_config"]["compile"] is True
    register_probes()
    try:                                       # the compiled run resumes eagerly
        assert train(c.replace(steps=3), store, tmp_path / "compiled", progress=False)["step"] == 3
    finally:
        unregister_probes()
    with pytest.raises(ConfigError, match='"compile" must be true or false'):
        TrainConfig(compile="yes")


def test_cuda_graphs_only_for_the_realtime_models_on_a_gpu():
    """Compiled for CUDA, nbg, wskpn and the temporal family replay CUDA graphs (fixed shapes, one
    launch a frame); the offline models, and every model on the CPU, compile as before."""
    cuda, cpu = torch.device("cuda"), torch.device("cpu")
    for name in names():
        m = build(name, **get(name).tiny)
        realtime = name in ("nbg", "wskpn") or name.startswith("temporal")
        assert m.realtime == realtime, name
        assert accel.compile_options(m, cuda) == {**accel.COMPILE_OPTIONS, **({"triton.cudagraphs": True} if realtime else {})}
        assert accel.compile_options(m, cpu) == accel.COMPILE_OPTIONS
    assert accel.compile_options(build("nbg", **get("nbg").tiny)) == accel.COMPILE_OPTIONS   # its weights' device


@pytest.mark.gpu
@pytest.mark.parametrize("name", ["nbg", "temporal-small"])
def test_compiled_realtime_models_replay_cuda_graphs_with_the_eager_outputs(name):
    """On a GPU the compiled real-time form (CUDA graphs) gives the eager outputs frame after frame, a
    recurrent state carried from one replay into the next included."""
    torch.manual_seed(0)
    dev = torch.device("cuda")
    m = accel.prepare(build(name, **get(name).tiny), dev).for_inference()
    spec = m.input_spec()
    frames = [{k: v.to(dev) for k, v in spec.input_kind.example_batch(1, spec.default_spp, 32, 32, 1,
                                                                       torch.Generator().manual_seed(i)).items()}
              for i in range(3)]

    def run(model):
        outs, state = [], None
        with torch.no_grad():
            for f in frames:
                if m.stepwise:
                    out, state, _ = model.step(f, state)
                else:
                    out = model(f)
                outs.append(out)
        return [o.float().cpu() for o in outs]
    eager = run(m)
    compiled = run(accel.compile_model(m))
    for a, b in zip(eager, compiled):
        torch.testing.assert_close(b, a, rtol=1e-3, atol=1e-4)
