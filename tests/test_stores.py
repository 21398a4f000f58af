"""Schema, writer and reader of the Zarr store: round trips, HDR extremes, append, bad input, xarray."""
from __future__ import annotations

import json

import numpy as np
import pytest
import zarr
from hypothesis import given, settings
from hypothesis import strategies as st

from stores import codecs, create, schema
from stores.contract import FEATURE_NAMES, FRAME_ARRAYS, FRAME_META
from stores.errors import (CropSizeError, ForeignStoreError, FrameIndexError, IncompleteFrameError,
                           SampleCountError, SchemaVersionError, StoreError, StoreLayoutError,
                           StoreNotFoundError, StoreValueError)
from stores.reader import open_store, split_of_clip
from stores.schema import StoreLayout
from stores.writer import StoreWriter, open_or_create
from test_stores_synthetic import stored, synthetic_frame

H, W, S = 20, 24, 4
LAYOUT = StoreLayout(num_frames=3, height=H, width=W, spp=S, tile=16)   # 16 does not divide 20 or 24


@pytest.fixture(params=["compact3", "compact2", "compact", "lz4"])
def store3(tmp_path, request):
    """Three frames, in a store of each encoding (``compact3`` is what a layout that leaves it open gets)."""
    path = tmp_path / "s.zarr"
    lay = LAYOUT if request.param == codecs.DEFAULT_ENCODING else StoreLayout(**{**LAYOUT.to_dict(),
                                                                                 "encoding": request.param})
    w = open_or_create(path, lay, {"seed": 1, "split": {"train": 0.5, "val": 0.25, "test": 0.25}})
    frames = [synthetic_frame(10 + i, H, W, S, sun=True) for i in range(3)]
    for i, fr in enumerate(frames):
        w.write_frame(i, fr)
    return path, frames


def _rel_err(a, b, floor=1e-6):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.max(np.abs(a - b) / np.maximum(np.abs(a), floor)))


def test_round_trip_every_array(store3):
    path, frames = store3
    s = open_store(path)
    assert s.num_frames == 3 and s.complete_frames() == [0, 1, 2]
    compact = {"reference", "reference_stderr", "camera_to_world", "world_to_clip"}
    lossless = {"compact3": compact, "compact2": compact, "compact": compact,
                "lz4": set(FRAME_ARRAYS) - {"features"}}[s.layout.encoding]
    root = zarr.open_group(str(path), mode="r")
    for i, fr in enumerate(frames):
        out = s.read_frame(i)
        for name in FRAME_ARRAYS:
            assert out[name].shape == fr[name].shape, name
            np.testing.assert_array_equal(out[name], stored(name, fr[name], s.layout), err_msg=name)
            if name in lossless:
                np.testing.assert_array_equal(out[name], fr[name], err_msg=name)
                continue
            # within the bound the array's attributes give (float16 features alone: 2**-11);
            # float16 subnormals (< 2**-14) 1e-7 absolute
            attrs = root[schema.ARRAY_BY_SOURCE[name].path].attrs
            rtol = attrs.get("max_rel_error", 2 ** -11)
            if "feature_precision" in attrs:         # compact2: each feature its own bound
                rtol = np.array([attrs["feature_precision"][f]["max_rel_error"] for f in FEATURE_NAMES])
            err = np.abs(out[name].astype(np.float64) - fr[name])
            assert (err <= rtol * np.abs(fr[name].astype(np.float64)) + 1e-7).all(), name
        meta = out["meta"]
        for k in FRAME_META:
            assert meta[k] == fr["meta"][k], k
        assert meta["clip_id"] == fr["meta"]["scene_seed"] and meta["complete"] and meta["error"] == ""


def test_crop_and_spp_match_full_frame_and_zarr_path(store3):
    path, frames = store3
    fast, slow = open_store(path), open_store(path, fast=False)
    crop = (3, 5, 15, 17)                         # crosses inner-chunk borders (tile 16)
    a = fast.read_frame(1, ["radiance", "features", "layers", "guides_depth"], crop=crop, spp=2)
    b = slow.read_frame(1, ["radiance", "features", "layers", "guides_depth"], crop=crop, spp=2)
    c = open_store(path, threads=2).read_frame(1, list(a), crop=crop, spp=2)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
        np.testing.assert_array_equal(a[k], c[k])
    lay = fast.layout
    np.testing.assert_array_equal(a["radiance"], stored("radiance", frames[1]["radiance"], lay)[3:18, 5:22, :2])
    np.testing.assert_array_equal(a["layers"], stored("layers", frames[1]["layers"], lay)[:, 3:18, 5:22])


def test_root_attributes_record_provenance(store3):
    path, _ = store3
    attrs = dict(zarr.open_group(str(path), mode="r").attrs)
    assert attrs["schema_version"] == schema.SCHEMA_VERSION
    assert attrs["config"]["seed"] == 1
    enc = attrs["layout"]["encoding"]
    assert enc in codecs.ENCODINGS                                     # recorded, decided
    assert StoreLayout.from_dict(attrs["layout"]) == StoreLayout(**{**LAYOUT.to_dict(), "encoding": enc})
    assert LAYOUT.resolved().encoding == codecs.DEFAULT_ENCODING
    assert "zarr" in attrs["package_versions"] and "numpy" in attrs["package_versions"]
    assert len(attrs["feature_names"]) == 17


def test_xarray_opens_every_group_with_named_dims(store3):
    xr = pytest.importorskip("xarray")
    path, frames = store3
    for g in schema.GROUPS:
        ds = xr.open_zarr(str(path), group=g, consolidated=False)
        assert ds.sizes["frame"] == 3, g
    ds = xr.open_zarr(str(path), group="inputs", consolidated=False)
    assert ds["radiance"].dims == ("frame", "sample", "rgb", "y", "x")
    assert list(ds["feature"].values[:4]) == ["normal_x", "normal_y", "normal_z", "depth"]
    # xarray (zarr-python) decodes the compact codecs too: float32 values, not codes
    np.testing.assert_array_equal(ds["radiance"].isel(frame=2).values,
                                  stored("radiance", frames[2]["radiance"], open_store(path).layout).transpose(2, 3, 0, 1))
    depth = xr.open_zarr(str(path), group="guides", consolidated=False)["depth"]
    assert depth.dims == ("frame", "y", "x")
    meta = xr.open_zarr(str(path), group="frames", consolidated=False)
    assert json.loads(str(meta["scene_json"].values[1]))["seed"] == 11


@pytest.mark.parametrize("encoding,codec_set", [("float32", "lz4"), ("float32", "compact"), ("float32", "compact2"),
                                                ("float32", "compact3"), ("log16", "lz4"), ("log16", "compact"),
                                                ("log16", "compact2"), ("log16", "compact3")])
def test_hdr_extremes_round_trip_without_inf(tmp_path, encoding, codec_set):
    lay = StoreLayout(num_frames=1, height=8, width=8, spp=4, tile=8, radiance_encoding=encoding, encoding=codec_set)
    w = open_or_create(tmp_path / "x.zarr", lay)
    fr = synthetic_frame(1, 8, 8, 4)
    vals = np.array([0.0, 1e-8, 1e5, 1e8], np.float32)
    fr["radiance"][...] = vals[np.arange(8 * 8 * 4 * 3) % 4].reshape(8, 8, 4, 3)
    fr["layers"][0, 0, 0] = [1e8, 1e-8, 0.0]
    fr["reference"][0, 0] = [1e8, 1e5, 1e-8]
    w.write_frame(0, fr)
    out = open_store(tmp_path / "x.zarr").read_frame(0)
    for k in ("radiance", "layers", "reference"):
        assert np.isfinite(out[k]).all(), k
    assert (out["radiance"][fr["radiance"] == 0] == 0).all()
    tol = {("float32", "lz4"): 0.0, ("float32", "compact"): 2 ** -10,
           ("float32", "compact2"): 2 ** -10, ("float32", "compact3"): 2 ** -10}.get((encoding, codec_set), 1e-3)
    nz = fr["radiance"] > 0
    assert _rel_err(fr["radiance"][nz], out["radiance"][nz]) <= tol
    assert out["radiance"].max() == pytest.approx(1e8, rel=tol)
    np.testing.assert_array_equal(out["layers"], stored("layers", fr["layers"], lay.resolved()))
    np.testing.assert_array_equal(out["reference"], fr["reference"])        # lossless in every encoding


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(min_value=2.0 ** -29, max_value=2.0 ** 33, allow_nan=False, width=32), min_size=1, max_size=50))
def test_log16_relative_error_property(values):
    x = np.array(values, np.float32)
    y = codecs.decode_log16(codecs.encode_log16(x))
    assert np.isfinite(y).all()
    assert np.all(np.abs(y.astype(np.float64) - x) <= codecs.LOG16_MAX_REL_ERROR * 1.001 * x + 1e-30)
    assert codecs.LOG16_MAX_REL_ERROR < 1e-3


def test_log16_special_values():
    x = np.array([0.0, -1.0, np.nan, np.inf, 1e30, 1e-20], np.float32)
    y = codecs.decode_log16(codecs.encode_log16(x))
    assert list(y[:3]) == [0.0, 0.0, 0.0]
    assert np.isfinite(y).all() and y[3] == y[4] == pytest.approx(2.0 ** codecs.LOG16_MAX_EXP, rel=1e-3)
    assert y[5] == pytest.approx(2.0 ** codecs.LOG16_MIN_EXP, rel=1e-3)


def test_rewrite_overwrites_cleanly(store3):
    path, frames = store3
    w = StoreWriter(path)
    new = synthetic_frame(99, H, W, S, sun=False)
    w.write_frame(1, new)
    st_ = open_store(path)
    out = st_.read_frame(1)
    np.testing.assert_array_equal(out["radiance"], stored("radiance", new["radiance"], st_.layout))
    np.testing.assert_array_equal(out["layers"], stored("layers", new["layers"], st_.layout))
    assert out["meta"]["scene_seed"] == 99
    np.testing.assert_array_equal(st_.read_frame(0)["radiance"], stored("radiance", frames[0]["radiance"], st_.layout))


def test_append_grows_the_store(store3):
    path, frames = store3
    w = open_or_create(path, LAYOUT.with_frames(5), {"seed": 2})
    assert w.num_frames == 5 and w.incomplete_frames() == [3, 4]
    w.write_frame(4, synthetic_frame(50, H, W, S))
    s = open_store(path)
    assert s.num_frames == 5 and s.complete_frames() == [0, 1, 2, 4]
    np.testing.assert_array_equal(s.read_frame(2)["radiance"], stored("radiance", frames[2]["radiance"], s.layout))
    assert s.attrs["config"] == {"seed": 2} and s.attrs["config_history"][0]["seed"] == 1
    # never shrinks
    assert open_or_create(path, LAYOUT.with_frames(2)).num_frames == 5


def test_failed_frame_is_recorded_and_refused(store3):
    path, _ = store3
    w = StoreWriter(path)
    w.mark_failed(2, RuntimeError("drjit ran out of memory"))
    assert not w.frame_complete(2) and w.incomplete_frames() == [2]
    assert w.errors() == {2: "RuntimeError: drjit ran out of memory"}
    with pytest.raises(IncompleteFrameError, match="out of memory"):
        open_store(path).read_frame(2)


def test_missing_foreign_and_wrong_version_stores(tmp_path, store3):
    with pytest.raises(StoreNotFoundError):
        open_store(tmp_path / "nope.zarr")
    with pytest.raises(FileNotFoundError):               # also the built-in
        open_store(tmp_path / "nope.zarr")
    zarr.open_group(str(tmp_path / "other.zarr"), mode="w").attrs["kind"] = "something-else"
    with pytest.raises(ForeignStoreError, match="not a denoise-datagen"):
        open_store(tmp_path / "other.zarr")
    (tmp_path / "plain").mkdir()
    with pytest.raises(ForeignStoreError, match="not a Zarr v3 group"):
        open_store(tmp_path / "plain")
    path, _ = store3
    zarr.open_group(str(path), mode="r+").attrs["schema_version"] = 99
    with pytest.raises(SchemaVersionError, match="version 99"):
        open_store(path)
    with pytest.raises(SchemaVersionError):
        open_or_create(path, LAYOUT)


def test_bad_reads_are_precise(store3):
    path, _ = store3
    s = open_store(path)
    with pytest.raises(SampleCountError, match="1..4"):
        s.read_frame(0, spp=5)
    with pytest.raises(CropSizeError, match="does not fit"):
        s.read_frame(0, crop=(0, 0, H + 1, 8))
    with pytest.raises(CropSizeError, match="leaves"):
        s.read_frame(0, crop=(10, 0, 16, 8))
    with pytest.raises(FrameIndexError):
        s.read_frame(3)
    with pytest.raises(StoreLayoutError, match="unknown frame array"):
        s.read_frame(0, ["colour"])


def test_writer_refuses_bad_frames(store3, tmp_path):
    path, _ = store3
    w = StoreWriter(path)
    fr = synthetic_frame(1, H, W + 1, S)
    with pytest.raises(StoreLayoutError, match="radiance"):
        w.write_frame(0, fr)
    fr = synthetic_frame(1, H, W, S)
    fr["features"][0, 0, 0, 3] = 1e6                      # depth beyond float16
    with pytest.raises(StoreValueError, match="depth"):
        w.write_frame(0, fr)
    del fr["meta"]["scene_seed"]
    with pytest.raises(StoreLayoutError, match="scene_seed"):
        w.write_frame(0, fr)
    with pytest.raises(FrameIndexError):
        w.write_frame(7, synthetic_frame(1, H, W, S))
    with pytest.raises(StoreLayoutError, match="height"):
        open_or_create(path, StoreLayout(num_frames=3, height=H + 2, width=W, spp=S, tile=16))
    with pytest.raises(StoreError, match="already exists"):
        create.create_store(path, LAYOUT)
    with pytest.raises(StoreLayoutError, match='"spp"'):
        StoreLayout(num_frames=1, height=4, width=4, spp=0)


def test_split_is_by_scene_and_deterministic(tmp_path):
    lay = StoreLayout(num_frames=12, height=8, width=8, spp=2, tile=8)
    w = open_or_create(tmp_path / "c.zarr", lay)
    for i in range(12):                                    # 4 clips x 3 frames
        w.write_frame(i, synthetic_frame(i, 8, 8, 2, scene_seed=100 + i // 3, frame=i % 3, num_frames=3))
    s = open_store(tmp_path / "c.zarr")
    by_split = {sp: s.frames_in_split(sp) for sp in ("train", "val", "test")}
    assert sorted(sum(by_split.values(), [])) == list(range(12))
    for sp, idx in by_split.items():
        for i in idx:
            clip = s.frames_meta(i)["clip_id"]
            assert split_of_clip(clip) == sp
            assert all(s.split_of_frame(j) == sp for j in range(12) if s.frames_meta(j)["clip_id"] == clip)
    assert s.clips()[101] == [3, 4, 5]
    # the hash split is uniform: ~80/10/10 over many ids
    names = [split_of_clip(k) for k in range(4000)]
    assert abs(names.count("train") / 4000 - 0.8) < 0.03 and abs(names.count("test") / 4000 - 0.1) < 0.02


def test_black_frame_overwrites_stale_data(store3):
    """A hard case: an all-black re-render over a frame with data leaves zeros, not the old values
    (zarr drops all-fill chunks; the old shard must not survive)."""
    path, frames = store3
    black = synthetic_frame(10, H, W, S)
    for k in ("radiance", "layers", "reference", "reference_stderr", "features", "guides_albedo",
              "guides_normal", "guides_depth", "guides_motion"):
        black[k][...] = 0.0
    StoreWriter(path).write_frame(0, black)
    for fast in (True, False):
        out = open_store(path, fast=fast).read_frame(0)
        for k in ("radiance", "layers", "reference", "features", "guides_depth"):
            assert not out[k].any(), (k, fast)
    st_ = open_store(path)
    np.testing.assert_array_equal(st_.read_frame(1)["radiance"], stored("radiance", frames[1]["radiance"], st_.layout))


@settings(max_examples=25, deadline=None)
@given(h=st.integers(1, 40), w=st.integers(1, 40), tile=st.sampled_from([3, 8, 16, 32]), s=st.integers(1, 3),
       chain=st.sampled_from(["plain", "lz4", "compact", "compact2", "compact3"]),
       array=st.sampled_from(["inputs/radiance", "inputs/features", "layers/radiance", "guides/depth"]),
       data=st.data())
def test_fast_shard_reader_matches_numpy_property(tmp_path_factory, h, w, tile, s, chain, array, data):
    """The direct shard reader returns exactly zarr's values for any frame size, tile, crop and codec
    chain (``plain``: LZ4 without a checksum; ``lz4``, ``compact``, ``compact2``, ``compact3``: the schema v2 chains,
    the compact ones with their transposed, bit-rounded inner chunks)."""
    from stores.shard_reader import ShardReader
    lay = StoreLayout(num_frames=2, height=h, width=w, spp=s, tile=tile,
                      encoding=None if chain == "plain" else chain).resolved()
    spec = schema.ARRAY_BY_PATH[array]
    path = tmp_path_factory.mktemp("prop")
    root = zarr.open_group(str(path), mode="w")
    if chain == "plain":
        arr = root.create_array("a", shape=spec.shape(lay), dtype="float32", chunks=spec.chunks(lay),
                                shards=spec.shards(lay), compressors=codecs.compressor(), fill_value=0,
                                dimension_names=spec.dims)
    else:
        arr = root.create_array("a", **schema.create_kwargs(spec, lay))
    assert ShardReader.applicable(arr.metadata.to_dict())
    full = np.random.default_rng(h * 100 + w).random(spec.shape(lay), dtype=np.float32)
    full[1, ..., : h // 2, :] = 0                      # some all-fill inner chunks
    arr[...] = full
    full = arr[...]                                    # what zarr decodes (bit-rounded in compact)
    r = ShardReader(str(path / "a"), arr.metadata.to_dict(), spec.dims)
    y0 = data.draw(st.integers(0, h - 1))
    x0 = data.draw(st.integers(0, w - 1))
    y1 = data.draw(st.integers(y0 + 1, h))
    x1 = data.draw(st.integers(x0 + 1, w))
    k = data.draw(st.integers(1, s))
    for f in (0, 1):
        want = full[f, :k, :, y0:y1, x0:x1] if "sample" in spec.dims else full[f, ..., y0:y1, x0:x1]
        np.testing.assert_array_equal(r.read(f, y0, y1, x0, x1, k), want)
