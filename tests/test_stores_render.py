"""A real Mitsuba frame (pipeline.render) through the store: write, validate, read back, datasets, export."""
from __future__ import annotations

import numpy as np
import pytest

from stores import validate
from training import adaptive
from training.datasets import LayerFrames, SampleFrames
from stores.reader import open_store
from stores.schema import ARRAY_BY_SOURCE, StoreLayout
from stores.writer import open_or_create
from test_stores_synthetic import stored


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
    st_ = open_store(tmp_path / "r.zarr")
    out = st_.read_frame(0)
    assert st_.layout.encoding == "compact3"       # the default of new stores: 9-bit radiance, exact references
    for k in ("radiance", "layers", "features", "guides_albedo", "guides_normal", "guides_depth", "guides_motion"):
        np.testing.assert_array_equal(out[k], stored(k, fr[k], st_.layout), err_msg=k)
        chain = ARRAY_BY_SOURCE[k].chain(st_.layout)       # features and guides: their group's bits
        rtol = 2.0 ** -(np.array(chain.channel_bits(fr[k].shape[-1]), np.float64) + 1)
        assert (np.abs(out[k].astype(np.float64) - fr[k]) <= rtol * np.abs(fr[k]) + 1e-7).all(), k
    np.testing.assert_allclose(out["radiance"], fr["radiance"], rtol=2 ** -10, atol=0)      # < 1e-3
    np.testing.assert_array_equal(out["reference"], fr["reference"])
    np.testing.assert_array_equal(out["reference_stderr"], fr["reference_stderr"])
    assert out["meta"]["scene_json"] == fr["meta"]["scene_json"]
    item = SampleFrames(tmp_path / "r.zarr", split=None, spp=4, crop=8, augment=True)[0]
    assert item["radiance"].shape == (4, 3, 8, 8) and item["features"].shape == (4, 17, 8, 8)
    it = LayerFrames(tmp_path / "r.zarr", split=None, spp=63, crop=None, augment=False)[0]
    layers_t = it["layers"].unsqueeze(0)
    px = {"radiance": adaptive.compose(layers_t, adaptive.uniform_counts(layers_t[:, 0], 63))[0]}
    # 63 spp composed from all six layers: the mean of their 63 samples
    layers = stored("layers", fr["layers"], st_.layout)
    expect = sum(s * layers[n] for n, s in enumerate((1, 2, 4, 8, 16, 32))) / 63
    np.testing.assert_allclose(px["radiance"].numpy(), expect.transpose(2, 0, 1), rtol=1e-5, atol=1e-7)
