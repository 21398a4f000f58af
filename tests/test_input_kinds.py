"""Every input kind plugs in: a tiny test-only model of each kind (tests/kind_models.py, registered here,
never shipped) goes through the whole CLI (train, evaluate, report, bench, denoise, hard-cases) and
through torchrun with 2 ranks, which gives the one-process weights. A model's output that does not
match its kind's target is refused, not broadcast; a clips model's time axis is handled by the kind."""
from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from training import checkpoint as ckpt

ROOT = Path(__file__).resolve().parents[1]
KINDS = ("samples", "pixels", "clips", "sampled-layers")
CLIPS, FRAMES = (2, 1, 2), 3     # train, val and test clips of three frames
TEST_FRAMES = CLIPS[2] * FRAMES


@pytest.fixture(scope="module")
def probes():
    from kind_models import PROBES, register_probes, unregister_probes
    register_probes()
    yield PROBES
    unregister_probes()


@pytest.fixture(scope="module")
def clip_store(tmp_path_factory):
    from test_temporal import make_clip_store
    return make_clip_store(tmp_path_factory.mktemp("kinds") / "clips.zarr", clips=CLIPS, frames=FRAMES)


def cli(*args) -> int:
    from training.__main__ import main
    return main([str(a) for a in args])


def train_argv(name: str, store: str, out) -> list[str]:
    return ["train", "--model", name, "--store", store, "--out", str(out), "--steps", "3", "--batch", "2",
            "--crop", "8", "--val-every", "3", "--val-frames", "2", "--lr", "0.01",
            "--seed", "4", "--checkpoint-every", "100", "--workers", "0", "--device", "cpu", "--no-progress"]


@pytest.mark.parametrize("kind", KINDS)
def test_a_model_of_each_kind_goes_through_every_command(kind, probes, clip_store, tmp_path):
    name = probes[kind]
    run = tmp_path / "run"
    assert cli(*train_argv(name, clip_store, run)) == 0
    ck = ckpt.load(run / "checkpoint.pt")
    assert ck["step"] == 3 and ck["model"] == name
    val = [r for r in (run / "metrics.csv").read_text().splitlines() if ",val," in r]
    assert val and all(math.isfinite(float(v)) for v in val[-1].split(",")[3:7])

    assert cli("evaluate", "--checkpoint", run / "checkpoint.pt", "--store", clip_store, "--out", tmp_path / "e.json",
               "--no-flip", "--device", "cpu") == 0
    ev = json.loads((tmp_path / "e.json").read_text())
    assert ev["input_kind"] == kind and len(ev["frames"]) == TEST_FRAMES
    for metric in ("relmse", "psnr", "ssim"):
        lo, hi = ev["ci95"][metric]
        assert math.isfinite(ev["mean"][metric]) and lo <= hi
    assert ev["clips"] == CLIPS[2] and ev["mean"]["tpsnr"] is not None    # each clip's frames in order

    assert cli("bench", "--models", name, "--size", "16", "--repeats", "1", "--no-oidn", "--device", "cpu",
               "--json", tmp_path / "b.json") == 0
    assert json.loads((tmp_path / "b.json").read_text())[name]["ms_per_mp"] > 0

    from core.images import read_exr
    from stores.reader import open_store
    last = open_store(clip_store).frames_in_split("test")[-1]        # a recurrent model runs its clip first
    assert cli("denoise", "--checkpoint", run / "checkpoint.pt", "--store", clip_store, "--frame", last,
               "--out", tmp_path / "d.exr", "--device", "cpu") == 0
    img, _ = read_exr(tmp_path / "d.exr")
    assert img.shape[:2] == (16, 16) and np.isfinite(img).all()
    assert np.allclose(img[..., :3], _evaluated_image(run, clip_store, TEST_FRAMES - 1), rtol=1e-4, atol=1e-5)

    assert cli("report", "--runs", run, "--store", clip_store, "--out", tmp_path / "report", "--no-flip") == 0
    text = (tmp_path / "report" / "report.md").read_text()
    assert f"| {run.name} |" in text and "| input |" in text and "| oidn |" in text
    assert "Each method against **its own noisy input**" in text      # paired differences with intervals
    saved = json.loads((tmp_path / "report" / "comparisons.json").read_text())
    comp, by_kind = saved["comparisons"], saved["comparisons_by_kind"]
    assert by_kind["kinds"] and all(k in row for row in by_kind["rows"] for k, _ in by_kind["kinds"])
    assert comp["baseline"] == "its own noisy input" and [r["label"] for r in comp["rows"]] == [run.name, "oidn"]
    assert {r["against"] for r in comp["rows"]} == {"input"}             # one spp, one input kind: one input
    lo, hi = comp["rows"][0]["relmse"]["ci95"]
    assert lo <= comp["rows"][0]["relmse"]["mean"] <= hi
    assert comp["rows"][0]["tpsnr"]["frames"] == CLIPS[2]      # tPSNR paired clip by clip (one run each)
    assert "ΔtPSNR (95%)" in text
    if kind == "samples":
        assert cli("report", "--runs", run, "--store", clip_store, "--out", tmp_path / "r2", "--no-flip",
                   "--baseline", "nonesuch") == 2

    assert cli("hard-cases", "--store", clip_store, "--runs", run, "--out", tmp_path / "hc", "--no-oidn") == 0
    hc = json.loads((tmp_path / "hc" / "hard-cases.json").read_text())
    assert run.name in hc["frames"] and len(hc["frames"][run.name]) == open_store(clip_store).num_frames


def _evaluated_image(run, store, pos: int) -> np.ndarray:
    from training.evaluate import evaluate
    return evaluate(run / "checkpoint.pt", store, keep=(pos,), with_flip=False)["images"][pos]


def test_an_output_that_is_not_the_kinds_target_is_refused(probes, clip_store, tmp_path, capsys):
    """A clips model that outputs one frame for a window of two: before, the loss broadcast it against
    the window's references and training "worked"."""
    from kind_models import ProbeClips
    from training.models.registry import MODELS, register

    class OneFrame(ProbeClips):
        def forward(self, batch):
            return self.step({k: v[:, -1] for k, v in batch.items() if k != "origin"}, None)[0]

    register("probe-one-frame")(OneFrame)
    try:
        assert cli(*train_argv("probe-one-frame", clip_store, tmp_path / "r")) == 2
    finally:
        MODELS.pop("probe-one-frame")
    err = capsys.readouterr().err
    assert "(2, 3, 8, 8)" in err and "(2, 2, 3, 8, 8)" in err


def test_the_clips_kind_steps_the_model_through_the_window(probes):
    from training.inputs import KINDS as INPUT_KINDS
    from training.models import build
    torch.manual_seed(0)
    model = build(probes["clips"])
    with torch.no_grad():
        model.mix.fill_(0.3)
        batch = INPUT_KINDS["clips"].example_batch(2, 2, 8, 8, frames=3, generator=torch.Generator().manual_seed(1))
        out = model(batch)
        assert out.shape == (2, 3, 3, 8, 8)
        state = None
        for t in range(3):                           # by hand: what evaluation does frame by frame
            o, state, _ = model.step({k: (v if k == "origin" else v[:, t]) for k, v in batch.items()}, state)
            assert torch.equal(out[:, t], o)
    assert model.stepwise


def test_time_is_unrolled_in_the_kinds_alone():
    """The recurrent models declare a step (and temporal how a window starts), never their own unrolling:
    forward comes from the base class for every registered model that steps, and a model is recurrent
    exactly when it defines step."""
    from training.models import build, get, names
    from training.models.common import Denoiser
    for name in names():
        cls = get(name)
        if cls.step is not Denoiser.step:
            assert cls.forward is Denoiser.forward, name
            assert "stepwise" not in vars(cls), name
            assert build(name, **cls.tiny).stepwise, name
    assert not build("nbg").stepwise and build("temporal-small").stepwise and build("nppd").stepwise


# ------------------------------------------------------------------------------ torchrun
def test_two_ranks_train_every_kind_to_the_one_process_weights(probes, clip_store, tmp_path):
    from training.models import build
    argvs = {kind: train_argv(probes[kind], clip_store, tmp_path / "ddp" / kind) for kind in KINDS}
    spec = tmp_path / "argvs.json"
    spec.write_text(json.dumps(list(argvs.values())))
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONFAULTHANDLER": "1",   # an abort shows its stacks
           "PYTHONPATH": os.pathsep.join([str(ROOT), str(ROOT / "tests"), os.environ.get("PYTHONPATH", "")])}
    for k in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        env.pop(k, None)
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
           str(ROOT / "tests" / "kind_models.py"), "--each", str(spec)]
    p = subprocess.Popen(cmd, env=env, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         start_new_session=True)
    try:
        stdout, stderr = p.communicate(timeout=240)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        stdout, stderr = p.communicate()
        pytest.fail("torchrun with 2 ranks did not finish in 240 s: " + stderr[-5000:])
    assert p.returncode == 0, stdout[-3000:] + stderr[-5000:]
    for kind, argv in argvs.items():
        one = tmp_path / "one" / kind
        assert cli(*train_argv(probes[kind], clip_store, one)) == 0
        a, b = ckpt.load(one / "checkpoint.pt")["state_dict"], ckpt.load(tmp_path / "ddp" / kind / "checkpoint.pt")["state_dict"]
        assert a.keys() == b.keys()
        worst = max(float((a[k].double() - b[k].double()).abs().max()) for k in a)
        assert worst <= 1e-5, f"{kind}: 2 ranks differ from one process by {worst:.3g}"
        torch.manual_seed(4)
        start = build(probes[kind]).state_dict()
        assert any(not torch.equal(start[k], a[k]) for k in a), f"{kind}: the steps changed no weight"


def test_evaluate_times_only_warm_calls_of_each_shape(probes, clip_store, monkeypatch):
    """A compiled model compiles again for each new input shape and for a recurrent model's first step
    with a state (torch.compile's guards): evaluate runs each such call once untimed, so no frame's time
    holds a compilation (here: 0.3 s the first time a call signature is seen), and says how many frames
    it timed."""
    import time as _time

    from training import evaluate as ev
    from training.models import build
    model = build(probes["clips"])
    kind = type(model.input_spec().input_kind)
    seen, real = set(), kind.stream

    def slow_first(self, net, batch, state=None):       # inside the timed step, as a compilation is
        sig = (tuple(tuple(v.shape) for v in batch.values()), state is None)
        if sig not in seen:
            seen.add(sig)
            _time.sleep(0.3)
        return real(self, net, batch, state)
    monkeypatch.setattr(kind, "stream", slow_first)
    res = ev.evaluate(model, clip_store, split="test", with_flip=False, device="cpu")
    assert len(seen) == 2                                   # a clip's first step, and steps with a state
    assert all(f["ms"] < 250 for f in res["frames"]), [f["ms"] for f in res["frames"]]
    assert res["timing"]["frames_timed"] == len(res["frames"]) == TEST_FRAMES
    assert res["timing"]["untimed_warmups"] == 2


def test_evaluate_times_the_model_step_without_the_read_back(probes, clip_store, monkeypatch):
    """A frame's time is the model's step alone: a slow read-back of its output (0.3 s here; on a GPU the
    copy to pageable memory) is not in it, and the JSON says what the time measures."""
    import time as _time

    from training import evaluate as ev
    from training.models import build
    real = ev._hwc

    def slow_read_back(x):
        if isinstance(x, ev.torch.Tensor) and x.dim() == 3 and x.shape[0] == 3:     # the model's output, CHW
            _time.sleep(0.3)
        return real(x)
    monkeypatch.setattr(ev, "_hwc", slow_read_back)
    t = _time.perf_counter()
    res = ev.evaluate(build(probes["clips"]), clip_store, split="test", with_flip=False, device="cpu")
    assert _time.perf_counter() - t > 0.3 * TEST_FRAMES                      # the read-backs did happen
    assert all(f["ms"] < 250 for f in res["frames"]), [f["ms"] for f in res["frames"]]
    assert "read-back" in res["timing"]["measures"]


def test_evaluate_leaves_two_calls_a_signature_untimed_where_cuda_graphs_record(probes, clip_store, monkeypatch):
    """With CUDA graphs (a real-time model compiled on a GPU) a call signature's first call compiles and
    its second records the graph; only the third replays. Pretended here: ``compile_model`` marks the
    model as the CUDA-graph path does, and each signature's first two calls are slow. No timed frame
    holds either, and the JSON counts both."""
    import time as _time

    from training import accel
    from training import evaluate as ev
    from training.models import build
    model = build(probes["clips"])
    kind = type(model.input_spec().input_kind)
    calls, real = {}, kind.stream

    def as_if_graphed(model):
        model.warmup_calls = 2
        return model

    def slow_twice(self, net, batch, state=None):       # inside the timed step, as compiling and recording are
        sig = (tuple(tuple(v.shape) for v in batch.values()), state is None)
        calls[sig] = calls.get(sig, 0) + 1
        if calls[sig] <= 2:
            _time.sleep(0.3)
        return real(self, net, batch, state)
    monkeypatch.setattr(accel, "compile_model", as_if_graphed)
    monkeypatch.setattr(kind, "stream", slow_twice)
    res = ev.evaluate(model, clip_store, split="test", with_flip=False, device="cpu", compile=True)
    assert all(f["ms"] < 250 for f in res["frames"]), [f["ms"] for f in res["frames"]]
    assert {k: res["timing"][k] for k in ("frames_timed", "untimed_warmups", "call_signatures")} == \
        {"frames_timed": TEST_FRAMES, "untimed_warmups": 4, "call_signatures": 2}
