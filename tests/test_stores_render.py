"""A real Mitsuba frame (pipeline.render) through the store: write, validate, read back, datasets, export."""
from __future__ import annotations

import numpy as np
import pytest

from stores import validate
from stores.datasets import PixelDataset, SampleDataset
from stores.reader import open_store
from stores.schema import StoreLayout
from stores.writer import open_or_create


@pytest.fixture(scope="module")
def rendered(mi):
    render = pytest.importorskip("pipeline.render")
    tr = pytest.importorskip("test_render")            # its tiny ball scene
    cfg = render.RenderConfig(res=(16, 12), spp=4, layer_levels=6, ref_spp=64, ref_passes=8, ref_min_passes=8)
    return render.render_frame(tr.ball_scene(seed=3), 0, cfg)


def test_real_frame_round_trip(rendered, tmp_path):
    fr = rendered
    lay = StoreLayout(num_frames=1, height=12, width=16, spp=4, tile=8)
    open_or_create(tmp_path / "r.zarr", lay, {"real": True}).write_frame(0, fr)
    rep = validate.validate_store(tmp_path / "r.zarr")
    assert rep.ok, rep.format()
    out = open_store(tmp_path / "r.zarr").read_frame(0)
    np.testing.assert_array_equal(out["radiance"], fr["radiance"])
    np.testing.assert_array_equal(out["layers"], fr["layers"])
    np.testing.assert_array_equal(out["reference"], fr["reference"])
    np.testing.assert_allclose(out["features"], fr["features"], rtol=2 ** -11, atol=1e-6)
    assert out["meta"]["scene_json"] == fr["meta"]["scene_json"]
    item = SampleDataset(tmp_path / "r.zarr", split=None, spp=4, crop=8, augment=True)[0]
    assert item["radiance"].shape == (4, 3, 8, 8) and item["features"].shape == (4, 17, 8, 8)
    px = PixelDataset(tmp_path / "r.zarr", split=None, spp=63, crop=None, augment=False)[0]
    # 63 spp composed from all six layers: the mean of their 63 samples
    expect = sum(s * fr["layers"][n] for n, s in enumerate((1, 2, 4, 8, 16, 32))) / 63
    np.testing.assert_allclose(px["radiance"].numpy(), expect.transpose(2, 0, 1), rtol=1e-5, atol=1e-7)
