"""The ``compact`` encoding (issue 13 item 5): error bounds, lossless references, old stores still read and
resume, validation on the new codecs, and ``frames/*`` arrays newer than a store. (New stores are
``compact2`` since; tests of ``compact`` itself name it: ``COMPACT``.)"""
from __future__ import annotations

import json
import os
import shutil

import numpy as np
import pytest
import zarr
from hypothesis import given, settings
from hypothesis import strategies as st

from stores import chunk_files, codecs, create, schema, validate
from stores.__main__ import main as stores_main
from stores.contract import FRAME_META
from stores.errors import CorruptChunkError, StoreLayoutError
from stores.reader import open_store
from stores.schema import StoreLayout
from stores.writer import StoreWriter, open_or_create
from test_stores_synthetic import stored, synthetic_frame

H, W, S = 20, 24, 4
LAYOUT = StoreLayout(num_frames=2, height=H, width=W, spp=S, tile=16)
COMPACT = StoreLayout(**{**LAYOUT.to_dict(), "encoding": "compact"})
LOSSY = ("inputs/radiance", "inputs/features", "layers/radiance", "guides/albedo", "guides/normal",
         "guides/depth", "guides/motion")


def _image_bytes(path) -> dict[str, int]:
    out = {}
    for spec in schema.ARRAYS:
        if spec.image:
            d = os.path.join(os.fspath(path), *spec.path.split("/"))
            out[spec.path] = sum(os.path.getsize(os.path.join(r, f)) for r, _, fs in os.walk(d) for f in fs
                                 if f != "zarr.json")
    return out


def _strip_encoding(path) -> None:
    """Make a store look like one written before ``encoding`` existed: no key in its recorded layout."""
    p = os.path.join(os.fspath(path), "zarr.json")
    meta = json.load(open(p))
    meta["attributes"]["layout"].pop("encoding")
    meta.pop("consolidated_metadata", None)
    json.dump(meta, open(p, "w"))


def test_compact_stores_record_their_chains(tmp_path):
    open_or_create(tmp_path / "s.zarr", COMPACT)
    root = zarr.open_group(str(tmp_path / "s.zarr"), mode="r")
    assert dict(root.attrs)["layout"]["encoding"] == "compact"
    inner = root["inputs/radiance"].metadata.to_dict()["codecs"][0]["configuration"]["codecs"]
    assert [c["name"] for c in inner] == ["transpose", "numcodecs.bitround", "bytes", "blosc", "crc32c"]
    assert list(inner[0]["configuration"]["order"]) == [0, 2, 3, 4, 1]        # samples innermost
    assert (inner[3]["configuration"]["cname"], inner[3]["configuration"]["shuffle"]) == ("lz4hc", "bitshuffle")
    ref = root["reference/radiance"].metadata.to_dict()["codecs"][0]["configuration"]["codecs"]
    assert [c["name"] for c in ref] == ["bytes", "blosc", "crc32c"]      # lossless: no bit rounding
    assert ref[1]["configuration"]["cname"] == "zstd"
    assert root["inputs/radiance"].attrs["max_rel_error"] == 2 ** -10
    assert "max_rel_error" not in root["reference/radiance"].attrs


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(float(np.float32(-1e30)), float(np.float32(1e30)), allow_nan=False, width=32,
                          allow_subnormal=False),     # drjit may leave flush-to-zero on in this process
                min_size=1, max_size=64))
def test_bitround_relative_error_property(values):
    """9 kept mantissa bits: |x' - x| <= 2**-10 |x| for every normal float32 (< 1e-3); zero stays zero,
    signs stay, nothing becomes Inf."""
    x = np.array(values, np.float32)
    y = codecs.bitround(x, codecs.KEEPBITS)
    normal = np.abs(x) >= np.finfo(np.float32).tiny
    assert np.isfinite(y).all() and (np.sign(y[normal]) == np.sign(x[normal])).all()
    err = np.abs(y.astype(np.float64) - x)
    assert (err[normal] <= codecs.COMPACT_MAX_REL_ERROR * np.abs(x[normal].astype(np.float64))).all()
    assert (y[~normal] == 0).all()                       # zero (subnormals are not drawn) stays zero
    assert codecs.COMPACT_MAX_REL_ERROR < 1e-3


def test_compact_error_bounds_through_the_store(tmp_path):
    """Per sample: max |x' - x| / |x| over non-zero input radiance <= 2**-10, zeros exact, HDR extremes
    (1e-8 .. 1e8) within the same bound; references and their stderr bit-exact."""
    fr = synthetic_frame(5, H, W, S, sun=True, motion=True, defocus=True)
    fr["radiance"][0, 0] = [[0.0, 1e-8, 1e8]] * S
    w = open_or_create(tmp_path / "c.zarr", COMPACT)
    w.write_frame(0, fr)
    out = open_store(tmp_path / "c.zarr").read_frame(0)
    for k in ("radiance", "layers", "guides_albedo", "guides_normal", "guides_depth", "guides_motion"):
        x, y = fr[k].astype(np.float64), out[k].astype(np.float64)
        nz = x != 0
        assert (y[~nz] == 0).all(), k
        rel = np.abs(y[nz] - x[nz]) / np.abs(x[nz])
        assert rel.max() <= 2 ** -10, (k, rel.max())
        assert rel.max() > 2 ** -12, k          # it is rounded (a lossless store would pass the bound too)
    x, y = fr["features"].astype(np.float64), out["features"].astype(np.float64)
    assert (np.abs(y - x) <= 2 ** -10 * np.abs(x) + 1e-7).all()       # one rounding, not f16 then 9 bits
    np.testing.assert_array_equal(out["reference"], fr["reference"])
    np.testing.assert_array_equal(out["reference_stderr"], fr["reference_stderr"])


def test_float16_features_near_the_top_are_refused_not_inf(tmp_path):
    w = open_or_create(tmp_path / "c.zarr", COMPACT)
    fr = synthetic_frame(1, H, W, S)
    fr["features"][0, 0, 0, 3] = 65500.0          # fits float16, but 9 bits round it to 65536 = Inf
    from stores.errors import StoreValueError
    with pytest.raises(StoreValueError, match="depth.*65472"):
        w.write_frame(0, fr)
    fr["features"][0, 0, 0, 3] = 65472.0
    w.write_frame(0, fr)
    assert open_store(tmp_path / "c.zarr").read_frame(0)["features"][0, 0, 0, 3] == 65472.0


def test_store_written_before_the_encoding_field_reads_validates_and_resumes(tmp_path):
    """A v2 store of the LZ4 era (``layout`` without ``encoding``, like data/*.zarr): lossless reads,
    validate passes, a config that leaves the encoding open resumes and appends in LZ4; asking for
    ``compact`` explicitly is a layout mismatch naming the field."""
    path = tmp_path / "old.zarr"
    w = open_or_create(path, StoreLayout(**{**LAYOUT.to_dict(), "encoding": "lz4"}))
    frames = [synthetic_frame(30 + i, H, W, S) for i in range(2)]
    w.write_frame(0, frames[0])
    _strip_encoding(path)
    s = open_store(path)
    assert s.layout.encoding == "lz4"
    np.testing.assert_array_equal(s.read_frame(0)["radiance"], frames[0]["radiance"])
    assert validate.validate_store(path).frames[0].problems == []
    w = open_or_create(path, LAYOUT.with_frames(3))                    # encoding left open: the store's
    assert w.layout.encoding == "lz4" and w.incomplete_frames() == [1, 2]
    w.write_frame(1, frames[1])
    s = open_store(path)
    np.testing.assert_array_equal(s.read_frame(1)["radiance"], frames[1]["radiance"])    # still lossless
    assert s.num_frames == 3 and dict(s.root.attrs)["layout"]["encoding"] == "lz4"     # grow records it
    for enc in ("compact", "compact2"):
        with pytest.raises(StoreLayoutError, match="encoding"):
            open_or_create(path, StoreLayout(**{**LAYOUT.to_dict(), "encoding": enc}))


def test_layout_encoding_field_and_config_keys():
    from pipeline.config import STORE_KEYS
    assert "encoding" in STORE_KEYS
    assert "encoding" not in LAYOUT.to_dict()                        # left open: configs keep their form
    assert StoreLayout.from_dict(LAYOUT.to_dict()) == LAYOUT
    lz4 = StoreLayout(**{**LAYOUT.to_dict(), "encoding": "lz4"})
    assert StoreLayout.from_dict(lz4.to_dict()) == lz4 and lz4.frame_shape_compatible(LAYOUT)
    assert not lz4.frame_shape_compatible(lz4.__class__(**{**lz4.to_dict(), "encoding": "compact"}))
    assert StoreLayout.of_store({k: v for k, v in LAYOUT.to_dict().items()}).encoding == "lz4"
    with pytest.raises(StoreLayoutError, match='"encoding" must be one of'):
        StoreLayout(num_frames=1, height=4, width=4, encoding="zip")


@pytest.mark.parametrize("array", LOSSY + ("reference/radiance",))
@pytest.mark.parametrize("fast", [True, False])
def test_flipped_byte_in_a_compact_chunk_is_caught(tmp_path, array, fast, capsys):
    path = tmp_path / "c.zarr"
    w = open_or_create(path, LAYOUT)
    w.write_frame(0, synthetic_frame(7, H, W, S, motion=True))
    spec = schema.ARRAY_BY_PATH[array]
    f = chunk_files.chunk_file(zarr.open_group(str(path), mode="r"), spec, 0)[1]
    with open(f, "r+b") as fh:
        fh.seek(40)                                   # inside the first inner chunk's bytes
        b = fh.read(1)
        fh.seek(40)
        fh.write(bytes([b[0] ^ 0x10]))
    with pytest.raises(CorruptChunkError, match=array):
        open_store(path, fast=fast).read_array(array, 0)
    assert stores_main(["validate", str(path)]) == 3
    assert "STORE DAMAGED" in capsys.readouterr().out


@pytest.mark.parametrize("key", [k for k in FRAME_META if k not in schema.BASE_META_KEYS])
def test_frames_array_newer_than_the_store_reads_as_fill_and_is_added_on_resume(tmp_path, key, capsys):
    """Every FRAME_META key added since the first v2 stores (``case``, ``ref_time_slices``)."""
    spec = schema.ARRAY_BY_PATH[schema.meta_path(key)]
    path = tmp_path / "old.zarr"
    w = open_or_create(path, LAYOUT)
    frames = [synthetic_frame(40 + i, H, W, S) for i in range(2)]
    frames[1]["meta"][key] = {str: "a,b", int: 7, bool: True, float: 0.5}[FRAME_META[key]]
    w.write_frame(0, frames[0])
    shutil.rmtree(os.path.join(path, *spec.path.split("/")))          # a store made before the key existed
    schema.consolidate(path)
    # read-only: the array is not damage, the frame is complete and reads the fill value
    s = open_store(path)
    assert s.complete_frames() == [0] and s.missing_data() == {} and s.metadata_damage() == {}
    assert s.frames_meta(0)[key] == spec.fill == ({str: "", int: 0, bool: False, float: 0}[FRAME_META[key]])
    assert stores_main(["validate", str(path), "--frames", "0"]) == 0, capsys.readouterr().out    # 1 is not written yet
    capsys.readouterr()
    # a writer opened without open_or_create skips it; open_or_create (the resume) adds it
    StoreWriter(path).write_frame(1, frames[0])
    w = open_or_create(path, LAYOUT)
    assert spec.path in {p for p in schema.later_meta_paths()} and not schema.absent_arrays(w.root)
    assert w.incomplete_frames() == []              # old frames' chunks were written with the fill value
    w.write_frame(1, frames[1])
    s = open_store(path)
    assert s.frames_meta(0)[key] == spec.fill and s.frames_meta(1)[key] == frames[1]["meta"][key]
    assert s.missing_data() == {}
    assert stores_main(["validate", str(path)]) == 0, capsys.readouterr().out
    # any other deleted array is still damage
    shutil.rmtree(os.path.join(path, "frames", "scene_seed"))
    with pytest.raises(schema.ArrayMetadataError, match="frames/scene_seed: missing"):
        open_store(path)


def test_real_frame_compact_size_and_error(mi, tmp_path):
    """A real Mitsuba frame (the tiny ball scene) in every encoding: compact stores it in well under
    half of LZ4's bytes and within 0.15 of float32, compact2 in less than compact, with radiance
    within 2**-10 and references exact in both."""
    render = pytest.importorskip("pipeline.render")
    tr = pytest.importorskip("test_render")
    cfg = render.RenderConfig(res=(32, 32), spp=8, layer_levels=6, ref_spp=64, ref_passes=8, ref_min_passes=8)
    fr = render.render_frame(tr.ball_scene(seed=3), 0, cfg)
    sizes = {}
    for enc in ("lz4", "compact", "compact2"):
        lay = StoreLayout(num_frames=1, height=32, width=32, spp=8, tile=32, encoding=enc)
        open_or_create(tmp_path / f"{enc}.zarr", lay).write_frame(0, fr)
        sizes[enc] = _image_bytes(tmp_path / f"{enc}.zarr")
        assert validate.validate_store(tmp_path / f"{enc}.zarr").ok
    raw = sum(int(np.prod(schema.ARRAY_BY_PATH[p].shape(lay)[1:])) * 4 for p in sizes["lz4"])
    ratio = {e: sum(v.values()) / raw for e, v in sizes.items()}
    assert ratio["compact"] <= 0.15 and ratio["compact"] < 0.6 * ratio["lz4"], ratio
    assert ratio["compact2"] < ratio["compact"], ratio
    for p in ("reference/radiance", "reference/stderr"):              # lossless; zstd beats LZ4
        assert sizes["compact"][p] < sizes["lz4"][p], p
        assert sizes["compact2"][p] <= sizes["compact"][p], p          # zstd-7 vs zstd-5
    for enc in ("compact", "compact2"):
        lay = StoreLayout(num_frames=1, height=32, width=32, spp=8, tile=32, encoding=enc)
        out = open_store(tmp_path / f"{enc}.zarr").read_frame(0)
        np.testing.assert_array_equal(out["reference"], fr["reference"])
        np.testing.assert_array_equal(out["reference_stderr"], fr["reference_stderr"])
        np.testing.assert_array_equal(out["radiance"], stored("radiance", fr["radiance"], lay))
        nz = fr["radiance"] != 0
        rel = np.abs(out["radiance"][nz].astype(np.float64) - fr["radiance"][nz]) / np.abs(fr["radiance"][nz])
        assert rel.max() <= 2 ** -10, enc
