"""``python -m pipeline render-frame``: the command's contract on a tiny generated scene."""
from __future__ import annotations

import json

import numpy as np
import pytest

from stores.contract import FEATURE_NAMES


def test_render_frame_command(tmp_path, mi):
    from PIL import Image

    from pipeline.__main__ import main
    out = tmp_path / "sub" / "frame.npz"
    rc = main(["render-frame", "--seed", "1", "--kind", "indoor", "--res", "16", "--spp", "2",
               "--ref-spp", "32", "--oracle-spp", "16", "--out", str(out)])
    assert rc == 0
    z = np.load(out)
    assert z["radiance"].shape == (16, 16, 2, 3) and z["radiance"].dtype == np.float32
    assert z["features"].shape == (16, 16, 2, 17)
    assert tuple(z["feature_names"]) == FEATURE_NAMES
    assert z["layers"].shape == (6, 16, 16, 3)
    for k in ("reference", "reference_stderr", "oracle", "guides_albedo", "guides_normal"):
        assert z[k].shape == (16, 16, 3), k
    assert z["guides_depth"].shape == (16, 16, 1) and z["guides_motion"].shape == (16, 16, 2)
    from scene_gen.sampling import sample_scene
    from scene_gen.spec import SceneSpec
    assert SceneSpec.from_json(str(z["scene_json"])) == sample_scene(1, "indoor", num_frames=1, res=16)
    meta = json.loads(str(z["meta_json"]))
    assert meta["reference_spp"] == 32 and meta["frame"] == 0
    # the oracle is plain mi.render: it agrees with the reference on the image mean
    assert abs(z["oracle"].mean() - z["reference"].mean()) < 0.2 * z["reference"].mean() + 1e-3
    png = Image.open(out.with_suffix(".png"))
    assert png.size == (9 * 16 + 8 * 2, 16)   # input mean, 6 layers, reference, oracle


@pytest.mark.parametrize("argv, word", [
    (["--res", "16", "--out", "x.png"], "npz"),
    (["--res", "16", "--ref-spp", "100", "--out", "x.npz"], "ref-spp"),
    (["--res", "16", "--frame", "3", "--num-frames", "2", "--out", "x.npz"], "frame"),
])
def test_render_frame_command_errors(argv, word, capsys):
    from pipeline.__main__ import main
    assert main(["render-frame", "--seed", "1", "--kind", "indoor"] + argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and word in err and len(err.strip().splitlines()) == 1
