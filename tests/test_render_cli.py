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


def test_render_seed_gives_an_independent_render_of_the_same_scene(tmp_path, mi, capsys):
    """``--render-seed N``: the samples' seed apart from the scene's. Two renders of one scene with different
    render seeds share the scene and differ in every stream; the same seed repeats the bytes. The output
    records the reference's shutter times."""
    from pipeline.__main__ import main
    z = {}
    for name, rs in (("a", "0"), ("b", "5"), ("c", "5")):
        out = tmp_path / f"{name}.npz"
        assert main(["render-frame", "--seed", "2", "--kind", "outdoor", "--res", "8", "--spp", "2", "--layers", "2",
                     "--ref-spp", "64", "--render-seed", rs, "--out", str(out)]) == 0
        z[name] = dict(np.load(out))
    assert "ref_time_slices" in capsys.readouterr().out
    assert str(z["a"]["scene_json"]) == str(z["b"]["scene_json"])
    for k in ("radiance", "layers", "reference", "reference_stderr"):
        assert z["a"][k].tobytes() != z["b"][k].tobytes(), k
        assert z["b"][k].tobytes() == z["c"][k].tobytes(), k
    assert json.loads(str(z["a"]["meta_json"]))["ref_time_slices"] >= 1


@pytest.mark.parametrize("argv, word", [
    (["--res", "16", "--out", "x.png"], "npz"),
    (["--res", "16", "--ref-spp", "100", "--out", "x.npz"], "ref-spp"),
    (["--res", "16", "--frame", "3", "--num-frames", "2", "--out", "x.npz"], "frame"),
    (["--res", "16", "--render-seed", "-1", "--out", "x.npz"], "render-seed"),
    (["--res", "16", "--ref-spp", "32", "--ref-passes", "16", "--ref-times", "2", "--out", "x.npz"], "ref_times"),
])
def test_render_frame_command_errors(argv, word, capsys):
    from pipeline.__main__ import main
    assert main(["render-frame", "--seed", "1", "--kind", "indoor"] + argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and word in err and len(err.strip().splitlines()) == 1
