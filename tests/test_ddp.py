"""Data-parallel training (``torchrun``, :mod:`training.distributed`) on tiny real stores: 2 CPU ranks
(gloo) give the weights of one process with the same global batch, for a per-sample layer model
(through the CLI, ``python -m training train``), a recurrent temporal model over clip windows and a
per-pixel model; a run interrupted and resumed under 2 ranks equals the uninterrupted one, and a
one-process run resumes under 2 ranks; only rank 0 writes; and each rank's crops in a step are its
slice of the one-process batch.

One ``torchrun --standalone --nproc_per_node 2`` launch runs every distributed case (this file is its
script: see ``_worker``); the one-process runs it is compared with run in the test process."""
from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from training import checkpoint as ckpt
from training.config import TrainConfig
from training.distributed import Dist, from_env
from training.errors import ConfigError, DataError

ROOT = Path(__file__).resolve().parents[1]
LAYER_TINY = dict(embed=8, context=8, kernel_size=5, partition_hidden=[8], kernel_hidden=[8],
                  unet_encoder=[[8], [8]], unet_bottleneck=[8], unet_decoder=[[8], [8]])
# atol on weights after a few Adam steps: the 2-rank gradient is the one-process one up to the order
# of float sums (~1e-7 relative); Adam's normalised step turns that into ~1e-6 of lr at most.
ATOL = 1e-5


def layer_argv(store, out):
    """``python -m training train`` arguments of the layer case (the CLI's own defaults otherwise)."""
    return ["train", "--model", "layer", "--model-cfg", json.dumps(LAYER_TINY), "--store", store, "--out", out,
            "--steps", "4", "--batch", "4", "--crop", "16", "--spp", "2", "--lr", "0.005", "--seed", "3",
            "--val-every", "2", "--val-frames", "2", "--checkpoint-every", "100", "--workers", "0",
            "--no-progress"]


def layer_cfg() -> TrainConfig:
    """The TrainConfig that ``layer_argv`` makes (training/__main__.py with its defaults)."""
    return TrainConfig(model="layer", model_cfg=LAYER_TINY, steps=4, batch=4, crop=16, spp=2, lr=0.005, seed=3,
                       val_every=2, val_frames=2, checkpoint_every=100, workers=0)


def temporal_cfg() -> TrainConfig:
    from training.models import build
    return TrainConfig(model="temporal", model_cfg={**build("temporal").tiny, "frames": 3}, steps=3, batch=2,
                       crop=16, val_every=3, val_frames=2, val_crop=16, log_every=1, checkpoint_every=100, seed=1,
                       workers=0)


def nbg_cfg() -> TrainConfig:
    return TrainConfig(model="nbg", model_cfg={"guide_hidden": [6], "guide_kernel": 3}, steps=3, batch=4, crop=16,
                       val_every=3, val_frames=2, val_crop=16, log_every=1, checkpoint_every=100, seed=2, workers=0)


# ------------------------------------------------------------------------------ the torchrun script
def _worker(spec_path: str) -> None:
    """Run every case of the spec under this torchrun process group (2 ranks)."""
    from training.__main__ import main
    from training.distributed import session
    from training.loop import train
    spec = json.loads(Path(spec_path).read_text())
    # through the CLI first, with no process group yet: train() makes one from torchrun's variables
    # (and keeps it for the process: the runs below reuse it)
    assert main(layer_argv(spec["store"], spec["out"] + "/layer")) == 0
    assert torch.distributed.is_initialized()
    with session("cpu") as (dist, _):
        assert dist.world == 2
        c = layer_cfg()                                          # interrupted after 2 steps, then resumed
        train(c, spec["store"], spec["out"] + "/resumed", progress=False, stop_after=2)
        train(c, spec["store"], spec["out"] + "/resumed", progress=False)
        train(c, spec["store"], spec["out"] + "/from-one", progress=False)   # one process's 2 steps, resumed
        train(temporal_cfg(), spec["clip_store"], spec["out"] + "/temporal", progress=False)
        import training.loop as loop                             # record the crops each rank trains on
        seen, step = [], loop.device_train_step

        def spy(model, optimizer, loss_fn, batch, *a, **kw):
            seen.append({"index": batch["index"].tolist(), "origin": batch["origin"].tolist()})
            return step(model, optimizer, loss_fn, batch, *a, **kw)
        loop.device_train_step = spy
        res = train(nbg_cfg(), spec["store"], spec["out"] + "/nbg", progress=False)
        loop.device_train_step = step
        Path(spec["out"], f"nbg/seen-{dist.rank}.json").write_text(json.dumps(seen))
        assert res["rank"] == dist.rank and res["world"] == 2
        with pytest.raises(ConfigError, match="divide evenly over the 2 ranks"):
            train(nbg_cfg().replace(batch=3), spec["store"], spec["out"] + "/odd", progress=False)


# ------------------------------------------------------------------------------ tests
@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    from test_temporal import make_clip_store
    from test_training import make_store
    d = tmp_path_factory.mktemp("ddp")
    return make_store(d / "tiny.zarr"), make_clip_store(d / "clips.zarr")


@pytest.fixture(scope="module")
def ddp_runs(stores, tmp_path_factory):
    """Folder of the 2-rank runs (one torchrun launch)."""
    from training.loop import train
    out = tmp_path_factory.mktemp("ddp-runs")
    train(layer_cfg(), stores[0], out / "from-one", progress=False, stop_after=2)   # resumed under 2 ranks
    spec = out / "spec.json"
    spec.write_text(json.dumps({"store": stores[0], "clip_store": stores[1], "out": str(out)}))
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONFAULTHANDLER": "1",   # an abort shows its stacks
           "PYTHONPATH": os.pathsep.join([str(ROOT), str(ROOT / "tests"), os.environ.get("PYTHONPATH", "")])}
    for k in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        env.pop(k, None)
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
           __file__, str(spec)]
    p = subprocess.Popen(cmd, env=env, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         start_new_session=True)                 # its own group: a hang is killed whole
    try:
        stdout, stderr = p.communicate(timeout=240)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        stdout, stderr = p.communicate()
        pytest.fail("torchrun with 2 ranks did not finish in 240 s: " + stderr[-5000:])
    assert p.returncode == 0, stdout[-3000:] + stderr[-5000:]
    return out, stdout


def _weights(path):
    return ckpt.load(path)["state_dict"]


def _close(a: dict, b: dict, atol: float = ATOL) -> float:
    assert a.keys() == b.keys()
    worst = max(float((a[k].double() - b[k].double()).abs().max()) for k in a)
    assert worst <= atol, f"max weight difference {worst:.3g} > {atol}"
    return worst


def _rows(path):
    return list(csv.DictReader(open(path)))


def test_two_ranks_give_the_one_process_weights(stores, ddp_runs, tmp_path):
    from training.loop import train
    out, stdout = ddp_runs
    store, clip_store = stores
    one = {"layer": train(layer_cfg(), store, tmp_path / "layer", progress=False),
           "temporal": train(temporal_cfg(), clip_store, tmp_path / "temporal", progress=False),
           "nbg": train(nbg_cfg(), store, tmp_path / "nbg", progress=False)}
    for name in one:
        a, b = ckpt.load(tmp_path / name / "checkpoint.pt"), ckpt.load(out / name / "checkpoint.pt")
        assert a["train_config"] == b["train_config"] and a["step"] == b["step"]
        print(name, "max |w_1 - w_2|:", _close(a["state_dict"], b["state_dict"]))
        assert not any(k.startswith("module.") for k in b["state_dict"])      # the unwrapped model's
        # rank 0 alone wrote metrics.csv: one row per logged step; losses and validation are global
        r1, r2 = _rows(tmp_path / name / "metrics.csv"), _rows(out / name / "metrics.csv")
        assert [(r["step"], r["kind"]) for r in r1] == [(r["step"], r["kind"]) for r in r2]
        for x, y in zip(r1, r2):
            for k in ("loss", "psnr"):
                if x[k]:
                    assert float(x[k]) == pytest.approx(float(y[k]), rel=1e-4, abs=1e-5), (name, k, x, y)
    assert not list(out.glob("*/.write-test*"))
    printed = [json.loads(ln) for ln in stdout.splitlines() if ln.startswith("{")]
    assert [r["rank"] for r in printed] == [0] and printed[0]["step"] == 4     # rank 0 speaks for the run


def test_a_one_process_run_resumes_under_two_ranks(stores, ddp_runs, tmp_path):
    from training.loop import train
    out, _ = ddp_runs
    train(layer_cfg(), stores[0], tmp_path / "one", progress=False)
    _close(_weights(tmp_path / "one" / "checkpoint.pt"), _weights(out / "from-one" / "checkpoint.pt"))
    assert [int(r["step"]) for r in _rows(out / "from-one" / "metrics.csv") if r["kind"] == "val"] == [2, 4]


def test_the_ranks_crops_in_a_step_are_the_one_process_batch(stores, ddp_runs):
    """What each rank trained on (recorded in the nbg run): half the global batch each, together the
    one-process batch's frames and crop origins in order."""
    from batches import get_batch
    from training.data import model_dataset
    from training.inputs import InputSpec
    out, _ = ddp_runs
    c = nbg_cfg()
    seen = [json.loads((out / "nbg" / f"seen-{r}.json").read_text()) for r in (0, 1)]
    ds = model_dataset(InputSpec("pixels", 1, c.spp), stores[0], "train", c.spp, c.crop, augment=True, seed=c.seed)
    assert len(seen[0]) == len(seen[1]) == c.steps
    for step in range(c.steps):
        whole, _ = get_batch(ds, c.seed, step, c.batch)
        assert all(len(s[step]["index"]) == c.batch // 2 for s in seen)
        assert seen[0][step]["index"] + seen[1][step]["index"] == whole["index"].tolist()
        assert seen[0][step]["origin"] + seen[1][step]["origin"] == whole["origin"].tolist()


def test_resume_under_two_ranks_is_exact(ddp_runs):
    out, _ = ddp_runs
    assert ckpt.load(out / "resumed" / "checkpoint.pt")["step"] == 4
    _close(_weights(out / "layer" / "checkpoint.pt"), _weights(out / "resumed" / "checkpoint.pt"), atol=0.0)
    rows = _rows(out / "resumed" / "metrics.csv")
    assert [int(r["step"]) for r in rows if r["kind"] == "val"] == [2, 4]


def test_each_rank_takes_its_slice_of_the_one_process_batch(stores):
    from batches import get_batch
    from training.data import model_dataset
    from training.inputs import InputSpec
    ds = model_dataset(InputSpec("samples", 1, 2), stores[0], "train", 2, 16, augment=True, seed=5)
    for step in (0, 3):                                          # step 3 is in the second epoch
        whole, epoch = get_batch(ds, 5, step, 4)
        parts = [get_batch(ds, 5, step, 4, rank=r, world=2) for r in (0, 1)]
        assert all(e == epoch for _, e in parts)
        for k in ("radiance", "reference", "index", "origin"):
            assert torch.equal(whole[k], torch.cat([p[k] for p, _ in parts]))
    with pytest.raises(DataError, match="divide evenly over the 3 ranks"):
        get_batch(ds, 5, 0, 4, rank=0, world=3)


def test_the_environment_chooses_single_or_distributed():
    assert from_env({}) == Dist() and not Dist().enabled
    d = from_env({"RANK": "1", "WORLD_SIZE": "2", "LOCAL_RANK": "1"})
    assert d == Dist(1, 2, 1) and d.enabled and not d.is_main and d.share([1, 2, 3, 4]) == [3, 4]
    with pytest.raises(ConfigError, match="RANK"):
        from_env({"RANK": "2", "WORLD_SIZE": "2", "LOCAL_RANK": "0"})
    from training.distributed import backend_for, rank_device
    assert rank_device("cuda", d) == "cuda:1" and rank_device("cpu", d) == "cpu"
    assert backend_for("cuda:1") == "nccl" and backend_for("cpu") == "gloo"
    with pytest.raises(ConfigError, match="--device cuda"):
        rank_device("cuda:0", d)


def _one_rank_group():
    import torch.distributed as td
    td.init_process_group("gloo", rank=0, world_size=1, store=td.HashStore())
    return td


def test_at_exit_the_ranks_meet_before_the_group_is_destroyed(monkeypatch, capsys):
    """Two gloo ranks that destroyed their groups at exit without meeting first aborted after a
    finished run ("terminate called without an active exception", 9 of 40 two-rank runs): the exit
    hook meets the others (a monitored barrier) and only then destroys; if the others never come it
    says so and leaves the group alone. A real one-rank gloo group, the calls spied on."""
    from training import distributed as D
    td = _one_rank_group()
    calls = []
    for name in ("monitored_barrier", "destroy_process_group"):
        real = getattr(td, name)
        monkeypatch.setattr(td, name, lambda *a, _n=name, _f=real, **k: (calls.append(_n), _f(*a, **k))[1])
    monkeypatch.setattr(D, "_FAILED", [])
    D._destroy()
    assert calls == ["monitored_barrier", "destroy_process_group"] and not td.is_initialized()

    td = _one_rank_group()
    calls.clear()

    def never(*a, **k):
        calls.append("monitored_barrier")
        raise RuntimeError("Rank 1 failed to pass monitoredBarrier in 60000 ms")
    monkeypatch.setattr(td, "monitored_barrier", never)
    try:
        D._destroy()
        assert calls == ["monitored_barrier"] and td.is_initialized()
        assert "did not reach the end of training" in capsys.readouterr().err
    finally:
        monkeypatch.undo()
        td.destroy_process_group()


def test_a_rank_ends_with_its_code_and_its_output_without_the_interpreters_teardown(tmp_path):
    """A rank with a live gloo group ends through ``end_process``: the group is met and destroyed,
    unflushed output still arrives, the exit status is the command's, and nothing of the
    interpreter's teardown runs (gloo's threads outlive the destroyed group, and a rank aborted in
    that teardown after a finished run). A real one-rank group in a child process."""
    script = tmp_path / "rank.py"
    script.write_text(
        "import atexit, sys\n"
        "import torch.distributed as td\n"
        "from training import distributed\n"
        "td.init_process_group('gloo', rank=0, world_size=1, store=td.HashStore())\n"
        "atexit.register(lambda: print('teardown ran', flush=True))\n"
        "print('results written')            # block-buffered into the pipe, not flushed\n"
        "distributed.end_process(int(sys.argv[1]) if len(sys.argv) > 1 else None)\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    for code, want in (("3", 3), (None, 0)):
        p = subprocess.run([sys.executable, str(script)] + ([code] if code else []), env=env, cwd=ROOT,
                           capture_output=True, text=True, timeout=120)
        assert p.returncode == want, p.stderr[-3000:]
        assert p.stdout == "results written\n", p.stdout + p.stderr[-3000:]


if __name__ == "__main__":
    from training import distributed
    _worker(sys.argv[1])
    distributed.end_process(0)
