"""SceneSpec → Mitsuba: every BSDF and light loads and renders finite pixels; values checked against
closed forms (emitter radiance seen directly, a constant environment, Mitsuba's own look_at)."""
from __future__ import annotations

import numpy as np
import pytest

from scene_gen import to_mitsuba
from scene_gen.probes import make_probe, sun_direction
from scene_gen.spec import (CameraSpec, LightSpec, MaterialSpec, MeshSpec, ObjectSpec, SceneSpec, TextureSpec,
                            Transform, MATERIAL_KINDS)

CAM = CameraSpec((0.0, 1.0, 6.0), (0.0, 0.5, 0.0), fov=40.0)


def _material(kind: str) -> MaterialSpec:
    tex = TextureSpec("checker", (0.1, 0.2, 0.3), (0.9, 0.8, 0.7), uv_scale=4.0, seed=1)
    if kind == "blend":
        return MaterialSpec("blend", params={"weight": 0.3}, children=(_material("diffuse"), _material("roughconductor")))
    return MaterialSpec(kind, base_color=(0.6, 0.4, 0.2), specular_color=(0.9, 0.9, 0.8), roughness=0.3,
                        params={"int_ior": 1.45}, texture=tex if kind in ("diffuse", "plastic", "principled") else None)


def _scene(objects, lights, cam=CAM):
    return SceneSpec("outdoor", 7, tuple(objects), tuple(lights), (cam,))


def _render(mi, spec, res=16, spp=16):
    return np.array(mi.render(to_mitsuba.load(spec, 0, res=(res, res)), spp=spp, seed=3))


@pytest.mark.parametrize("kind", MATERIAL_KINDS)
def test_every_material_renders_finite(mi, kind):
    floor = ObjectSpec("floor", MeshSpec("plane"), MaterialSpec("diffuse"), Transform(scale=(5, 1, 5)))
    ball = ObjectSpec("ball", MeshSpec("sphere"), _material(kind), Transform((0, 0.6, 0), scale=(0.6, 0.6, 0.6)))
    img = _render(mi, _scene([floor, ball], [LightSpec("constant", {"radiance": [1, 1, 1]})]))
    assert img.shape == (16, 16, 3)
    assert np.isfinite(img).all() and (img >= 0).all()
    assert img.mean() > 0.05


@pytest.mark.parametrize("light", [
    LightSpec("point", {"position": [0, 3, 2], "intensity": [30, 30, 30]}),
    LightSpec("constant", {"radiance": [0.5, 0.5, 0.5]}),
    LightSpec("envmap", {"probe": {"seed": 5, "sun_elevation": 40}, "scale": 1.0, "rotation": 30}),
    LightSpec("sunsky", {"sun_direction": [0.3, 0.6, 0.5], "turbidity": 4}),
])
def test_every_light_renders_finite(mi, light):
    floor = ObjectSpec("floor", MeshSpec("plane"), MaterialSpec("diffuse"), Transform(scale=(5, 1, 5)))
    img = _render(mi, _scene([floor], [light]))
    assert np.isfinite(img).all() and img.mean() > 1e-3


def test_area_emitter_seen_directly_equals_its_radiance(mi):
    # A large emissive black box filling the view: every pixel sees exactly the emitted radiance.
    wall = ObjectSpec("wall", MeshSpec("box"), MaterialSpec("diffuse", base_color=(0, 0, 0)),
                      Transform((0, 0, 0), scale=(50, 50, 0.1)), emitter_radiance=(3.0, 2.0, 0.5))
    cam = CameraSpec((0, 0, 5), (0, 0, 0), fov=30)
    img = _render(mi, _scene([wall], [], cam), spp=4)
    np.testing.assert_allclose(img, np.broadcast_to([3.0, 2.0, 0.5], img.shape), rtol=1e-5)


def test_constant_environment_on_white_diffuse_ball_is_energy_conserving(mi):
    # A white Lambertian convex object under a uniform environment of radiance 1 looks exactly 1
    # everywhere (furnace test): it sees only the sky. Flat-shaded box, so shading and geometric
    # normals agree (smooth shading normals on a coarse sphere break energy conservation at grazing).
    ball = ObjectSpec("ball", MeshSpec("box"), MaterialSpec("diffuse", base_color=(1, 1, 1)), Transform(rotate=(30, 40, 0)))
    img = _render(mi, _scene([ball], [LightSpec("constant", {"radiance": [1, 1, 1]})],
                             CameraSpec((0, 0, 4), (0, 0, 0), fov=30)), spp=64)
    assert abs(img.mean() - 1.0) < 0.01          # MC noise of the mean of 256 px x 64 spp is ~0.003
    np.testing.assert_allclose(img, 1.0, atol=0.25)


def test_camera_matches_mitsuba_look_at(mi):
    cam = CameraSpec((1.0, 2.0, 3.0), (-1.0, 0.5, 0.2), up=(0.0, 1.0, 0.0), fov=50)
    ours = __import__("scene_gen.projection", fromlist=["x"]).camera_to_world(cam)
    theirs = np.array(mi.ScalarTransform4f().look_at(origin=cam.origin, target=cam.target, up=cam.up).matrix)
    np.testing.assert_allclose(ours, theirs, atol=1e-6)


def test_moving_object_is_displaced_by_velocity_times_tau(mi):
    obj = ObjectSpec("m", MeshSpec("box"), MaterialSpec("diffuse"), Transform((1, 2, 3), (10, 20, 30), (0.5, 1, 2)),
                     velocity=(0.5, 0.0, -1.0))
    v0, f0, n0, _ = to_mitsuba.world_mesh(obj, 0.0)
    v2, f2, n2, _ = to_mitsuba.world_mesh(obj, 2.5)
    np.testing.assert_allclose(v2 - v0, np.broadcast_to([1.25, 0.0, -2.5], v0.shape), atol=1e-5)
    np.testing.assert_array_equal(f0, f2)
    np.testing.assert_allclose(np.linalg.norm(n0, axis=1), 1.0, atol=1e-5)
    # the Mitsuba scene's bounding box follows tau
    spec = _scene([obj], [LightSpec("constant", {})])
    b0 = to_mitsuba.load(spec, 0, res=8, tau=0.0).bbox()
    b1 = to_mitsuba.load(spec, 0, res=8, tau=2.5).bbox()
    np.testing.assert_allclose(np.array(b1.min) - np.array(b0.min), [1.25, 0.0, -2.5], atol=1e-4)


def test_integrator_has_five_bounces_and_no_russian_roulette():
    spec = _scene([], [LightSpec("constant", {})])
    d = to_mitsuba.integrator_dict(spec)
    assert d["max_depth"] == 6 and d["rr_depth"] > d["max_depth"]


def test_probe_sun_is_where_its_parameters_say(mi):
    params = {"seed": 2, "sun_elevation": 30.0, "sun_azimuth": 120.0, "sun_radiance": 5e4}
    probe = make_probe(params, 128)
    assert probe.shape == (128, 256, 3) and np.isfinite(probe).all() and probe.min() >= 0
    # render with a camera looking at the sun: the centre pixel sees the sun disc (radiance ~5e4)
    s = sun_direction(params)
    cam = CameraSpec((0, 0, 0), tuple(s * 10), fov=2.0)
    img = _render(mi, _scene([], [LightSpec("envmap", {"probe": params})], cam), res=9, spp=16)
    assert img[4, 4].max() > 1e4
    # looking away from it sees only sky
    cam_away = CameraSpec((0, 0, 0), tuple(-s * 10 + np.array([0, 15, 0])), fov=2.0)
    assert _render(mi, _scene([], [LightSpec("envmap", {"probe": params})], cam_away), res=9, spp=4).max() < 10


def test_sunsky_sun_is_in_the_world_direction_given(mi):
    # y is up: a sun low in the -z direction (z <= 0 used to be "below the horizon" in Mitsuba's z-up frame)
    d = np.array([0.2, 0.35, -0.9])
    d /= np.linalg.norm(d)
    light = LightSpec("sunsky", {"sun_direction": d.tolist(), "turbidity": 3})
    toward = _render(mi, _scene([], [light], CameraSpec((0, 0, 0), tuple(d * 10), fov=1.0)), res=5, spp=16)
    assert toward[2, 2].max() > 1e4                      # the sun disc itself
    up = _render(mi, _scene([], [light], CameraSpec((0, 0, 0), (0, 10, 0.01), fov=20.0)), res=5, spp=16)
    down = _render(mi, _scene([], [light], CameraSpec((0, 0, 0), (0, -10, 0.01), fov=20.0)), res=5, spp=16)
    assert 0 < up.mean() < 1e3 and up.mean() > 10 * down.mean()   # sky above, (dark) ground below


def _shared_material_scene():
    """Three static boxes and a moving ball that share one material, a floor of another, an emitter."""
    mat = MaterialSpec("roughplastic", base_color=(0.7, 0.2, 0.1), specular_color=(0.3, 0.2, 0.1), roughness=0.4)
    objs = [ObjectSpec(f"box{i}", MeshSpec("box"), mat, Transform((i - 1.0, 0.3, 0.0), scale=(0.3, 0.3, 0.3)))
            for i in range(3)]
    objs += [ObjectSpec("ball", MeshSpec("sphere"), mat, Transform((0, 1.2, 0), scale=(0.3, 0.3, 0.3)),
                        velocity=(0.2, 0.0, 0.0)),
             ObjectSpec("floor", MeshSpec("plane"), MaterialSpec("diffuse"), Transform(scale=(5, 1, 5))),
             ObjectSpec("lamp", MeshSpec("box"), mat, Transform((0, 3, 0), scale=(0.2, 0.05, 0.2)),
                        emitter_radiance=(5.0, 5.0, 5.0))]
    return _scene(objs, [LightSpec("constant", {"radiance": [0.3, 0.3, 0.3]})])


def test_shape_groups_merge_static_objects_sharing_a_material():
    spec = _shared_material_scene()
    assert [n for n, _ in to_mitsuba.shape_groups(spec)] == [o.name for o in spec.objects]
    groups = to_mitsuba.shape_groups(spec, merge=True)
    names = [n for n, _ in groups]
    assert names == ["merged-000", "ball", "floor", "lamp"]        # moving and emissive objects stay apart
    assert [o.name for o in dict(groups)["merged-000"]] == ["box0", "box1", "box2"]


def test_merged_scene_has_the_same_geometry_and_image(mi):
    spec = _shared_material_scene()
    a = to_mitsuba.load(spec, 0, res=16)
    b = to_mitsuba.load(spec, 0, res=16, merge=True)
    assert len(a.shapes()) == 6 and len(b.shapes()) == 4
    np.testing.assert_array_equal(np.array(a.bbox().min), np.array(b.bbox().min))
    np.testing.assert_array_equal(np.array(a.bbox().max), np.array(b.bbox().max))
    tris = lambda s: sum(int(sh.face_count()) for sh in s.shapes())  # noqa: E731
    assert tris(a) == tris(b)
    # one BSDF instance serves the merged boxes, the ball and the lamp
    bs = {sh.id(): sh.bsdf() for sh in b.shapes()}
    assert bs["merged-000"] is bs["ball"] and bs["ball"] is bs["lamp"]
    # the image's distribution is unchanged: independent 64-spp renders agree within their noise
    ia = np.stack([np.asarray(mi.render(a, spp=16, seed=s), np.float64)[..., :3] for s in range(4)])
    ib = np.stack([np.asarray(mi.render(b, spp=16, seed=100 + s), np.float64)[..., :3] for s in range(4)])
    d = ia.mean(0).mean() - ib.mean(0).mean()
    se = np.sqrt(ia.mean(axis=(1, 2, 3)).var(ddof=1) / 4 + ib.mean(axis=(1, 2, 3)).var(ddof=1) / 4)
    assert abs(d) < 5 * se + 1e-4, (d, se)
