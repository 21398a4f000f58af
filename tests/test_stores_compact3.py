"""The ``compact3`` encoding, the default of new stores: ``compact2``'s values with the writer doing every
rounding, so every chain holds only codecs of the Zarr v3 specification and its registered extensions.
Another Zarr v3 implementation (tensorstore) opens every numeric array and reads zarr-python's values,
and zarr-python opens the store without a warning."""
from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import zarr

from stores import codecs, schema, validate
from stores.contract import FEATURE_NAMES
from stores.reader import open_store
from stores.schema import StoreLayout
from stores.writer import open_or_create
from test_stores_synthetic import stored, synthetic_frame

H, W, S = 20, 24, 4
OPEN = StoreLayout(num_frames=2, height=H, width=W, spp=S, tile=16)            # encoding left open
# the Zarr v3 core specification's codecs, and vlen-utf8 (registered in zarr-extensions) for strings
SPEC_CODECS = {"sharding_indexed", "transpose", "bytes", "blosc", "crc32c", "gzip", "zstd", "vlen-utf8"}


def _frames(n=2):
    return [synthetic_frame(40 + i, H, W, S, sun=True, motion=True, defocus=True) for i in range(n)]


def _write(path, layout, frames):
    w = open_or_create(path, layout.with_frames(len(frames)))
    for i, fr in enumerate(frames):
        w.write_frame(i, fr)
    return path


def _codec_names(chain) -> set[str]:
    out = set()
    for c in chain or ():
        out.add(c["name"])
        conf = c.get("configuration") or {}
        out |= _codec_names(conf.get("codecs")) | _codec_names(conf.get("index_codecs"))
    return out


@pytest.fixture(scope="module")
def stores_(tmp_path_factory):
    d = tmp_path_factory.mktemp("c3")
    frames = _frames()
    c3 = _write(d / "c3.zarr", OPEN, frames)
    c2 = _write(d / "c2.zarr", StoreLayout(**{**OPEN.to_dict(), "encoding": "compact2"}), frames)
    return c3, c2, frames


def test_new_stores_are_compact3_with_spec_codecs_only(stores_):
    c3, _, _ = stores_
    assert codecs.DEFAULT_ENCODING == "compact3"
    assert open_store(c3).layout.encoding == "compact3"
    found = set()
    for meta in Path(c3).rglob("zarr.json"):
        m = json.loads(meta.read_text())
        if m.get("node_type") == "array":
            names = _codec_names(m["codecs"])
            assert names <= SPEC_CODECS, (meta, names - SPEC_CODECS)
            found |= names
    assert "numcodecs.bitround" not in found and {"transpose", "blosc", "crc32c", "sharding_indexed"} <= found
    root = zarr.open_group(str(c3), mode="r")
    prec = root["inputs/features"].attrs["feature_precision"]      # the precision is still recorded
    assert [prec[n]["keepbits"] for n in FEATURE_NAMES] == list(codecs.feature_keepbits())
    assert root["inputs/radiance"].attrs["max_rel_error"] == 2 ** -10
    assert schema.array_problems(root, open_store(c3).layout) == []
    assert validate.validate_store(c3).ok


def test_compact3_keeps_compact2s_values(stores_):
    """Radiance, layers, guides and references are compact2's bit for bit; features too, but for float16
    subnormals (|x| < 2**-14), which compact2's codec rounded once more (within 1e-7)."""
    c3, c2, frames = stores_
    a, b = open_store(c3), open_store(c2)
    for i, fr in enumerate(frames):
        x, y = a.read_frame(i), b.read_frame(i)
        for k in ("radiance", "layers", "reference", "reference_stderr", "guides_albedo", "guides_normal",
                  "guides_depth", "guides_motion"):
            np.testing.assert_array_equal(x[k], y[k], err_msg=k)
            np.testing.assert_array_equal(x[k], stored(k, fr[k], a.layout), err_msg=k)
        big = np.abs(y["features"]) >= 2 ** -14
        np.testing.assert_array_equal(x["features"][big], y["features"][big])
        assert np.abs(x["features"] - y["features"]).max() <= 1e-7
        np.testing.assert_array_equal(x["features"], stored("features", fr["features"], a.layout))


def test_zarr_python_opens_a_compact3_store_without_a_warning(stores_):
    c3, _, _ = stores_
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        root = zarr.open_group(str(c3), mode="r")
        for path in ("inputs/radiance", "inputs/features", "layers/radiance", "guides/normal"):
            root[path][0]
        open_store(c3).read_frame(1)


def test_tensorstore_reads_every_numeric_array_as_zarr_python_does(stores_):
    ts = pytest.importorskip("tensorstore", reason="tensorstore (a dev dependency) is not installed")
    c3, _, _ = stores_
    root = zarr.open_group(str(c3), mode="r")
    checked = []
    for spec in schema.ARRAYS:
        arr = root[spec.path]
        if arr.dtype.kind not in "biuf":          # tensorstore has no variable-length strings
            continue
        t = ts.open({"driver": "zarr3", "kvstore": {"driver": "file", "path": str(Path(c3) / spec.path)}},
                    read=True).result()
        np.testing.assert_array_equal(t.read().result(), arr[...], err_msg=spec.path)
        checked.append(spec.path)
    assert {"inputs/radiance", "inputs/features", "layers/radiance", "guides/albedo", "guides/normal",
            "guides/depth", "guides/motion", "reference/radiance", "status/complete"} <= set(checked)
