"""The training loop on a tiny real Zarr store (synthetic frames written by stores.writer):
loss goes down, a fixed seed reproduces a run, a resumed run equals an uninterrupted one, checkpoints
refuse mismatches, and the CLI contract (train / evaluate) writes what it promises."""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import torch

from training import checkpoint as ckpt
from training.config import TrainConfig
from training.errors import CheckpointError, ConfigError
from training.loop import train

TINY = dict(embed=8, context=8, kernel_size=5, partition_hidden=(8,), kernel_hidden=(8,),
            unet_encoder=((8,), (8,)), unet_bottleneck=(8,), unet_decoder=((8,), (8,)))


def make_store(path, h=32, w=32, spp=2, per_split=(4, 2, 2)):
    """A real store with ``per_split`` frames in train/val/test (scenes chosen by the store's split hash)."""
    from stores.reader import split_of_clip
    from stores.schema import StoreLayout
    from stores.writer import open_or_create
    from test_stores_synthetic import synthetic_frame

    want = dict(zip(("train", "val", "test"), per_split))
    seeds = []
    seed = 0
    while any(want.values()):
        s = split_of_clip(seed)
        if want.get(s, 0) > 0:
            want[s] -= 1
            seeds.append(seed)
        seed += 1
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


def test_resume_refuses_other_settings_and_schema(store, tmp_path):
    train(cfg(steps=1), store, tmp_path / "r", progress=False)
    with pytest.raises(CheckpointError, match="lr"):
        train(cfg(steps=2, lr=0.001), store, tmp_path / "r", progress=False)
    ck = ckpt.load(tmp_path / "r" / "checkpoint.pt")
    with pytest.raises(CheckpointError, match="schema version"):
        ckpt.check_store(ck, ck["store"]["schema_version"] + 1)


def test_loss_decreases_on_the_store(store, tmp_path):
    """A few dozen steps of a tiny pixelgather on real (synthetic) frames lower the validation loss."""
    c = cfg(model="pixelgather", model_cfg={k: v for k, v in TINY.items() if k != "partition_hidden"},
            steps=60, warmup=5, val_every=60, checkpoint_every=60, batch=2, crop=24, val_crop=32, val_frames=2)
    from training.data import sample_dataset
    from training.loop import validate
    from training.losses import build_loss
    from training.models import build
    torch.manual_seed(c.seed)
    before = validate(build(c.model, **c.model_cfg), sample_dataset(store, "val", 2, 32, False, c.seed),
                      build_loss("smape"), torch.device("cpu"), 2)
    res = train(c, store, tmp_path / "p", progress=False)
    assert res["val"]["loss"] < before["loss"] * 0.9


def test_warmup_ramps_the_learning_rate():
    from training.loop import warmup_lr
    assert [warmup_lr(1e-3, 4, s) for s in range(6)] == pytest.approx([2.5e-4, 5e-4, 7.5e-4, 1e-3, 1e-3, 1e-3])
    assert warmup_lr(1e-3, 0, 0) == 1e-3
    with pytest.raises(ConfigError, match="warmup"):
        TrainConfig(warmup=-1)
