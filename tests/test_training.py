"""The training loop on a tiny real Zarr store (synthetic frames written by stores.writer):
loss goes down, a fixed seed reproduces a run, a resumed run equals an uninterrupted one, checkpoints
refuse mismatches, and the CLI contract (train / evaluate) writes what it promises."""
from __future__ import annotations

import csv
import os
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from training import checkpoint as ckpt
from training.config import TrainConfig
from training.errors import CheckpointError, ConfigError
from training.loop import train

TINY = dict(embed=8, context=8, kernel_size=5, partition_hidden=(8,), kernel_hidden=(8,),
            unet_encoder=((8,), (8,)), unet_bottleneck=(8,), unet_decoder=((8,), (8,)))


def seeds_by_split(per_split, start: int = 0) -> list[int]:
    """The first scene seeds from ``start`` that the store's split hash puts ``per_split`` (train, val,
    test) in each split."""
    from stores.reader import split_of_clip
    want = dict(zip(("train", "val", "test"), per_split))
    seeds, seed = [], start
    while any(want.values()):
        s = split_of_clip(seed)
        if want.get(s, 0) > 0:
            want[s] -= 1
            seeds.append(seed)
        seed += 1
    return seeds


def make_store(path, h=32, w=32, spp=2, per_split=(4, 2, 2)):
    """A real store with ``per_split`` frames in train/val/test (scenes chosen by the store's split hash)."""
    from stores.schema import StoreLayout
    from stores.writer import open_or_create
    from test_stores_synthetic import synthetic_frame

    seeds = seeds_by_split(per_split)
    layout = StoreLayout(num_frames=len(seeds), height=h, width=w, spp=spp, tile=16)
    writer = open_or_create(str(path), layout, {"test": True})
    for i, s in enumerate(seeds):
        fr = synthetic_frame(s, h, w, spp, sun=False)
        writer.write_frame(i, fr)
    return str(path)


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return make_store(tmp_path_factory.mktemp("store") / "tiny.zarr")


def cfg(**kw):
    base = dict(model="layer", model_cfg=TINY, steps=4, batch=2, crop=16, spp=2, val_every=2, val_frames=1,
                val_crop=16, log_every=1, checkpoint_every=2, lr=0.005, seed=3)
    base.update(kw)
    return TrainConfig(**base)


def _weights(path):
    return ckpt.load(path)["state_dict"]


def test_config_validates_and_round_trips():
    c = cfg()
    assert TrainConfig.from_dict(c.to_dict()) == c
    with pytest.raises(ConfigError, match="lr"):
        cfg(lr=0)
    with pytest.raises(ConfigError, match="loss"):
        cfg(loss="nope")
    with pytest.raises(ConfigError, match="unknown"):
        TrainConfig.from_dict({"modle": "layer"})


def test_train_writes_checkpoint_and_log(store, tmp_path):
    res = train(cfg(steps=4), store, tmp_path / "run", progress=False)
    assert res["step"] == 4
    ck = ckpt.load(tmp_path / "run" / "checkpoint.pt")
    assert ck["step"] == 4 and ck["model"] == "layer" and ck["store"]["schema_version"] >= 1
    assert ck["model_config"]["kernel_size"] == 5
    rows = list(csv.DictReader(open(tmp_path / "run" / "metrics.csv")))
    assert [int(r["step"]) for r in rows if r["kind"] == "train"] == [1, 2, 3, 4]
    val = [r for r in rows if r["kind"] == "val"]
    assert len(val) == 2 and all(np.isfinite(float(r["relmse"])) for r in val)
    model = ckpt.build_model(ck)
    assert not model.training
    assert (torch.tensor([1e-20]) * 1e-20).item() == 0.0     # training flushes denormals (2x faster steps)


def test_seconds_stops_the_run_on_time_with_a_checkpoint_and_the_loaders_record(store, tmp_path):
    """``train --seconds``: the run stops once that long has passed (far short of its steps), writes its
    checkpoint, and returns the loader's wait as a share of the steps' time; the same run resumes."""
    c = cfg(steps=100000, val_every=0, checkpoint_every=100000, log_every=5)
    res = train(c, store, tmp_path / "run", progress=False, seconds=1.0)
    assert 2 <= res["step"] < 100000 and res["seconds"] < 60
    assert ckpt.load(tmp_path / "run" / "checkpoint.pt")["step"] == res["step"]
    feed = res["feed"]
    assert feed["steps"] == res["step"] - 1 and 0 <= feed["wait_share"] <= 1 and feed["steps_per_s"] > 0
    again = train(c, store, tmp_path / "run", progress=False, seconds=0.5)
    assert again["step"] > res["step"]
    with pytest.raises(ConfigError, match="--seconds"):
        train(c, store, tmp_path / "other", progress=False, seconds=0)


def test_seed_reproduces_and_resume_is_exact(store, tmp_path):
    train(cfg(steps=4), store, tmp_path / "a", progress=False)
    train(cfg(steps=4), store, tmp_path / "b", progress=False)
    wa, wb = _weights(tmp_path / "a" / "checkpoint.pt"), _weights(tmp_path / "b" / "checkpoint.pt")
    assert all(torch.equal(wa[k], wb[k]) for k in wa)
    # interrupted after 3 steps (checkpoint at step 3), then resumed to 4: bit-identical
    r1 = train(cfg(steps=4, checkpoint_every=100), store, tmp_path / "c", progress=False, stop_after=3)
    assert r1["step"] == 3 and ckpt.load(tmp_path / "c" / "checkpoint.pt")["step"] == 3
    r2 = train(cfg(steps=4, checkpoint_every=100), store, tmp_path / "c", progress=False)
    assert r2["step"] == 4
    wc = _weights(tmp_path / "c" / "checkpoint.pt")
    assert all(torch.equal(wa[k], wc[k]) for k in wa)
    rows = list(csv.DictReader(open(tmp_path / "c" / "metrics.csv")))
    assert [int(r["step"]) for r in rows if r["kind"] == "train"] == [1, 2, 3, 4]
    # a different seed gives different weights
    train(cfg(steps=1, seed=4), store, tmp_path / "d", progress=False)
    wd = _weights(tmp_path / "d" / "checkpoint.pt")
    assert not all(torch.equal(wa[k], wd[k]) for k in wa)


def test_resume_refuses_other_settings(store, tmp_path):
    train(cfg(steps=1), store, tmp_path / "r", progress=False)
    with pytest.raises(CheckpointError, match="lr"):
        train(cfg(steps=2, lr=0.001), store, tmp_path / "r", progress=False)
    # the same store upgraded from an older schema version (python -m stores upgrade) is the same store;
    # another layout is not
    from training.loop import check_same_store
    ck = ckpt.load(tmp_path / "r" / "checkpoint.pt")
    old = {**ck, "store": {**ck["store"], "schema_version": 2}}
    check_same_store(old, ck["store"], "r")
    with pytest.raises(CheckpointError, match="layout"):
        check_same_store(old, {**ck["store"], "layout": {**ck["store"]["layout"], "height": 99}}, "r")


def test_loss_decreases_on_the_store(store, tmp_path):
    """A few dozen steps of a tiny pixelgather on real (synthetic) frames lower the validation loss."""
    c = cfg(model="pixelgather", model_cfg={k: v for k, v in TINY.items() if k != "partition_hidden"},
            steps=60, warmup=5, val_every=60, checkpoint_every=60, batch=2, crop=24, val_crop=32, val_frames=2)
    from training.data import model_dataset
    from training.inputs import InputSpec
    from training.loop import validate
    from training.losses import build_loss
    from training.models import build
    torch.manual_seed(c.seed)
    before = validate(build(c.model, **c.model_cfg), model_dataset(InputSpec("samples", 1, 2), store, "val", 2, 32, False, c.seed),
                      build_loss("smape"), torch.device("cpu"), 2)
    res = train(c, store, tmp_path / "p", progress=False)
    assert res["val"]["loss"] < before["loss"] * 0.9


def test_warmup_ramps_the_learning_rate():
    from training.loop import warmup_lr
    assert [warmup_lr(1e-3, 4, s) for s in range(6)] == pytest.approx([2.5e-4, 5e-4, 7.5e-4, 1e-3, 1e-3, 1e-3])
    assert warmup_lr(1e-3, 0, 0) == 1e-3
    with pytest.raises(ConfigError, match="warmup"):
        TrainConfig(warmup=-1)


# -- input kinds and the DataLoader -----------------------------------------------------------------

def test_pixel_frames_are_the_mean_of_the_first_samples_with_their_features(store):
    from stores.reader import open_store
    from training.inputs import KINDS, InputSpec
    from training.data import model_dataset
    st = open_store(store)
    ds = model_dataset(InputSpec("pixels", 1, 1), st, "train", 1, None, augment=False, seed=0)
    item = ds[0]
    i = int(item["index"])
    rad = st.read_array("inputs/radiance", i)                      # (S, 3, H, W)
    feat = st.read_array("inputs/features", i)
    assert torch.allclose(item["radiance"], torch.from_numpy(rad[0]))
    assert torch.allclose(item["albedo"], torch.from_numpy(feat[0, 4:7].astype(np.float32)))
    assert torch.allclose(item["normal"], torch.from_numpy(feat[0, 0:3].astype(np.float32)))
    ds2 = model_dataset(InputSpec("pixels", 1, 2), st, "train", 2, None, augment=False, seed=0)
    assert torch.allclose(ds2[0]["radiance"], torch.from_numpy(rad[:2].mean(axis=0)), atol=1e-6)
    from training.errors import DataError
    with pytest.raises(DataError, match="1..2 samples"):
        model_dataset(InputSpec("pixels", 1, 1), st, "train", 3, None, augment=False, seed=0)
    # every kind builds its dataset on a real store
    for name, kind in KINDS.items():
        frames = 1
        try:
            d = model_dataset(InputSpec(name, frames, 1), st, "train", 1, 16, augment=True, seed=0)
        except DataError as e:            # clips need clips: the tiny store holds stills
            assert name == "clips" and "consecutive" in str(e)
            continue
        assert len(d) >= 1 and torch.isfinite(kind.target({k: v[None] for k, v in d[0].items()})).all()


def test_a_store_without_a_declared_array_is_refused_by_name(store, tmp_path):
    import shutil
    from training.errors import DataError
    cut = tmp_path / "cut.zarr"
    shutil.copytree(store, cut)
    shutil.rmtree(cut / "layers" / "radiance")
    from training.data import model_dataset
    from training.inputs import InputSpec
    with pytest.raises(DataError, match="layers/radiance"):
        model_dataset(InputSpec("sampled-layers", 1, 4), str(cut), "train", 4, 16, augment=False, seed=0)


def test_dataloader_workers_give_the_batches_of_the_pure_order(store):
    from batches import get_batch
    from training.data import batch_loader, model_dataset
    from training.inputs import InputSpec
    ds = model_dataset(InputSpec("pixels", 1, 1), store, "train", 1, 16, augment=True, seed=5)
    inproc = [get_batch(ds, 5, s, 2)[0] for s in range(4)]
    for workers in (0, 2):
        got = list(batch_loader(ds, 2, 5, 1, 4, workers))          # resumed at step 1
        assert len(got) == 3
        for a, b in zip(inproc[1:], got):
            assert all(torch.equal(a[k], b[k]) for k in a)
    assert not torch.equal(inproc[0]["radiance"], inproc[2]["radiance"])   # a new epoch: new crops


def test_per_pixel_models_train_and_resume_exactly(store, tmp_path):
    for name in ("nbg", "wskpn"):
        c = TrainConfig(model=name, steps=4, batch=2, crop=16, val_every=2, val_frames=1, val_crop=16,
                        checkpoint_every=100, seed=1)
        assert (c.spp, c.loss) == (1, {"nbg": "l1", "wskpn": "smape"}[name])
        train(c, store, tmp_path / f"{name}-a", progress=False)
        train(c, store, tmp_path / f"{name}-b", progress=False, stop_after=2)
        train(c, store, tmp_path / f"{name}-b", progress=False)
        wa = _weights(tmp_path / f"{name}-a" / "checkpoint.pt")
        wb = _weights(tmp_path / f"{name}-b" / "checkpoint.pt")
        assert all(torch.equal(wa[k], wb[k]) for k in wa)


def test_train_refuses_bad_requests_clearly(store, tmp_path):
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(ConfigError, match="is a file"):
        train(cfg(), store, f, progress=False)
    res = train(cfg(steps=0), store, tmp_path / "zero", progress=False)
    assert res["checkpoint"] is None and not (tmp_path / "zero" / "checkpoint.pt").exists()
    with pytest.warns(UserWarning, match="without validation"):
        res = train(cfg(steps=1, val_split="nope-split"), store, tmp_path / "noval", progress=False)
    assert res["step"] == 1 and res["val"] == {}


def test_resume_on_another_store_is_refused(store, tmp_path):
    train(cfg(steps=1), store, tmp_path / "r", progress=False)
    other = make_store(tmp_path / "other.zarr", per_split=(3, 1, 1))
    with pytest.raises(CheckpointError, match="another store"):
        train(cfg(steps=2), other, tmp_path / "r", progress=False)


def test_flagged_frames_are_refused_or_skipped_with_a_count(tmp_path):
    """A frame validate would flag (here: a negative reference) stops training and evaluation with a
    message naming it; --skip-bad-frames leaves it out with a warning."""
    from stores.writer import StoreWriter
    from test_stores_synthetic import synthetic_frame
    from training.errors import DataError
    from training.evaluate import evaluate
    from stores.reader import open_store
    path = make_store(tmp_path / "bad.zarr")
    st = open_store(path)
    def spoil(i):                        # the same scene (so the same split), one negative reference value
        fr = synthetic_frame(int(st.meta_column("scene_seed")[i]), 32, 32, 2, sun=False)
        fr["reference"][0, 0, 0] = -1.0
        StoreWriter(path).write_frame(i, fr)

    bad = st.frames_in_split("train")[0]
    spoil(bad)
    with pytest.raises(DataError, match=f"frame {bad}: reference has 1 negative"):
        train(cfg(steps=1), path, tmp_path / "r", progress=False)
    with pytest.warns(UserWarning, match="skipping 1 flagged frames"):
        res = train(cfg(steps=1, skip_bad_frames=True), path, tmp_path / "r2", progress=False)
    assert res["step"] == 1
    test_bad = st.frames_in_split("test")[0]
    spoil(test_bad)
    with pytest.raises(DataError, match="skip-bad-frames"):
        evaluate("input", path, split="test", with_flip=False)
    with pytest.warns(UserWarning, match="skipping"):
        r = evaluate("input", path, split="test", with_flip=False, skip_bad_frames=True)
    assert test_bad not in [f["index"] for f in r["frames"]]


def test_default_crop_is_128_or_the_whole_smaller_frame(store, tmp_path):
    c = TrainConfig(**{**cfg().to_dict(), "crop": None, "steps": 1})
    train(c, store, tmp_path / "c", progress=False)
    assert ckpt.load(tmp_path / "c" / "checkpoint.pt")["train_config"]["crop"] == 32
    train(c.replace(steps=2), store, tmp_path / "c", progress=False)      # resumes: the same resolved crop
    from training.errors import DataError
    with pytest.raises(DataError, match="does not fit"):
        train(cfg(crop=64), store, tmp_path / "big", progress=False)


def test_resume_takes_a_layout_recorded_before_the_encoding_field_as_lz4():
    """A checkpoint whose store layout predates ``encoding`` resumes on that store once a re-run of the
    dataset has recorded ``encoding: lz4`` in it; another encoding is another store."""
    from training.errors import CheckpointError
    from training.loop import check_same_store
    layout = {"num_frames": 28, "height": 64, "width": 64, "spp": 8, "layer_spp": [1, 2, 4, 8, 16, 32], "tile": 32,
              "radiance_encoding": "float32", "feature_dtype": "float16"}
    old = {"store": {"path": "/s.zarr", "layout": layout}}
    check_same_store(old, {"path": "/s.zarr", "layout": {**layout, "encoding": "lz4"}}, "ck.pt")
    with pytest.raises(CheckpointError, match="another store"):
        check_same_store(old, {"path": "/s.zarr", "layout": {**layout, "encoding": "compact"}}, "ck.pt")
    with pytest.raises(CheckpointError, match="another store"):
        check_same_store(old, {"path": "/s.zarr", "layout": {**layout, "height": 32, "encoding": "lz4"}}, "ck.pt")


@pytest.mark.parametrize("text, message", [
    ('{"layers": 2.5}', 'setting "layers" must be an integer, got 2.5'),
    ('{"layers": true}', 'setting "layers" must be an integer, got True'),
    ('{"kernel_sigma": NaN}', "holds NaN, which is not a JSON value"),
    ('{"kernel_sigma": "wide"}', 'setting "kernel_sigma" must be a finite number'),
    ('{"partition_hidden": [8, 2.5]}', 'setting "partition_hidden" must be a list of integers'),
])
def test_model_settings_are_type_checked_before_anything_trains(store, tmp_path, capsys, text, message):
    """An integer setting refuses 2.5 and true (not silently 2 or 1), NaN is a one-line error."""
    from training.__main__ import main
    out = tmp_path / "run"
    assert main(["train", "--model", "layer", "--store", store, "--out", str(out), "--steps", "1",
                 "--model-cfg", text, "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
    assert not (out / "checkpoint.pt").exists()


def test_a_batch_larger_than_the_store_draws_several_crops_per_frame(store, tmp_path):
    """--batch larger than the training items (a smoke store's 2 frames) trains, says so once, and every
    visit of a frame in an epoch draws its own crop."""
    from training.data import EpochBatches, epoch_keys
    n = 4                                       # the store's train split (make_store: per_split 4, 2, 2)
    keys = epoch_keys(n, 3, 0, 3)
    assert sorted(i for i, _ in keys) == sorted(list(range(n)) * 3)
    assert len(set(keys)) == len(keys)          # (item, draw) pairs never repeat: three crops of each frame
    assert epoch_keys(n, 3, 1, 1) == [(int(i), 1) for i in __import__("training.data", fromlist=["x"]).epoch_order(n, 3, 1)]
    batches = list(EpochBatches(n, 10, 3, 0, 3))
    assert [len(b) for b in batches] == [10, 10, 10]
    with pytest.warns(UserWarning, match=r"--batch 10 is larger than the 4 training items.*3 times") as rec:
        res = train(cfg(batch=10, steps=2, val_every=0), store, tmp_path / "big", progress=False)
    assert res["step"] == 2 and sum("larger than" in str(w.message) for w in rec) == 1


def _zarr_set(path, array, sel, value):
    """Write ``value`` into ``array`` of the store through zarr-python alone (past every check of ours)."""
    import zarr
    a = zarr.open_array(f"{path}/{array}", mode="r+").with_config({"write_empty_chunks": True})
    a[sel] = value


@pytest.mark.parametrize("array, sel, value, problem", [
    ("inputs/radiance", (None, 0, 0, 3, 3), np.inf, "radiance: 1 NaN/Inf values"),
    ("inputs/features", (None, 1, 2, 4, 4), np.nan, "features: 1 NaN/Inf values"),
    ("guides/depth", (None, 2, 2), -np.inf, "guides_depth: 1 NaN/Inf values"),
    ("reference/stderr", (None, 0, 1, 1), -0.5, "reference_stderr has 1 negative values"),
])
def test_train_and_evaluate_refuse_what_validate_flags_in_any_array(tmp_path, capsys, array, sel, value, problem):
    """NaN/Inf in the inputs, features or guides, or a negative reference stderr, written through
    zarr-python: validate flags the frame, and train and evaluate refuse it by name (exit 2) instead of
    quietly training on it; --skip-bad-frames leaves it out and names it."""
    from stores.reader import open_store
    from stores.validate import validate_store
    from training.__main__ import main
    path = make_store(tmp_path / "s.zarr")
    st = open_store(path)
    frame = st.frames_in_split("train")[1]
    _zarr_set(path, array, (frame,) + sel[1:], value)
    rep = validate_store(path)
    assert any(problem in p for p in rep.frames[frame].problems), rep.frames[frame].problems
    args = ["train", "--model", "nbg", "--store", path, "--out", str(tmp_path / "run"), "--steps", "1",
            "--crop", "16", "--batch", "2", "--no-progress", "--val-every", "0"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert f"frame {frame}: " in err and problem in err and "--skip-bad-frames" in err
    with pytest.warns(UserWarning, match=f"skipping 1 flagged frames .*frame {frame}:"):
        assert main(args + ["--skip-bad-frames"]) == 0
    capsys.readouterr()
    test_frame = st.frames_in_split("test")[0]
    _zarr_set(path, array, (test_frame,) + sel[1:], value)
    assert main(["evaluate", "--checkpoint", "input", "--store", path, "--out", str(tmp_path / "e.json"),
                 "--no-flip"]) == 2
    assert f"frame {test_frame}: " in capsys.readouterr().err


def test_evaluate_writes_strict_json(tmp_path):
    """Every number evaluate writes is finite JSON: a noiseless reference's infinite PSNR ceiling and a
    perfect PSNR are null, never NaN or Infinity (which JSON parsers other than Python's refuse)."""
    import json
    from training.evaluate import evaluate, write_json
    path = make_store(tmp_path / "s.zarr")
    from stores.reader import open_store
    for i in open_store(path).frames_in_split("test"):
        _zarr_set(path, "reference/stderr", (i,), 0.0)              # a reference without noise
    res = evaluate("input", path, split="test", with_flip=False)
    assert any(not np.isfinite(f["ref_psnr_ceiling"]) for f in res["frames"])
    write_json(res, tmp_path / "e.json")
    text = (tmp_path / "e.json").read_text()
    assert "NaN" not in text and "Infinity" not in text
    back = json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} in the JSON"))
    assert back["frames"][0]["ref_psnr_ceiling"] is None and back["mean"]["psnr"] is not None


def test_a_nan_loss_is_a_failed_run_not_a_bad_setting(store, tmp_path, capsys, monkeypatch):
    """A loss that becomes NaN ends the run with exit 1 (the run failed), not 2 (bad settings)."""
    import training.loop
    from training.__main__ import main
    real = training.loop.build_loss

    def nan_loss(name):
        fn = real(name)
        return lambda out, ref: fn(out, ref) * float("nan")
    monkeypatch.setattr(training.loop, "build_loss", nan_loss)
    assert main(["train", "--model", "layer", "--model-cfg", __import__("json").dumps(TINY), "--store", store,
                 "--out", str(tmp_path / "r"), "--steps", "2", "--crop", "16", "--batch", "2", "--spp", "2",
                 "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert "error: loss is nan (non-finite) at step 1; the loss is read from the device every 10 steps " \
           "(--log-every), here steps 1..2" in err


def test_ctrl_c_stops_training_with_130_and_no_traceback(store, tmp_path):
    """SIGINT to the training process group (a terminal's Ctrl-C reaches the DataLoader workers too):
    exit 130, one line saying how to resume, no traceback."""
    import json
    import signal
    import subprocess
    import sys
    import time
    out = tmp_path / "r"
    proc = subprocess.Popen([sys.executable, "-m", "training", "train", "--model", "layer", "--model-cfg",
                             json.dumps(TINY), "--store", store, "--out", str(out), "--steps", "100000",
                             "--crop", "16", "--batch", "2", "--spp", "2", "--workers", "1", "--checkpoint-every", "5"],
                            cwd=Path(__file__).resolve().parents[1], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)
    try:
        t0 = time.monotonic()
        while not (out / "checkpoint.pt").exists() and time.monotonic() - t0 < 120:
            time.sleep(0.2)
        assert (out / "checkpoint.pt").exists()
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "interrupted" in err and "resumes" in err


def _train_until_ctrl_c(store, tmp_path, workers: int, before_ctrl_c=None, *, ctrl_c=None, hook: str = "",
                        extra: tuple = ()) -> tuple[int, str, Path]:
    """``train`` (tiny layer model, a step a metrics line) in its own process group: once a few steps are
    logged, ``before_ctrl_c(proc, steps)`` if given, then ``ctrl_c(proc, steps)``, by default one SIGINT to
    the group (a terminal's Ctrl-C). ``proc``: a :class:`procs.Command` (its markers on stdout, lines to its
    stdin); ``hook``: Python code the process runs first (:func:`procs.python_m`); ``extra``: more train
    options (the last of two wins). Returns the exit code, stderr and the run's folder."""
    import json
    import time

    from procs import Command, kill_group, python_m
    out = tmp_path / "r"
    argv = python_m("training", hook) + [
        "train", "--model", "layer", "--model-cfg", json.dumps(TINY), "--store", store, "--out", str(out), "--steps",
        "100000", "--crop", "16", "--batch", "2", "--spp", "2", "--workers", str(workers), "--checkpoint-every",
        "100000", "--log-every", "1", "--no-progress", *extra]

    def steps():
        return len((out / "metrics.csv").read_text().splitlines()) if (out / "metrics.csv").exists() else 0
    proc = Command(argv)
    try:
        t0 = time.monotonic()
        while time.monotonic() - t0 < 120 and steps() < 4 and proc.poll() is None:
            time.sleep(0.1)                           # a few steps logged (one a step): training is under way
        if before_ctrl_c:
            before_ctrl_c(proc, steps)
        (ctrl_c or (lambda p, _: p.ctrl_c()))(proc, steps)
    except BaseException:
        kill_group(proc)
        raise
    code, _, err = proc.finish(timeout=60)
    return code, err, out


def test_a_ctrl_c_that_reaches_the_loader_workers_alone_does_not_stop_training(store, tmp_path):
    """The loader's workers ignore SIGINT: a terminal's Ctrl-C reaches them as well as the training process,
    and a worker that died of it before the training process shut the loader down ended the run in a
    traceback ("DataLoader worker ... exited unexpectedly", or multiprocessing's resource_sharer when it
    died mid-transfer). Deterministic here: SIGINT to the workers only, then training goes on; a Ctrl-C to
    the training process afterwards is the usual clean exit 130."""
    import signal
    import time

    import psutil

    def ctrl_c_to_the_loader_workers(proc, steps):
        loaders = psutil.Process(proc.pid).children()
        assert len(loaders) == 2, loaders
        for w in loaders:
            os.kill(w.pid, signal.SIGINT)
        t0, done = time.monotonic(), steps()
        while time.monotonic() - t0 < 60 and steps() < done + 3 and proc.poll() is None:
            time.sleep(0.1)
        assert proc.poll() is None and all(w.is_running() for w in loaders)   # training went on
    code, err, _ = _train_until_ctrl_c(store, tmp_path, 2, ctrl_c_to_the_loader_workers)
    assert code == 130 and "Traceback" not in err, err


@pytest.mark.parametrize("workers", [0, 1])
def test_ctrl_c_before_the_first_checkpoint_keeps_the_steps_done(store, tmp_path, workers):
    """Ctrl-C long before the first --checkpoint-every step: the step under way finishes, checkpoint.pt is
    written at it and the line says so (exit 130, no traceback, the loader's workers' included); the same
    command resumes from that step. Before, the line promised a checkpoint that did not exist."""
    import torch
    from procs import last_line
    code, err, out = _train_until_ctrl_c(store, tmp_path, workers)
    assert code == 130, err
    assert "Traceback" not in err and "leaked semaphore" not in err, err
    line = [ln for ln in err.splitlines() if ln.startswith("interrupted")]
    assert len(line) == 1 and "checkpoint.pt holds it" in line[0] and "resumes" in line[0], err
    step = int(line[0].split("at step ")[1].split(":")[0])
    assert step >= 3 and torch.load(out / "checkpoint.pt", weights_only=False)["step"] == step
    last_line(err, line[0])                         # nothing after it


# Points inside `train` where the test holds the process (a line on stdout, then a wait for one on stdin)
# while it presses Ctrl-C: the stop's checkpoint write, the loader's shut-down, the interpreter's exit.
HOLD = {
    "checkpoint write": """
import sys
import training.checkpoint as ck
write = ck._write
def held(path, payload):
    print("held: checkpoint write", flush=True)
    sys.stdin.readline()
    write(path, payload)
ck._write = held
""",
    "loader shut-down": """
import sys
from torch.utils.data import dataloader
shut_down = dataloader._MultiProcessingDataLoaderIter._shutdown_workers
def held(self):
    if not self._shutdown:
        print("held: loader shut-down", flush=True)
        sys.stdin.readline()
    shut_down(self)
dataloader._MultiProcessingDataLoaderIter._shutdown_workers = held
""",
    "exit": """
import atexit
import sys
def held():
    print("held: exit", flush=True)
    sys.stdin.readline()
atexit.register(held)
""",
}


@pytest.mark.parametrize("where", list(HOLD))
def test_ctrl_c_pressed_again_while_train_stops_changes_nothing(store, tmp_path, where):
    """Ctrl-C, then four more presses 0.1 s apart while the run stops: during the checkpoint write of the
    step it stops at, during the loader's shut-down before it, or during the interpreter's exit (each held
    by the test until the presses are sent). The write completes, the run stops at that step, and its one
    line is the last thing on stderr (exit 130). Before, a press during the write cut it short (the steps
    since the last checkpoint were lost, here every one), one during the shut-down printed "Exception
    ignored in ... __del__" ending at the loop's handler, and one during the exit "Exception ignored in
    atexit callback"."""
    from procs import last_line

    def ctrl_c(proc, steps):
        proc.ctrl_c()
        proc.wait_for(f"held: {where}")
        proc.ctrl_c(presses=4)
        proc.send()
    code, err, out = _train_until_ctrl_c(store, tmp_path, 1, ctrl_c=ctrl_c, hook=HOLD[where])
    assert code == 130, err
    step = ckpt.load(out / "checkpoint.pt")["step"]
    assert step >= 3          # the steps logged before the first press (it may land between two steps)
    last_line(err, f"interrupted: at step {step}: {out / 'checkpoint.pt'} holds it, and the same command resumes "
                   "from there")


def test_ctrl_c_twice_before_the_step_under_way_ends_stops_at_once(store, tmp_path):
    """Ctrl-C while the step under way waits for its batch (the test has stopped the loader's worker), then
    again: the first press waits for the step, the second stops the run at once, without that step and in
    one line naming the checkpoint that is kept (the last --checkpoint-every step); exit 130, nothing after
    the line."""
    import time

    import psutil
    from procs import last_line

    def ctrl_c_twice(proc, steps):
        worker, = psutil.Process(proc.pid).children()
        worker.suspend()
        n = -1
        while steps() != n:                         # the batches the worker had made are used up
            n = steps()
            time.sleep(1.0)
        proc.ctrl_c()
        time.sleep(1.0)
        assert proc.poll() is None and steps() == n     # the first press waits for the step under way
        proc.ctrl_c()
        time.sleep(0.5)
        worker.resume()
    code, err, out = _train_until_ctrl_c(store, tmp_path, 1, ctrl_c=ctrl_c_twice, extra=("--checkpoint-every", "2"))
    assert code == 130, err
    kept = ckpt.load(out / "checkpoint.pt")["step"]
    logged = [int(r["step"]) for r in csv.DictReader(open(out / "metrics.csv")) if r["kind"] == "train"]
    assert kept % 2 == 0 and 2 <= kept <= max(logged), (kept, logged)
    last_line(err, f"interrupted: {out / 'checkpoint.pt'} (its last --checkpoint-every step) is kept, and the same "
                   "command resumes from it")


def test_ctrl_c_pressed_during_the_imports_is_one_line(store, tmp_path):
    """Five presses 0.1 s apart while `train` imports torch (from the moment the process has mapped
    libtorch): exit 130 and one line. Before, a KeyboardInterrupt traceback and no line."""
    import json

    from procs import Command, last_line, python_m
    proc = Command(python_m("training") + ["train", "--model", "layer", "--model-cfg", json.dumps(TINY), "--store",
                                           store, "--out", str(tmp_path / "r"), "--steps", "5", "--no-progress"])
    def mapped() -> str:
        try:
            return Path(f"/proc/{proc.pid}/maps").read_text()
        except OSError:                             # it ended
            return ""
    proc.ctrl_c_when(lambda: "libtorch" in mapped(), poll=0.005)
    code, _, err = proc.finish()
    assert code == 130, err
    last_line(err, "interrupted: before training started: nothing was written")
    assert not (tmp_path / "r").exists()


def test_an_incomplete_frame_is_refused_by_name_or_left_out_and_recorded(tmp_path, capsys):
    """A finished store with one frame's completion flag turned off (validate: exit 1) is refused by train
    and evaluate, naming the frame and --skip-bad-frames, instead of being used without it; with the flag
    the frame is left out in one warning line and recorded: in the checkpoint and evaluate's JSON."""
    from stores.reader import open_store
    from training.__main__ import main
    path = make_store(tmp_path / "s.zarr")
    frame = open_store(path).frames_in_split("train")[1]
    _zarr_set(path, "status/complete", frame, False)
    args = ["train", "--model", "nbg", "--store", path, "--out", str(tmp_path / "run"), "--steps", "1",
            "--crop", "16", "--batch", "2", "--no-progress", "--val-every", "0"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert f"frame {frame}: incomplete" in err and "--skip-bad-frames" in err
    with pytest.warns(UserWarning, match=f"skipping 1 flagged frames .*frame {frame}: incomplete"):
        assert main(args + ["--skip-bad-frames"]) == 0
    assert ckpt.load(tmp_path / "run" / "checkpoint.pt")["store"]["left_out"] == {str(frame): ["incomplete"]}
    ev = ["evaluate", "--checkpoint", "input", "--store", path, "--split", "train", "--out", str(tmp_path / "e.json"),
          "--no-flip"]
    assert main(ev) == 2
    assert f"frame {frame}: incomplete" in capsys.readouterr().err
    with pytest.warns(UserWarning, match=f"frame {frame}: incomplete"):
        assert main(ev + ["--skip-bad-frames"]) == 0
    res = json.loads((tmp_path / "e.json").read_text())
    assert res["left_out"] == {str(frame): ["incomplete"]} and frame not in [f["index"] for f in res["frames"]]


def test_train_options_are_the_config_fields_and_the_shared_ones_come_from_them():
    """train's command line is TrainConfig's fields (a new setting is an option without a second
    definition), and evaluate, bench and denoise take --device, --precision and --compile from the same
    fields, with the same defaults and choices."""
    from dataclasses import fields

    from training.commands import parser
    from training.cli import HIDDEN
    base = ["--model", "nbg", "--store", "s"]
    a = parser().parse_args(["train", *base, "--val-crop", "64", "--grad-clip-norm", "0.5", "--compile"])
    names = {f.name for f in fields(TrainConfig)} - HIDDEN
    assert names <= set(vars(a)) and a.val_crop == 64 and a.grad_clip_norm == 0.5 and a.compile is True
    from training.cli import config_from
    assert config_from(a, {}).val_crop == 64
    runs = {"evaluate": ["--checkpoint", "c", "--store", "s", "--out", "o"],
            "bench": [], "denoise": ["--checkpoint", "c", "--out", "o"]}
    for cmd, args in runs.items():
        ns = parser().parse_args([cmd, *args])
        assert (ns.device, ns.precision, ns.compile) == ("auto", "auto", False), cmd
        with pytest.raises(SystemExit):
            parser().parse_args([cmd, *args, "--precision", "fp8"])


def test_a_notice_of_the_command_line_is_one_plain_line(tmp_path):
    """`train --skip-bad-frames` names the frame it leaves out on one line, ``warning: skipping 1 flagged frames
    ...``, as the command line's other notices read (before: Python's ``FILE:LINE: UserWarning: ...`` and the
    source line of the warnings.warn call)."""
    import subprocess
    import sys
    from stores.reader import open_store
    path = make_store(tmp_path / "s.zarr", h=16, w=16, per_split=(2, 1, 1))
    frame = open_store(path).frames_in_split("train")[1]
    _zarr_set(path, "reference/stderr", (frame, 0, 1, 1), -0.5)
    r = subprocess.run([sys.executable, "-m", "training", "train", "--model", "nbg", "--store", path, "--out",
                        str(tmp_path / "run"), "--steps", "1", "--crop", "16", "--batch", "1", "--workers", "0",
                        "--no-progress", "--val-every", "0", "--skip-bad-frames"], cwd=Path(__file__).parents[1],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    said = [x for x in r.stderr.splitlines() if "flagged" in x]
    assert len(said) == 1 and said[0].startswith("warning: skipping 1 flagged frames of split 'train'"), r.stderr
    assert f"frame {frame}: reference_stderr has 1 negative" in said[0]
    assert "UserWarning" not in r.stderr and "warnings.warn" not in r.stderr and ".py:" not in r.stderr, r.stderr
