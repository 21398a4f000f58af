"""The ``compact2`` encoding (issue 13, store size; the default of new stores until ``compact3``, which keeps
its values with spec-only chains: ``tests/test_stores_compact3.py``), each feature group rounded to
its own mantissa bits (``codecs.FEATURE_KEEPBITS``) and recorded per feature, input radiance and layers
within 2**-10 (< 1e-3), references bit-exact; ``compact`` and ``lz4`` stores (schema v1 and v2) still
read and resume in their own chains."""
from __future__ import annotations

import os

import numpy as np
import pytest
import zarr
from hypothesis import given, settings
from hypothesis import strategies as st

from stores import codecs, create, schema, validate
from stores.contract import FEATURE_GROUPS, FEATURE_NAMES, NUM_FEATURES
from stores.errors import StoreLayoutError, StoreValueError
from stores.reader import open_store
from stores.schema import StoreLayout
from stores.writer import StoreWriter, open_or_create
from test_stores_compact import _strip_encoding
from test_stores_synthetic import stored, synthetic_frame

H, W, S = 20, 24, 4
LAYOUT = StoreLayout(num_frames=2, height=H, width=W, spp=S, tile=16, encoding="compact2")
OPEN = StoreLayout(num_frames=2, height=H, width=W, spp=S, tile=16)            # encoding left open
GUIDES = {"guides_albedo": "albedo", "guides_normal": "normal", "guides_depth": "depth", "guides_motion": "motion"}


def _rel(x, y) -> np.ndarray:
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    nz = x != 0
    return np.abs(y[nz] - x[nz]) / np.abs(x[nz])


def _inner_codecs(root, path) -> list[dict]:
    return list(root[path].metadata.to_dict()["codecs"][0]["configuration"]["codecs"])


def test_feature_precision_table():
    """Every feature group has its bits; radiance and the sample layers keep 9 (2**-10 < 1e-3); no
    feature keeps more than compact did, and the features' chain holds the largest."""
    assert set(codecs.FEATURE_KEEPBITS) == set(FEATURE_GROUPS)
    bits = codecs.feature_keepbits()
    assert len(bits) == NUM_FEATURES and all(1 <= b <= codecs.KEEPBITS for b in bits)
    for g, sl in FEATURE_GROUPS.items():
        assert set(bits[sl]) == {codecs.FEATURE_KEEPBITS[g]}, g
    chain = codecs.image_chain("inputs/features", "compact2", "float16")
    assert chain.keepbits == max(bits) and chain.channel_keepbits == bits and chain.sample_last
    for path in ("inputs/radiance", "layers/radiance"):
        assert codecs.image_chain(path, "compact2", "float32") == codecs.image_chain(path, "compact", "float32")
        assert 2.0 ** -(codecs.image_chain(path, "compact2", "float32").keepbits + 1) < 1e-3
    for path, g in codecs.GUIDE_GROUPS.items():
        assert codecs.image_chain(path, "compact2", "float32").keepbits == codecs.FEATURE_KEEPBITS[g]
    for path in ("reference/radiance", "reference/stderr"):
        c = codecs.image_chain(path, "compact2", "float32")
        assert c.keepbits is None and (c.cname, c.clevel, c.shuffle) == ("zstd", codecs.ZSTD_LEVEL_2, "shuffle")
    # log16 codes are never rounded
    assert codecs.image_chain("inputs/radiance", "compact2", "uint16").keepbits is None


def test_compact2_stores_record_their_chains(tmp_path):
    open_or_create(tmp_path / "s.zarr", LAYOUT)
    root = zarr.open_group(str(tmp_path / "s.zarr"), mode="r")
    assert dict(root.attrs)["layout"]["encoding"] == "compact2"
    assert open_store(tmp_path / "s.zarr").layout.encoding == "compact2"
    feat = _inner_codecs(root, "inputs/features")
    assert [c["name"] for c in feat] == ["transpose", "numcodecs.bitround", "bytes", "blosc", "crc32c"]
    assert feat[1]["configuration"]["keepbits"] == max(codecs.FEATURE_KEEPBITS.values())
    assert (feat[3]["configuration"]["cname"], feat[3]["configuration"]["shuffle"]) == ("lz4hc", "bitshuffle")
    for path, g in codecs.GUIDE_GROUPS.items():
        c = _inner_codecs(root, path)
        assert c[0]["name"] == "numcodecs.bitround" and c[0]["configuration"]["keepbits"] == codecs.FEATURE_KEEPBITS[g]
        assert root[path].attrs["max_rel_error"] == 2.0 ** -(codecs.FEATURE_KEEPBITS[g] + 1)
    ref = _inner_codecs(root, "reference/radiance")
    assert [c["name"] for c in ref] == ["bytes", "blosc", "crc32c"]             # lossless
    assert (ref[1]["configuration"]["cname"], ref[1]["configuration"]["clevel"]) == ("zstd", codecs.ZSTD_LEVEL_2)
    assert "max_rel_error" not in root["reference/radiance"].attrs
    # the precision of every feature, by name, and the array's loosest bound
    prec = root["inputs/features"].attrs["feature_precision"]
    assert list(prec) == list(FEATURE_NAMES)
    for g, sl in FEATURE_GROUPS.items():
        for name in FEATURE_NAMES[sl]:
            k = codecs.FEATURE_KEEPBITS[g]
            assert prec[name] == {"keepbits": k, "max_rel_error": 2.0 ** -(k + 1)}, name
    assert root["inputs/features"].attrs["max_rel_error"] == 2.0 ** -(min(codecs.FEATURE_KEEPBITS.values()) + 1)
    assert root["inputs/radiance"].attrs["max_rel_error"] == 2 ** -10
    assert schema.array_problems(root, open_store(tmp_path / "s.zarr").layout) == []     # the chains checked


@settings(max_examples=150, deadline=None)
@given(st.lists(st.floats(float(np.float32(-1e30)), float(np.float32(1e30)), allow_nan=False, width=32,
                          allow_subnormal=False), min_size=NUM_FEATURES, max_size=NUM_FEATURES * 4)
       .map(lambda v: v[: len(v) // NUM_FEATURES * NUM_FEATURES]))
def test_bitround_channels_property(values):
    """Each channel within 2**-(k + 1) of itself for its own k, zeros and signs kept, nothing Inf, and
    no rounding finer than asked (the chain's BitRound then changes nothing)."""
    x = np.array(values, np.float32).reshape(-1, NUM_FEATURES)
    bits = codecs.feature_keepbits()
    y = codecs.bitround_channels(x, bits, axis=1)
    assert y.dtype == np.float32 and np.isfinite(y).all()
    normal = np.abs(x) >= np.finfo(np.float32).tiny
    assert (np.sign(y[normal]) == np.sign(x[normal])).all() and (y[~normal] == 0).all()
    bound = 2.0 ** -(np.array(bits, np.float64) + 1)
    assert (np.abs(y.astype(np.float64) - x) <= bound * np.abs(x.astype(np.float64))).all()
    np.testing.assert_array_equal(codecs.bitround(y, max(bits)), y)
    for c, k in enumerate(bits):
        np.testing.assert_array_equal(y[:, c], codecs.bitround(np.ascontiguousarray(x[:, c]), k))


@pytest.mark.parametrize("feature_dtype", ["float16", "float32"])
def test_compact2_error_bounds_through_the_store(tmp_path, feature_dtype):
    """Input radiance and layers within 2**-10 (< 1e-3; HDR extremes 1e-8 .. 1e8 too), zeros exact; each
    feature group and guide within 2**-(k + 1) of its k bits (float16 subnormals, |x| < 2**-14: 1e-7
    absolute), and rounded to them, not to the chain's 9; references and stderr bit-exact; zarr-python
    reads the same values as the fast path."""
    lay = StoreLayout(**{**LAYOUT.to_dict(), "feature_dtype": feature_dtype})
    fr = synthetic_frame(5, H, W, S, sun=True, motion=True, defocus=True)
    fr["radiance"][0, 0] = [[0.0, 1e-8, 1e8]] * S
    open_or_create(tmp_path / "c.zarr", lay).write_frame(0, fr)
    s = open_store(tmp_path / "c.zarr")
    out = s.read_frame(0)
    for k in ("radiance", "layers"):
        x, y = fr[k], out[k]
        assert (y[x == 0] == 0).all(), k
        assert 2 ** -12 < _rel(x, y).max() <= 2 ** -10 < 1e-3, k
    for g, sl in FEATURE_GROUPS.items():
        kb = codecs.FEATURE_KEEPBITS[g]
        x, y = fr["features"][..., sl].astype(np.float64), out["features"][..., sl].astype(np.float64)
        assert (y[x == 0] == 0).all(), g
        assert (np.abs(y - x) <= 2.0 ** -(kb + 1) * np.abs(x) + 1e-7).all(), g
        if np.count_nonzero(x) > 50 and len(np.unique(x)) > 50:     # varied values: rounded to kb bits
            assert _rel(x, y).max() > 2.0 ** -(kb + 3), g
            big = np.abs(x) >= 2 ** -14
            np.testing.assert_array_equal(y[big], codecs.bitround(x[big].astype(np.float32), kb))
    for k, g in GUIDES.items():
        kb = codecs.FEATURE_KEEPBITS[g]
        assert _rel(fr[k], out[k]).max() <= 2.0 ** -(kb + 1), k
        np.testing.assert_array_equal(out[k], stored(k, fr[k], s.layout), err_msg=k)
    for k in ("radiance", "features", "layers"):
        np.testing.assert_array_equal(out[k], stored(k, fr[k], s.layout), err_msg=k)
    np.testing.assert_array_equal(out["reference"], fr["reference"])
    np.testing.assert_array_equal(out["reference_stderr"], fr["reference_stderr"])
    slow = open_store(tmp_path / "c.zarr", fast=False).read_frame(0)
    for k in out:
        if k != "meta":
            np.testing.assert_array_equal(out[k], slow[k], err_msg=k)


def test_compact2_is_smaller_than_compact(tmp_path):
    """The same frames: fewer feature and guide bytes, the same radiance and layer bytes."""
    frames = [synthetic_frame(60 + i, 32, 32, 8, motion=True, defocus=True) for i in range(2)]
    sizes = {}
    for enc in ("compact", "compact2"):
        path = tmp_path / f"{enc}.zarr"
        w = open_or_create(path, StoreLayout(num_frames=2, height=32, width=32, spp=8, encoding=enc))
        for i, fr in enumerate(frames):
            w.write_frame(i, fr)
        sizes[enc] = {}
        for spec in schema.ARRAYS:
            if spec.image:
                d = os.path.join(path, *spec.path.split("/"))
                sizes[enc][spec.path] = sum(os.path.getsize(os.path.join(r, f)) for r, _, fs in os.walk(d)
                                            for f in fs if f != "zarr.json")
    a, b = sizes["compact"], sizes["compact2"]
    assert b["inputs/features"] < 0.9 * a["inputs/features"]
    for p in codecs.GUIDE_GROUPS:
        assert b[p] < a[p], p
    for p in ("inputs/radiance", "layers/radiance"):
        assert abs(b[p] - a[p]) <= 0.01 * a[p], p


def test_float16_feature_limits_follow_the_group_bits(tmp_path):
    """A float16 feature whose rounding would reach 65536 (Inf) is refused, naming it and its limit."""
    lay = LAYOUT
    limits = lay.feature_limits
    d = FEATURE_NAMES.index("depth")
    assert limits[d] == codecs.float16_max(codecs.FEATURE_KEEPBITS["depth"]) == 2.0 ** 15 * (2 - 2.0 ** -8)
    assert StoreLayout(**{**LAYOUT.to_dict(), "encoding": "lz4"}).feature_limits == (65504.0,) * NUM_FEATURES
    assert StoreLayout(**{**LAYOUT.to_dict(), "encoding": "compact"}).feature_limits == (65472.0,) * NUM_FEATURES
    assert StoreLayout(**{**LAYOUT.to_dict(), "feature_dtype": "float32"}).feature_limits == limits
    w = open_or_create(tmp_path / "c.zarr", lay)
    fr = synthetic_frame(1, H, W, S)
    fr["features"][0, 0, 0, d] = limits[d] + 1.0
    with pytest.raises(StoreValueError, match=rf"depth.*\|depth\| <= {limits[d]:g}"):
        w.write_frame(0, fr)
    fr["features"][0, 0, 0, d] = limits[d]
    w.write_frame(0, fr)
    assert open_store(tmp_path / "c.zarr").read_frame(0)["features"][0, 0, 0, d] == limits[d]


@pytest.mark.parametrize("encoding", ["compact2", "compact", "lz4"])
def test_old_encodings_read_and_resume_in_their_own_chains(tmp_path, encoding):
    """A ``compact`` store and an ``lz4`` store (from before the ``encoding`` field) read as
    written, and a config that leaves the encoding open resumes and appends to them in their own
    chains (features of a compact store keep 9 bits); asking for ``compact3`` is a layout mismatch."""
    path = tmp_path / "old.zarr"
    lay = StoreLayout(**{**LAYOUT.to_dict(), "encoding": encoding})
    create.create_store(path, lay)
    frames = [synthetic_frame(30 + i, H, W, S, motion=True, defocus=True) for i in range(3)]
    StoreWriter(path).write_frame(0, frames[0])
    if encoding == "lz4":
        _strip_encoding(path)
    s = open_store(path)
    assert s.layout.encoding == encoding
    before = s.read_frame(0)
    w = open_or_create(path, OPEN.with_frames(3))                    # encoding left open: the store's
    assert w.layout.encoding == encoding and w.incomplete_frames() == [1, 2]
    for i in (1, 2):
        w.write_frame(i, frames[i])
    s = open_store(path)
    assert s.num_frames == 3 and dict(s.root.attrs)["layout"]["encoding"] == encoding
    assert validate.validate_store(path).ok
    for i, fr in enumerate(frames):
        out = s.read_frame(i)
        for k in ("radiance", "features", "layers", "reference", "reference_stderr", "guides_albedo",
                  "guides_normal", "guides_depth", "guides_motion"):
            np.testing.assert_array_equal(out[k], stored(k, fr[k], s.layout), err_msg=f"{i} {k}")
            if i == 0:
                np.testing.assert_array_equal(out[k], before[k], err_msg=k)
    if encoding == "compact":        # compact's 9 bits for every feature, lens included
        x = frames[1]["features"][..., FEATURE_GROUPS["lens"]]
        assert _rel(x, s.read_frame(1)["features"][..., FEATURE_GROUPS["lens"]]).max() <= 2 ** -10
    elif encoding == "lz4":
        np.testing.assert_array_equal(s.read_frame(1)["radiance"], frames[1]["radiance"])    # lossless
    with pytest.raises(StoreLayoutError, match="encoding"):
        open_or_create(path, StoreLayout(**{**LAYOUT.to_dict(), "encoding": "compact3"}))
