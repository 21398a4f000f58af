"""Every material and light kind loads in Mitsuba (through scene_gen.to_mitsuba) and renders finite pixels
at 16x16; sampled scenes render; the preview CLI writes EXR and PNG with clear errors for bad input."""
from __future__ import annotations

import numpy as np
import pytest

from scene_gen.__main__ import main
from scene_gen.commands import render_spec
from scene_gen.config import SceneGenConfig
from scene_gen.materials import diffuse, random_material
from scene_gen.layout import probe_params
from scene_gen.sampling import sample_scene
from scene_gen.spec import (LIGHT_KINDS, MATERIAL_KINDS, CameraSpec, LightSpec, MeshSpec, ObjectSpec, SceneSpec,
                            Transform)

RES = 16


def _floor():
    return ObjectSpec("floor", MeshSpec("plane", {"resolution": 1}), diffuse((0.5, 0.5, 0.5)),
                      Transform((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (20.0, 20.0, 20.0)))


def _camera():
    return (CameraSpec(origin=(0.0, 2.0, -5.0), target=(0.0, 0.5, 0.0), fov=50.0),)


@pytest.fixture(scope="module")
def materials():
    rng = np.random.default_rng(1)
    out = {k: random_material(rng, k) for k in MATERIAL_KINDS}
    # textured variants of the textured kinds
    for k in ("diffuse", "plastic", "roughplastic", "principled"):
        for _ in range(20):
            m = random_material(rng, k, p_texture=1.0)
            if m.texture is not None:
                out[k + "_tex"] = m
                break
    return out


def test_every_material_kind_renders_finite(mi, materials):
    objs = [_floor()]
    n = len(materials)
    for i, (name, m) in enumerate(sorted(materials.items())):
        x = (i - (n - 1) / 2) * 0.45
        objs.append(ObjectSpec(f"m_{name}", MeshSpec("sphere", {"subdivisions": 2}), m,
                               Transform((x, 0.2, 0.0), (0.0, 0.0, 0.0), (0.2, 0.2, 0.2))))
    spec = SceneSpec("outdoor", 0, tuple(objs), (LightSpec("constant", {"radiance": [1.0, 1.0, 1.0]}),),
                     (CameraSpec(origin=(0.0, 1.0, -4.0), target=(0.0, 0.2, 0.0), fov=70.0),))
    img = render_spec(spec, res=RES, spp=4)
    assert img.shape == (RES, RES, 3) and np.isfinite(img).all()
    assert img.mean() > 0.05
    # each material on its own, in front of a black background: finite, and not all black except glass
    for name, m in sorted(materials.items()):
        s = SceneSpec("outdoor", 0, (ObjectSpec("s", MeshSpec("sphere", {"subdivisions": 1}), m),),
                      (LightSpec("constant", {"radiance": [1.0, 1.0, 1.0]}),),
                      (CameraSpec(origin=(0.0, 0.0, -3.0), target=(0.0, 0.0, 0.0), fov=40.0),))
        im = render_spec(s, res=RES, spp=2)
        assert np.isfinite(im).all(), name
        assert im[6:10, 6:10].mean() > 0.01, name   # the sphere shows (constant light: glass transmits it)


@pytest.mark.parametrize("kind", LIGHT_KINDS)
def test_every_light_kind_lights_the_scene(mi, kind):
    objs = [_floor(), ObjectSpec("ball", MeshSpec("sphere", {"subdivisions": 2}), diffuse((0.7, 0.7, 0.7)),
                                 Transform((0.0, 0.5, 0.0), (0.0, 0.0, 0.0), (0.5, 0.5, 0.5)))]
    rng = np.random.default_rng(0)
    if kind == "area":
        objs.append(ObjectSpec("panel", MeshSpec("plane", {"resolution": 1}), diffuse((0.8, 0.8, 0.8)),
                               Transform((0.0, 2.5, 0.0), (180.0, 0.0, 0.0), (0.5, 1.0, 0.5)),
                               emitter_radiance=(10.0, 10.0, 10.0)))
        lights = ()
    elif kind == "point":
        lights = (LightSpec("point", {"position": [1.0, 2.0, -1.0], "intensity": [5.0, 5.0, 5.0]}),)
    elif kind == "envmap":
        lights = (LightSpec("envmap", {"probe": probe_params(rng, sky=1.0, sun_irradiance=3.0), "scale": 1.0, "rotation": 30.0}),)
    elif kind == "sunsky":
        lights = (LightSpec("sunsky", {"sun_direction": [0.3, 0.8, -0.5], "turbidity": 3.0, "albedo": 0.2,
                                       "sun_scale": 2.0, "sky_scale": 5.0}),)
    else:
        lights = (LightSpec("constant", {"radiance": [0.5, 0.5, 0.5]}),)
    spec = SceneSpec("outdoor", 0, tuple(objs), lights, _camera())
    img = render_spec(spec, res=RES, spp=8)
    assert np.isfinite(img).all()
    floor = img[12:, :].mean()          # the lower rows see the lit floor
    assert 0.02 < floor < 5.0, floor    # lit, and at a sane level for the fixed tone map


@pytest.mark.parametrize("kind", ["indoor", "outdoor"])
def test_sampled_scene_renders_finite_and_exposed(mi, kind):
    cfg = SceneGenConfig(indoor_objects=10, outdoor_objects=10)
    spec = sample_scene(4, kind, res=RES, config=cfg)
    img = render_spec(spec, res=RES, spp=4)
    assert np.isfinite(img).all() and img.shape == (RES, RES, 3)
    assert 0.01 < float(np.median(img)) < 3.0


def test_preview_cli_writes_exr_and_png(mi, tmp_path):
    from core.images import read_exr
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("scene_gen:\n  outdoor_objects: 6\n  indoor_objects: 6\n")
    out = tmp_path / "p" / "outdoor-3.exr"
    rc = main(["preview", "--seed", "3", "--kind", "outdoor", "--res", "16", "--spp", "2", "--out", str(out),
               "--config", str(cfg), "--save-spec", str(tmp_path / "spec.json")])
    assert rc == 0
    img, ch = read_exr(out)
    assert ch == "RGB" and img.shape == (16, 16, 3) and np.isfinite(img).all() and img.mean() > 0
    from PIL import Image
    png = np.asarray(Image.open(out.with_suffix(".png")))
    assert png.shape == (16, 16, 3) and png.std() > 0
    from scene_gen.spec import SceneSpec as S
    assert S.from_json((tmp_path / "spec.json").read_text()) == sample_scene(
        3, "outdoor", res=16, config=SceneGenConfig(outdoor_objects=6, indoor_objects=6))


def test_cli_errors_are_one_line_with_exit_code_2(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("scene_gen:\n  outdoor_objects: -4\n")
    assert main(["preview", "--kind", "outdoor", "--out", str(tmp_path / "x.exr"), "--config", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert "outdoor_objects" in err and len(err.splitlines()) == 1
    assert main(["preview", "--res", "0", "--out", str(tmp_path / "x.exr")]) == 2
    assert "--res" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:   # argparse: unknown scene kind
        main(["preview", "--kind", "space", "--out", "x.exr"])
    assert e.value.code == 2
    assert "invalid choice" in capsys.readouterr().err
    for argv in (["--help"], ["preview", "--help"], ["contact-sheet", "--help"], ["spec", "--help"]):
        with pytest.raises(SystemExit) as e:
            main(argv)
        assert e.value.code == 0
