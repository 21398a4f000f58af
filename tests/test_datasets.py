"""The datasets every input kind builds on (training.datasets): shapes, determinism, workers, augmentation
vs motion vectors, windows of clips, sample layers."""
from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from training.datasets import LayerFrames, SampleFrames, apply_augment, augment_image
from stores.errors import CropSizeError, SampleCountError, SplitError
from stores.reader import open_store
from stores.schema import StoreLayout
from stores.writer import open_or_create
from test_stores_synthetic import stored, synthetic_frame

ALL_OPS = list(itertools.product(range(4), (False, True), (False, True)))


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """6 frames: 3 clips x 2 frames, 20x24, 4 spp."""
    path = tmp_path_factory.mktemp("ds") / "s.zarr"
    w = open_or_create(path, StoreLayout(num_frames=6, height=20, width=24, spp=4, tile=16))
    for i in range(6):
        w.write_frame(i, synthetic_frame(i, 20, 24, 4, scene_seed=7 + i // 2, frame=i % 2, num_frames=2))
    return path


def test_sample_dataset_items(store):
    ds = SampleFrames(store, split=None, spp=3, crop=16, augment=False, seed=1)
    assert len(ds) == 6
    it = ds[2]
    assert it["radiance"].shape == (3, 3, 16, 16) and it["features"].shape == (3, 17, 16, 16)
    for k, c in (("reference", 3), ("albedo", 3), ("normal", 3), ("depth", 1), ("motion", 2), ("stderr", 3)):
        assert it[k].shape == (c, 16, 16), k
        assert it[k].dtype == torch.float32
    # the values are the stored frame's, channel-first, at the reported origin
    oy, ox = (int(v) for v in it["origin"])
    fr = synthetic_frame(2, 20, 24, 4, scene_seed=8, frame=0, num_frames=2)
    rad = stored("radiance", fr["radiance"], open_store(store).layout)     # compact2: 9-bit mantissa
    np.testing.assert_array_equal(it["radiance"].numpy(), rad[oy:oy + 16, ox:ox + 16, :3].transpose(2, 3, 0, 1))
    np.testing.assert_array_equal(it["reference"].numpy(), fr["reference"][oy:oy + 16, ox:ox + 16].transpose(2, 0, 1))
    full = SampleFrames(store, split=None, spp=4, crop=None, augment=False)[0]
    assert full["radiance"].shape == (4, 3, 20, 24)
    aligned = SampleFrames(store, split=None, spp=1, crop=8, augment=False, crop_align=8)
    origins = set()
    for epoch in range(4):
        aligned.set_epoch(epoch)
        origins |= {tuple(int(v) for v in aligned[i]["origin"]) for i in range(6)}
    assert all(y % 8 == 0 and x % 8 == 0 for y, x in origins) and len(origins) > 1


def test_determinism_epochs_and_workers(store):
    ds = SampleFrames(store, split=None, spp=2, crop=8, augment=True, seed=5)
    a = [ds[i] for i in range(len(ds))]
    b = [SampleFrames(store, split=None, spp=2, crop=8, augment=True, seed=5)[i] for i in range(len(ds))]
    for x, y in zip(a, b):
        for k in x:
            assert torch.equal(x[k], y[k]), k
    ds.set_epoch(1)
    c = [ds[i] for i in range(len(ds))]
    assert any(not torch.equal(x["origin"], y["origin"]) or not torch.equal(x["radiance"], y["radiance"])
               for x, y in zip(a, c))
    ds.set_epoch(0)
    serial = list(torch.utils.data.DataLoader(ds, batch_size=2, num_workers=0))
    parallel = list(torch.utils.data.DataLoader(ds, batch_size=2, num_workers=2))
    for x, y in zip(serial, parallel):
        for k in x:
            assert torch.equal(x[k], y[k]), k


def _shifted_pair(h, w, mx, my, seed=0):
    """prev, cur (3,h,w) with cur[y, x] = prev-canvas[y + my, x + mx], i.e. motion (p_prev - p_cur) = (mx, my)."""
    rng = np.random.default_rng(seed)
    canvas = rng.random((3, h + 8, w + 8)).astype(np.float32)
    prev = canvas[:, 4:4 + h, 4:4 + w]
    cur = canvas[:, 4 + my:4 + my + h, 4 + mx:4 + mx + w]
    return torch.from_numpy(prev.copy()), torch.from_numpy(cur.copy())


def _check_motion_consistent(prev, cur, motion):
    """Every pixel p of cur equals prev at p + motion(p) (where that lies inside)."""
    _, h, w = cur.shape
    checked = 0
    for y in range(h):
        for x in range(w):
            mx, my = (int(round(float(v))) for v in motion[:, y, x])
            py, px = y + my, x + mx
            if 0 <= py < h and 0 <= px < w:
                assert torch.equal(cur[:, y, x], prev[:, py, px]), (y, x, mx, my)
                checked += 1
    assert checked > h * w // 2


@pytest.mark.parametrize("op", ALL_OPS)
def test_augmentation_keeps_motion_consistent_with_image(op):
    h, w, mx, my = 10, 12, 2, -1
    prev, cur = _shifted_pair(h, w, mx, my)
    motion = torch.tensor([float(mx), float(my)])[:, None, None].expand(2, h, w).clone()
    _check_motion_consistent(prev, cur, motion)          # the construction itself
    feats = torch.zeros(1, 17, h, w)
    feats[:, 11:13] = motion
    feats[:, 14:16] = torch.tensor([0.3, -0.4])[:, None, None]
    normal = torch.tensor([0.0, 0.6, 0.8])[:, None, None].expand(3, h, w).clone()
    a = apply_augment({"prev": prev, "cur": cur, "motion": motion, "features": feats, "normal": normal}, op)
    _check_motion_consistent(a["prev"], a["cur"], a["motion"])
    assert torch.equal(a["features"][0, 11:13], a["motion"])            # per-sample motion follows too
    lens = a["features"][0, 14:16, 0, 0]
    assert torch.allclose(lens.norm(), torch.tensor(0.5))              # a lens position stays on the lens
    assert torch.equal(a["normal"], augment_image(normal, op))         # world-space normals only move
    if op == (0, False, False):
        assert torch.equal(a["cur"], cur)


def test_clip_dataset_augmentation_end_to_end(tmp_path):
    """Frames written to a store with known motion; augmented windows of a clip stay consistent."""
    h = w = 12
    mx, my = -2, 1
    prev, cur = _shifted_pair(h, w, mx, my, seed=3)
    wr = open_or_create(tmp_path / "m.zarr", StoreLayout(num_frames=2, height=h, width=w, spp=2, tile=8))
    for t, img in enumerate((prev, cur)):
        fr = synthetic_frame(1, h, w, 2, scene_seed=42, frame=t, num_frames=2, motion=True)
        fr["reference"] = img.numpy().transpose(1, 2, 0).copy()
        fr["guides_motion"][...] = (mx, my)
        fr["features"][..., 11:13] = (mx, my)
        wr.write_frame(t, fr)
    ds = SampleFrames(tmp_path / "m.zarr", split=None, frames=2, spp=2, crop=None, augment=True, seed=0)
    assert len(ds) == 1
    seen = set()
    for epoch in range(12):
        ds.set_epoch(epoch)
        it = ds[0]
        assert it["radiance"].shape == (2, 2, 3, h, w) and it["motion"].shape == (2, 2, h, w)
        assert it["index"].tolist() == [0, 1]
        _check_motion_consistent(it["reference"][0], it["reference"][1], it["motion"][1])
        assert torch.equal(it["features"][1, 0, 11:13], it["motion"][1])
        seen.add(tuple(int(v) for v in it["motion"][1, :, 0, 0]))
    assert len(seen) >= 3                                # augmentation really rotated/flipped


def test_layer_frames_hold_the_stored_layers(tmp_path):
    """Layer n holds value (n+1)*[1,2,3]: the items carry the stored layers, their spp and the budget."""
    lay = StoreLayout(num_frames=1, height=8, width=8, spp=2, tile=8)
    wr = open_or_create(tmp_path / "l.zarr", lay)
    fr = synthetic_frame(0, 8, 8, 2)
    fr["layers"] = np.stack([np.full((8, 8, 3), n + 1.0, np.float32) * np.float32([1, 2, 3]) for n in range(6)])
    wr.write_frame(0, fr)
    it = LayerFrames(tmp_path / "l.zarr", split=None, spp=13, crop=None, augment=False)[0]
    assert torch.equal(it["layers"], torch.from_numpy(fr["layers"].transpose(0, 3, 1, 2)))
    assert it["layer_spp"].tolist() == [1, 2, 4, 8, 16, 32] and float(it["spp"]) == 13.0
    with pytest.raises(SampleCountError, match="1..63"):
        LayerFrames(tmp_path / "l.zarr", split=None, spp=64, crop=None)


def test_clip_windows(store):
    """Windows of consecutive frames of one clip, one ending on each frame; evaluation's also shorter ones."""
    ds = SampleFrames(store, split=None, frames=2, spp=1, crop=8, augment=False)
    assert len(ds) == 3 and [list(w) for w in ds.windows] == [[0, 1], [2, 3], [4, 5]]
    it = ds[1]
    assert it["radiance"].shape == (2, 1, 3, 8, 8) and it["reference"].shape == (2, 3, 8, 8)
    assert it["index"].tolist() == [2, 3]
    one = SampleFrames(store, split=None, spp=1, crop=8, augment=False)[3]      # a single frame: no T axis
    assert torch.equal(it["radiance"][1], one["radiance"]) and one["radiance"].shape == (1, 3, 8, 8)
    every = SampleFrames(store, split=None, frames=2, spp=1, crop=8, augment=False, full_windows=False)
    assert [list(w) for w in every.windows] == [[0], [0, 1], [2], [2, 3], [4], [4, 5]]
    with pytest.raises(SplitError, match="consecutive"):
        SampleFrames(store, split=None, frames=3, spp=2, crop=8)


def test_dataset_bad_arguments(store):
    with pytest.raises(SampleCountError, match="1..4"):
        SampleFrames(store, split=None, spp=5, crop=8)
    with pytest.raises(CropSizeError, match="20x24"):
        SampleFrames(store, split=None, spp=2, crop=21)
    with pytest.raises(SplitError, match="unknown split"):
        SampleFrames(store, split="holdout", spp=2, crop=8)
