"""Phenomena the families add at their own rates (scene_gen.phenomena): the sun in an outdoor camera's view,
lamps indoors, caustics through glass, textures of natural statistics, a ceiling panel in view. At the default rate 0 every scene is as before; at rate 1 each is
where it says, the rest of the scene unchanged; the draw follows the rate; a render shows the sun."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.stats import binomtest

from scene_gen import cameras as cams
from scene_gen.config import SceneGenConfig
from scene_gen.sampling import sample_scene

SMALL = {"indoor_objects": 8, "outdoor_objects": 8}


def scene(seed, kind, res=32, **rates):
    return sample_scene(seed, kind, res=res, config=SceneGenConfig.from_dict({**SMALL, **rates}))


def _without(spec, prefixes):
    return tuple(o for o in spec.objects if not o.name.startswith(prefixes))


def test_rates_of_0_change_nothing_and_are_not_written():
    cfg = SceneGenConfig.from_dict(SMALL)
    assert not {"p_caustics", "p_lamps", "p_sun_in_view", "p_natural_textures", "p_panels_in_view"} \
        & set(cfg.to_dict())                                                            # old stores resume
    assert SceneGenConfig.from_dict({**SMALL, "p_lamps": 0.5}).to_dict()["p_lamps"] == 0.5
    for kind in ("indoor", "outdoor"):
        assert scene(3, kind) == sample_scene(3, kind, res=32, config=cfg)


def test_lamps_and_caustics_leave_the_rest_of_the_scene_alone():
    plain, lit = scene(4, "indoor"), scene(4, "indoor", p_lamps=1.0, p_caustics=1.0)
    assert _without(lit, ("lamp_", "caustic_")) == plain.objects and lit.cameras == plain.cameras
    lamps = [o for o in lit.objects if o.name.startswith("lamp_")]
    assert 1 <= len(lamps) <= 3
    cam = lit.cameras[0]
    for o in lamps:
        assert 200 <= o.emitter_radiance[0] <= 5000 and 0.01 <= o.transform.scale[0] <= 0.03
        p = cams.to_camera(cam, np.array([o.transform.translate]))[0]
        tx, ty = cams.tan_half(cam, (32, 32))
        assert p[2] > 0 and abs(p[0] / p[2]) <= tx and abs(p[1] / p[2]) <= ty           # in view
    glass = next(o for o in lit.objects if o.name == "caustic_glass")
    light = next(o for o in lit.objects if o.name == "caustic_light")
    assert glass.material.kind == "dielectric" and light.emitter_radiance[0] >= 2e3
    assert light.transform.translate[1] > glass.transform.translate[1]
    outdoor = scene(4, "outdoor", p_lamps=1.0)                       # an indoor setting: not outdoors
    assert outdoor == scene(4, "outdoor")


def _sunsky_seed():
    return next(s for s in range(50) if any(lt.kind == "sunsky" for lt in scene(s, "outdoor").lights))


def test_the_sun_is_moved_into_view_on_flat_ground():
    seed = _sunsky_seed()
    plain, sunny = scene(seed, "outdoor"), scene(seed, "outdoor", p_sun_in_view=1.0)
    d = np.array(next(lt for lt in sunny.lights if lt.kind == "sunsky").params["sun_direction"])
    cam = sunny.cameras[0]
    r, u, f = cams.basis(cam)
    tx, ty = cams.tan_half(cam, (32, 32))
    x, y, z = -(d @ r) / (d @ f), (d @ u) / (d @ f), d @ f            # image coordinates (x right)
    assert z > 0 and abs(x) <= tx and 0 < y <= ty and d[1] > 0
    backdrop = next(o for o in sunny.objects if o.name == "backdrop")
    assert "bend" not in backdrop.mesh.params
    assert [o for o in sunny.objects if o.name != "backdrop"] == [o for o in plain.objects if o.name != "backdrop"]
    assert [dataclasses.replace(lt, params={}) for lt in sunny.lights] == \
        [dataclasses.replace(lt, params={}) for lt in plain.lights]


def test_each_phenomenon_is_drawn_at_its_rate():
    n = 150
    got = sum(any(o.name.startswith("lamp_") for o in scene(s, "indoor", res=16, p_lamps=0.3).objects)
              for s in range(n))
    assert binomtest(got, n, 0.3).pvalue > 1e-3, got


def test_a_render_shows_the_sun():
    """The brightest pixel of a render is where the sun projects, 100 times the frame's median or more (at
    32 px the sun's disc covers a few percent of a pixel: its ~2e4 radiance shows as a few hundred)."""
    from pipeline.render import RenderConfig, render_frame
    spec = scene(_sunsky_seed(), "outdoor", res=32, p_sun_in_view=1.0)
    out = render_frame(spec, 0, RenderConfig(res=(32, 32), spp=4, layer_levels=1, ref_spp=64, ref_passes=2,
                                             ref_min_passes=2))
    lum = out["reference"].mean(axis=-1)
    d = np.array(next(lt for lt in spec.lights if lt.kind == "sunsky").params["sun_direction"])
    cam = spec.cameras[0]
    r, u, f = cams.basis(cam)
    tx, ty = cams.tan_half(cam, (32, 32))
    col = (1 - (d @ r) / (d @ f) / tx) / 2 * 32          # image x to the right: basis right is the image's left
    row = (1 - (d @ u) / (d @ f) / ty) / 2 * 32
    y, x = np.unravel_index(np.argmax(lum), lum.shape)
    assert abs(x + 0.5 - col) <= 1.5 and abs(y + 0.5 - row) <= 1.5, ((x, y), (col, row))
    assert lum.max() > 100 * np.median(lum)


def test_phenomena_are_a_registry_whose_settings_are_declared_once():
    """Like families and cases: each phenomenon registers its setting (drawn in registration order), a
    shared one is a field every family has, a family's own is declared by that family alone, and the
    config names none of them but where it declares the field."""
    from dataclasses import fields
    from pathlib import Path

    from scene_gen.config import SceneGenConfig, SharedSettings
    from scene_gen.families import FAMILIES
    from scene_gen.phenomena import PHENOMENA_BY_SETTING
    assert list(PHENOMENA_BY_SETTING) == ["p_sun_in_view", "p_lamps", "p_caustics", "p_natural_textures",
                                          "p_panels_in_view"]
    shared = {f.name for f in fields(SharedSettings)}
    for name, p in PHENOMENA_BY_SETTING.items():
        owners = [f for f, fam in FAMILIES.items() if name in fam.settings]
        assert (name in shared) == p.shared and (owners == [] if p.shared else len(owners) == 1), name
        assert getattr(SceneGenConfig(), name) == 0.0 and name not in SceneGenConfig().to_dict()
    config = (Path(__file__).resolve().parent.parent / "scene_gen" / "config.py").read_text()
    assert {n: config.count(n) for n in PHENOMENA_BY_SETTING} == {"p_sun_in_view": 0, "p_lamps": 0, "p_caustics": 1,
                                                                  "p_natural_textures": 1, "p_panels_in_view": 0}


def test_later_phenomena_leave_the_first_three_as_stores_made_with_them_have_them():
    """The lamps and caustic of seed 4 as the code before p_natural_textures and p_panels_in_view drew them
    (a store made then resumes with the same scenes), and unchanged when the later ones are drawn too."""
    lit = scene(4, "indoor", p_lamps=1.0, p_caustics=1.0)
    got = [(o.name, o.transform.translate, o.emitter_radiance) for o in lit.objects
           if o.name.startswith(("lamp_", "caustic_"))]
    assert got == [("lamp_0", (-0.199247, 0.543317, -1.806861), (3049.95028,) * 3),
                   ("caustic_glass", (-0.015976, 0.158422, -1.693634), None),
                   ("caustic_light", (-0.015976, 0.293454, -1.693634), (3050.650125,) * 3)]
    both = scene(4, "indoor", p_lamps=1.0, p_caustics=1.0, p_natural_textures=1.0)
    assert [(o.name, o.transform) for o in both.objects] == [(o.name, o.transform) for o in lit.objects]


def _power_slope(v: np.ndarray) -> float:
    """The slope of the radially averaged power spectrum of ``v`` in log-log, over frequencies 4-64 cycles."""
    p = np.abs(np.fft.fft2(v - v.mean())) ** 2
    f = np.hypot(*np.meshgrid(np.fft.fftfreq(v.shape[0]) * v.shape[0], np.fft.fftfreq(v.shape[1]) * v.shape[1],
                              indexing="ij"))
    bins = np.arange(4, 65)
    power = [p[(f >= b) & (f < b + 1)].mean() for b in bins]
    return float(np.polyfit(np.log(bins + 0.5), np.log(power), 1)[0])


def test_natural_textures_have_natural_statistics_and_tile():
    """A power spectrum falling as about 1/f^2 (photographs: 1.6-2.6 here; the procedural value noise falls
    far faster), values spread over [0, 1], and no seam where the bitmap wraps."""
    from scene_gen.textures import natural
    slopes = []
    for seed in range(8):
        v = natural(np.random.default_rng(seed), 256)
        assert v.shape == (256, 256) and 0.0 <= v.min() and v.max() <= 1.0 and v.std() > 0.1
        slopes.append(_power_slope(v))
        inner = np.abs(np.diff(v, axis=1)).mean()
        seam = np.abs(v[:, 0] - v[:, -1]).mean()                  # the wrap is a neighbour like any other
        assert seam < 2.5 * inner, (seed, seam, inner)
    assert all(-3.2 < s < -1.0 for s in slopes), slopes


def test_natural_textures_retexture_the_scene_and_nothing_else():
    plain, nat = scene(6, "indoor"), scene(6, "indoor", p_natural_textures=1.0)
    assert [(o.name, o.transform, o.mesh) for o in nat.objects] == [(o.name, o.transform, o.mesh) for o in plain.objects]
    assert nat.cameras == plain.cameras and nat.lights == plain.lights
    for a, b in zip(plain.objects, nat.objects):
        m, n = a.material, b.material
        if a.emitter_radiance is not None or m.kind not in ("diffuse", "plastic", "roughplastic", "principled"):
            if m.kind != "blend":
                assert n == m, a.name                                  # emitters, metals and glass as they were
            continue
        assert n.texture is not None and n.texture.kind == "natural", a.name
        assert dataclasses.replace(n, texture=None) == dataclasses.replace(m, texture=None)
        if m.texture is not None:                                      # a texture keeps its colours and scale
            assert dataclasses.replace(n.texture, kind=m.texture.kind) == m.texture
    shared = scene(6, "indoor", p_natural_textures=1.0, material_palette=3)     # a palette stays a palette
    content = [o.material for o in shared.objects if o.name.startswith("obj_")]
    assert 1 <= len({repr(m) for m in content}) <= 3
    assert scene(6, "outdoor", p_natural_textures=1.0) != scene(6, "outdoor")  # every family


def test_a_panel_is_put_in_view_on_a_wall_or_the_ceiling_of_the_room():
    """At rate 1 each indoor scene gets one panel, the rest of the scene as it was: on the ceiling (facing
    down) or on a wall (upright), inside the room's plan, at least 0.5 m from the camera and in its view."""
    from scene_gen.phenomena import _in_plan
    kinds, placed = set(), 0
    for seed in range(16):
        plain, lit = scene(seed, "indoor"), scene(seed, "indoor", p_panels_in_view=1.0)
        assert _without(lit, ("panel_",)) == plain.objects and lit.cameras == plain.cameras
        panels = [o for o in lit.objects if o.name == "panel_in_view"]
        if not panels:                                          # no free wall or ceiling in view: as it was
            assert lit == plain
            continue
        (p,), placed = panels, placed + 1
        ceiling = next(o for o in lit.objects if o.name == "room_ceiling")
        H, rects = ceiling.mesh.params["height"], np.asarray(ceiling.mesh.params["rects"])
        pos = np.asarray(p.transform.translate)
        assert _in_plan(rects, pos) and 0.3 <= pos[1] <= H - 0.009, (seed, pos)
        kinds.add(p.transform.rotate[0])
        if p.transform.rotate[0] == 180.0:
            assert pos[1] == pytest.approx(H - 0.01, abs=1e-3)
        assert 0.08 <= p.transform.scale[0] <= 0.35 and min(p.emitter_radiance) > 0
        cam = lit.cameras[0]
        q = cams.to_camera(cam, pos[None])[0]
        tx, ty = cams.tan_half(cam, (32, 32))
        assert q[2] > 0 and abs(q[0] / q[2]) <= tx and -0.31 * ty <= q[1] / q[2] <= ty, seed     # in view
        assert np.linalg.norm(pos - np.asarray(cam.origin)) >= 0.5
    assert kinds == {90.0, 180.0} and placed >= 13, (kinds, placed)
    assert scene(3, "outdoor", p_panels_in_view=1.0) == scene(3, "outdoor")          # indoor only


def test_a_render_shows_the_panel_brighter_than_anything_else():
    """The brightest pixels of a render of a scene with a panel lie where the panel projects."""
    from pipeline.render import RenderConfig, render_frame
    spec = scene(3, "indoor", res=32, p_panels_in_view=1.0)
    out = render_frame(spec, 0, RenderConfig(res=(32, 32), spp=4, layer_levels=1, ref_spp=32, ref_passes=2,
                                             ref_min_passes=2))
    lum = out["reference"].mean(axis=-1)
    p = next(o for o in spec.objects if o.name == "panel_in_view")
    cam = spec.cameras[0]
    q = cams.to_camera(cam, np.array([p.transform.translate]))[0]
    tx, ty = cams.tan_half(cam, (32, 32))
    col, row = (1 - q[0] / q[2] / tx) / 2 * 32, (1 - q[1] / q[2] / ty) / 2 * 32
    y, x = np.unravel_index(np.argmax(lum), lum.shape)
    assert abs(x + 0.5 - col) <= 3 and abs(y + 0.5 - row) <= 3, ((x, y), (col, row))
    assert lum.max() > 20 * np.median(lum)
