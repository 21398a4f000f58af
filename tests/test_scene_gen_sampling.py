"""Random scene synthesis without rendering: determinism, round trip, statistics, culling, budgets, bad input."""
from __future__ import annotations

import hashlib
import json
import math
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from scene_gen import cameras as cams
from scene_gen import meshes, rooms
from scene_gen.config import ConfigError, SceneGenConfig
from scene_gen.errors import SpecError
from scene_gen.materials import random_material
from scene_gen.sampling import sample_scene
from scene_gen.spec import MATERIAL_KINDS, PROCEDURAL_TEXTURE_KINDS, MeshSpec, SceneSpec

ROOT = Path(__file__).resolve().parent.parent


def _digest(spec: SceneSpec) -> str:
    return hashlib.sha256(spec.to_json().encode()).hexdigest()


def _content(spec):
    return [o for o in spec.objects if o.name.startswith("obj_")]


# ---------------------------------------------------------------------------------------------
# determinism and round trip

@pytest.mark.parametrize("kind", ["indoor", "outdoor"])
def test_same_seed_same_spec_and_other_seed_differs(kind):
    a = sample_scene(5, kind, num_frames=3)
    b = sample_scene(5, kind, num_frames=3)
    assert a.to_json() == b.to_json()
    assert a == b
    assert sample_scene(6, kind, num_frames=3).to_json() != a.to_json()
    assert a.num_frames == 3 and len({c.origin for c in a.cameras}) == 3   # the camera moves along its path


def test_same_seed_same_spec_across_processes():
    here = {f"{k}-{s}": _digest(sample_scene(s, k, num_frames=2)) for k, s in (("indoor", 11), ("outdoor", 12))}
    code = ("import hashlib, json\nfrom scene_gen.sampling import sample_scene\n"
            "print(json.dumps({f'{k}-{s}': hashlib.sha256(sample_scene(s, k, num_frames=2).to_json().encode())"
            ".hexdigest() for k, s in (('indoor', 11), ('outdoor', 12))}))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300,
                         env={"PYTHONHASHSEED": "123", "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout.strip().splitlines()[-1]) == here


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), kind=st.sampled_from(["indoor", "outdoor"]), frames=st.integers(1, 3))
def test_json_round_trip(seed, kind, frames):
    s = sample_scene(seed, kind, num_frames=frames, res=64)
    back = SceneSpec.from_json(s.to_json())
    assert back == s
    assert back.to_json() == s.to_json()


# ---------------------------------------------------------------------------------------------
# statistics over 200 seeds (specs only)

@pytest.fixture(scope="module")
def population():
    return {k: [sample_scene(s, k) for s in range(100)] for k in ("indoor", "outdoor")}


def test_light_counts(population):
    for s in population["indoor"]:
        area = [o for o in s.objects if o.emitter_radiance is not None]
        assert len(area) == 4 and all(max(o.emitter_radiance) > 0 for o in area)
        assert sorted(l.kind for l in s.lights) == ["envmap", "point"]
        assert {"room_floor", "room_walls", "room_ceiling"} <= {o.name for o in s.objects}
    kinds = []
    for s in population["outdoor"]:
        assert not any(o.emitter_radiance is not None for o in s.objects)
        assert len(s.lights) == 1 and s.lights[0].kind in ("sunsky", "envmap")
        kinds.append(s.lights[0].kind)
        assert "backdrop" in {o.name for o in s.objects}
    assert 25 <= kinds.count("sunsky") <= 75   # both environments occur (p = 0.5)


def test_object_counts(population):
    cfg = SceneGenConfig()
    indoor = [len(_content(s)) for s in population["indoor"]]
    outdoor = [len(_content(s)) for s in population["outdoor"]]
    assert max(indoor) <= cfg.indoor_objects and max(outdoor) <= cfg.outdoor_objects
    # culling only drops what no frame sees: most placed meshes are in view
    assert 30 <= np.mean(indoor) <= 50 and min(indoor) >= 10
    assert 60 <= np.mean(outdoor) <= 75 and min(outdoor) >= 40
    # indoor scenes hold furniture as well, ~50 meshes in all
    total_indoor = [len(s.objects) - 3 - 4 for s in population["indoor"]]
    assert 35 <= np.mean(total_indoor) <= 55


def test_defocus_and_motion_shares_are_half(population):
    scenes = population["indoor"] + population["outdoor"]
    n = len(scenes)
    bound = 4 * math.sqrt(n * 0.25)   # 4 standard deviations of Binomial(200, 0.5)
    for flag in ("has_defocus", "has_motion"):
        k = sum(getattr(s, flag) for s in scenes)
        assert abs(k - n / 2) <= bound, (flag, k)
    # both flags are independent draws: all four combinations occur
    combos = {(s.has_defocus, s.has_motion) for s in scenes}
    assert len(combos) == 4


def test_motion_and_lens_parameters(population):
    cfg = SceneGenConfig()
    moving = movable = 0
    for s in population["indoor"] + population["outdoor"]:
        for c in s.cameras:
            assert cfg.fov_range[0] <= c.fov <= cfg.fov_range[1]
            if s.has_defocus:
                ratio = c.aperture_radius / c.focus_distance
                assert cfg.aperture_range[0] * 0.999 <= ratio <= cfg.aperture_range[1] * 1.001
            else:
                assert c.aperture_radius == 0.0
        if not s.has_motion:
            assert all(o.velocity is None for o in s.objects)   # static scenes carry no motion data
            continue
        for o in s.objects:
            if o.name.startswith(("room_", "backdrop", "light_", "table", "shelf", "pillar")):
                assert o.velocity is None
        c = _content(s)
        moving += sum(o.moving for o in c)
        movable += len(c)
    assert 0.4 <= moving / movable <= 0.6   # p_object_motion = 0.5 within a motion scene


# ---------------------------------------------------------------------------------------------
# geometry: culling, budgets, resting objects

def test_sphere_frustum_culling_and_motion_sweep():
    cam = cams.make_camera((0, 1, 0), (0, 1, 10), 40.0)
    centers = np.array([[0, 1, 5], [0, 1, -5], [6, 1, 5], [0, 1, -0.2], [-8, 1, 8]], float)
    radii = np.array([0.5, 0.5, 0.5, 0.5, 0.5])
    vis = cams.sphere_in_frustum(cam, centers, radii, (64, 64))
    # in front | behind | far to the side (tan 20° * 5 = 1.8 < 6) | straddles the camera plane | side
    assert vis.tolist() == [True, False, False, True, False]
    # behind the camera but moving into view within the exposure: kept; too slow: dropped
    v_fast = np.array([[0, 0, 30.0]])
    v_slow = np.array([[0, 0, 1.0]])
    c = np.array([[0, 1, -5.0]])
    assert cams.visible_any_frame([cam], c, [0.5], v_fast, (64, 64), shutter=0.5)[0]
    assert not cams.visible_any_frame([cam], c, [0.5], v_slow, (64, 64), shutter=0.5)[0]
    assert not cams.visible_any_frame([cam], c, [0.5], v_fast, (64, 64), shutter=0.0)[0]


@pytest.mark.parametrize("kind", ["indoor", "outdoor"])
def test_sampled_scenes_drop_objects_behind_the_camera(kind):
    cfg = SceneGenConfig(outdoor_objects=150, indoor_objects=80, p_motion=0.0)
    for seed in range(3):
        s = sample_scene(seed, kind, config=cfg)
        cam = s.cameras[0]
        fwd = np.subtract(cam.target, cam.origin)
        fwd = fwd / np.linalg.norm(fwd)
        for o in _content(s):
            scale = np.asarray(o.transform.scale)
            z = float(np.dot(np.subtract(o.transform.translate, cam.origin), fwd))
            assert z > -np.linalg.norm(scale) * 1.8, (o.name, z)   # nothing entirely behind the camera
        if kind == "outdoor":   # a tenth is placed anywhere around: those out of view are dropped
            assert len(_content(s)) < cfg.outdoor_objects


def test_triangle_budgets_follow_screen_size():
    cfg = SceneGenConfig()
    s_small = sample_scene(3, "outdoor", res=64)
    s_big = sample_scene(3, "outdoor", res=512)
    assert [o.name for o in s_small.objects] == [o.name for o in s_big.objects]
    b_small = np.array([o.mesh.triangle_budget for o in _content(s_small)])
    b_big = np.array([o.mesh.triangle_budget for o in _content(s_big)])
    assert (b_big >= b_small).all() and (b_big > b_small).mean() > 0.5
    assert b_small.min() >= cfg.min_triangles and b_big.max() <= cfg.max_triangles
    # within one image: projected radius (independent pinhole estimate) orders the budgets
    cam = s_big.cameras[0]
    f_px = 256 / math.tan(math.radians(cam.fov) / 2)
    r_px = []
    for o in _content(s_big):
        d = np.linalg.norm(np.subtract(o.transform.translate, cam.origin))
        r_px.append(f_px * np.linalg.norm(o.transform.scale) / d)
    r_px = np.array(r_px)
    order = np.argsort(r_px)
    small, large = order[: len(order) // 4], order[-len(order) // 4:]
    assert b_big[large].mean() > 2 * b_big[small].mean()
    for i in large:
        for j in small:
            if r_px[i] > 3 * r_px[j]:
                assert b_big[i] >= b_big[j]
    # the room, backdrop and lights keep their full resolution
    assert all(o.mesh.triangle_budget == 0 for o in s_big.objects if o.name == "backdrop")


def test_objects_rest_on_the_ground():
    """World-space meshes (built by scene_gen.meshes, an independent oracle) touch y = 0."""
    from scene_gen.to_mitsuba import world_mesh
    import dataclasses
    s = sample_scene(2, "outdoor", config=SceneGenConfig(outdoor_objects=30, p_floating=0.0, p_motion=0.0))
    exact = ("sphere", "box", "cylinder", "capsule", "cone", "torus", "revolve", "extrude")
    checked = 0
    for o in _content(s):
        if o.mesh.kind not in exact:
            continue
        o = dataclasses.replace(o, mesh=dataclasses.replace(o.mesh, triangle_budget=0))
        v = world_mesh(o)[0]
        size = float(np.max(o.transform.scale))
        assert abs(float(v[:, 1].min())) < 0.03 * size + 1e-3, (o.name, o.mesh.kind, float(v[:, 1].min()))
        checked += 1
    assert checked >= 10
    meshes.cache_clear()


# ---------------------------------------------------------------------------------------------
# materials and rooms

def test_materials_cover_every_kind_and_texture():
    rng = np.random.default_rng(0)
    mats = [random_material(rng) for _ in range(400)]
    assert {m.kind for m in mats} == set(MATERIAL_KINDS)
    tex = [m.texture for m in mats if m.texture is not None] + [c.texture for m in mats for c in m.children if c.texture]
    assert {t.kind for t in tex} == set(PROCEDURAL_TEXTURE_KINDS)
    assert len({t.uv_scale for t in tex}) > 20 and min(t.uv_scale for t in tex) < 1 < max(t.uv_scale for t in tex)
    for m in mats:
        if m.kind in ("dielectric", "thindielectric", "conductor", "plastic"):
            assert m.roughness == 0.0
        if m.kind == "diffuse":
            assert m.roughness == 1.0 and m.specular_color == (0.0, 0.0, 0.0)
    with pytest.raises(SpecError, match="material kind"):
        random_material(rng, "velvet")


@pytest.mark.parametrize("room_type", rooms.ROOM_TYPES)
def test_room_meshes_face_inward_with_openings(room_type):
    assert len(rooms.ROOM_TYPES) >= 8
    rng = np.random.default_rng(7)
    plan = rooms.random_plan(rng, room_type)
    openings, skylights = rooms.random_openings(rng, room_type, plan["rects"], plan["height"])
    assert len([o for o in openings if o[3] > 0]) >= 2   # windows (doors start at the floor)
    H = plan["height"]
    wall_area = sum(math.dist(a, b) for a, b, _ in rooms.room_walls(plan["rects"])) * H
    for part in rooms.PARTS:
        m = meshes.build(MeshSpec("room", {**plan, "openings": openings, "skylights": skylights, "part": part}))
        tri = m.vertices[m.faces].astype(np.float64)
        fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        assert (np.einsum("ij,ij->i", fn, m.normals[m.faces[:, 0]]) > 0).all()   # winding matches normals
        probe = tri.mean(1) + 0.01 * m.normals[m.faces[:, 0]]                    # a step along the normal
        assert rooms.inside_plan(plan["rects"], probe[:, [0, 2]]).all()          # ... stays inside the room
        assert ((probe[:, 1] > 0) & (probe[:, 1] < H)).all()
        area = 0.5 * np.linalg.norm(fn, axis=1).sum()
        if part == "walls":
            holes = sum((o[2] - o[1]) * (o[4] - o[3]) for o in openings)
            assert area == pytest.approx(wall_area - holes, rel=1e-4)
        assert m.uv is not None and m.uv.shape == (len(m.vertices), 2)


# ---------------------------------------------------------------------------------------------
# bad input

@pytest.mark.parametrize("kw, field", [
    ({"outdoor_objects": -1}, "outdoor_objects"),
    ({"indoor_objects": -5}, "indoor_objects"),
    ({"fov_range": (0.0, 40.0)}, "fov_range"),
    ({"fov_range": (30.0, 180.0)}, "fov_range"),
    ({"fov_range": (50.0, 20.0)}, "fov_range"),
    ({"p_defocus": 1.5}, "p_defocus"),
    ({"aperture_range": (0.0, 0.1)}, "aperture_range"),
    ({"min_triangles": 500, "max_triangles": 100}, "min_triangles"),
])
def test_bad_config_names_the_field(kw, field):
    with pytest.raises(ConfigError, match=field):
        SceneGenConfig(**kw)


def test_config_round_trip_and_unknown_fields():
    cfg = SceneGenConfig(outdoor_objects=10, fov_range=(20.0, 30.0))
    assert SceneGenConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    with pytest.raises(ConfigError, match="outdoor_objectz"):
        SceneGenConfig.from_dict({"outdoor_objectz": 3})


def test_bad_scene_arguments():
    with pytest.raises(ConfigError, match="kind"):
        sample_scene(0, "underwater")
    with pytest.raises(ConfigError, match="seed"):
        sample_scene(-1, "indoor")
    with pytest.raises(ConfigError, match="num_frames"):
        sample_scene(0, "indoor", num_frames=0)
    with pytest.raises(SpecError, match="camera.fov"):
        cams.make_camera((0, 0, 0), (0, 0, 1), 180.0)


def test_model_folder_errors_and_broken_files(tmp_path):
    with pytest.raises(ConfigError, match="model_folder"):
        SceneGenConfig(model_folder=str(tmp_path / "missing"))
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "chair.obj").write_text("this is not an obj file\nv 1 2\nf 9 9 9\n")
    with pytest.warns(UserWarning, match="chair.obj"):
        with pytest.raises(ConfigError, match="no loadable"):
            sample_scene(0, "outdoor", config=SceneGenConfig(model_folder=str(broken)))
    # a folder with one good and one broken model: the broken one is skipped with a warning
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    (mixed / "bad.ply").write_bytes(b"ply\nformat nonsense\n")
    verts = [(x, y, z) for x in (0, 1) for y in (0, 2) for z in (0, 1)]
    faces = [(1, 2, 4, 3), (5, 7, 8, 6), (1, 5, 6, 2), (3, 4, 8, 7), (1, 3, 7, 5), (2, 6, 8, 4)]
    (mixed / "block.obj").write_text("".join(f"v {x} {y} {z}\n" for x, y, z in verts)
                                     + "".join("f " + " ".join(map(str, f)) + "\n" for f in faces))
    cfg = SceneGenConfig(model_folder=str(mixed), p_user_model=1.0, outdoor_objects=6, p_motion=0.0, p_floating=0.0)
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        s = sample_scene(1, "outdoor", config=cfg)
    assert any("bad.ply" in str(w.message) for w in rec)
    files = [o for o in _content(s)]
    assert files and all(o.mesh.kind == "file" and o.mesh.params["path"].endswith("block.obj") for o in files)
    # the block (1 x 2 x 1, normalised to half extents 0.5, 1, 0.5) stands on the ground
    for o in files:
        if o.transform.rotate[0] == 0.0:
            assert o.transform.translate[1] == pytest.approx(o.transform.scale[1], rel=1e-3)


@pytest.mark.parametrize("kind", ["indoor", "outdoor"])
def test_clip_camera_path_is_smooth_and_stays_in_the_room(kind):
    s = sample_scene(9, kind, num_frames=24)
    o = np.array([c.origin for c in s.cameras])
    step = np.linalg.norm(np.diff(o, axis=0), axis=1)
    assert step.max() > 0 and step.max() < 3 * np.median(step) + 1e-6     # no jumps
    accel = np.linalg.norm(np.diff(o, 2, axis=0), axis=1)
    assert accel.max() < step.max()                                        # direction changes gently
    if kind == "indoor":
        room = next(x for x in s.objects if x.name == "room_floor").mesh.params
        assert rooms.inside_plan(room["rects"], o[:, [0, 2]]).all()
        assert ((o[:, 1] > 0) & (o[:, 1] < room["height"])).all()
        t = np.array([c.target for c in s.cameras])
        assert rooms.inside_plan(room["rects"], t[:, [0, 2]]).all()


@pytest.mark.parametrize("kind", ["indoor", "outdoor"])
def test_material_palette_keeps_the_layout_and_limits_content_materials(kind):
    from scene_gen.to_mitsuba import material_key
    base = sample_scene(11, kind, res=64)
    pal = sample_scene(11, kind, res=64, config=SceneGenConfig(material_palette=4))
    assert [(o.name, o.mesh, o.transform, o.velocity) for o in base.objects] == \
        [(o.name, o.mesh, o.transform, o.velocity) for o in pal.objects]
    assert base.cameras == pal.cameras and base.lights == pal.lights
    content = [o for o in pal.objects if o.name.startswith("obj_")]
    assert len(content) > 8
    assert len({material_key(o.material) for o in content}) <= 4
    assert len({material_key(o.material) for o in base.objects if o.name.startswith("obj_")}) > 8
    # structure and light panels keep their own materials
    for a, b in zip(base.objects, pal.objects):
        if not a.name.startswith("obj_"):
            assert a.material == b.material, a.name
    assert pal == sample_scene(11, kind, res=64, config=SceneGenConfig(material_palette=4))


def test_material_palette_zero_is_not_written():
    assert "material_palette" not in SceneGenConfig().to_dict()
    d = SceneGenConfig(material_palette=16).to_dict()
    assert d["material_palette"] == 16 and SceneGenConfig.from_dict(d) == SceneGenConfig(material_palette=16)
    with pytest.raises(ConfigError, match="material_palette"):
        SceneGenConfig(material_palette=-1)


@pytest.mark.parametrize("kind", ["indoor", "outdoor"])
def test_without_pymeshlab_the_scene_leaves_out_its_meshes_and_nothing_else(kind):
    """``pymeshlab: false`` (a machine without it): the blob and boolean objects are left out, no mesh
    has a triangle budget, and every other object, light and camera is the one of the full scene."""
    full = sample_scene(11, kind, res=64)
    bare = sample_scene(11, kind, res=64, config=SceneGenConfig(pymeshlab=False))
    assert not any(meshes.needs_pymeshlab(o.mesh) for o in bare.objects)
    assert any(meshes.needs_pymeshlab(o.mesh) for o in full.objects)
    kept = [o for o in full.objects if not ({o.mesh.kind} | {c.kind for c in o.mesh.children}) & {"blob", "boolean"}]
    assert [o.name for o in bare.objects] == [o.name for o in kept]
    assert [(o.material, o.transform, o.velocity, o.mesh.kind, o.mesh.params) for o in bare.objects] == \
        [(o.material, o.transform, o.velocity, o.mesh.kind, o.mesh.params) for o in kept]
    assert bare.cameras == full.cameras and bare.lights == full.lights
    assert "pymeshlab" not in SceneGenConfig().to_dict()
    assert SceneGenConfig.from_dict(SceneGenConfig(pymeshlab=False).to_dict()) == SceneGenConfig(pymeshlab=False)
    with pytest.raises(ConfigError, match="scene_gen.pymeshlab"):
        SceneGenConfig(pymeshlab="no")
