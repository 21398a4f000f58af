"""SceneSpec: validation names the bad field, JSON round trip is exact."""
from __future__ import annotations

import json

import pytest
from hypothesis import given, settings, strategies as st

from scene_gen.errors import SpecError
from scene_gen.spec import (CameraSpec, LightSpec, MaterialSpec, MeshSpec, ObjectSpec, SceneSpec, TextureSpec,
                            Transform, MATERIAL_KINDS)

finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False, allow_infinity=False)
unit = st.floats(min_value=0.0, max_value=1.0, allow_nan=False)
vec3 = st.tuples(finite, finite, finite)
col3 = st.tuples(unit, unit, unit)


@st.composite
def materials(draw, depth=0):
    kinds = [k for k in MATERIAL_KINDS if k != "blend" or depth == 0]
    kind = draw(st.sampled_from(kinds))
    tex = draw(st.none() | st.builds(TextureSpec, st.sampled_from(["checker", "noise", "stripes", "cells"]), col3, col3,
                                     st.floats(min_value=0.01, max_value=100), st.integers(0, 2**31)))
    children = (draw(materials(depth=1)), draw(materials(depth=1))) if kind == "blend" else ()
    return MaterialSpec(kind, draw(col3), draw(col3), draw(unit), {"int_ior": 1.5, "weight": 0.25}, tex, children)


@st.composite
def scenes(draw):
    n = draw(st.integers(0, 4))
    objs = tuple(ObjectSpec(f"o{i}", MeshSpec(draw(st.sampled_from(["sphere", "box", "blob"])), {"k": [1, 2.5]},
                                               draw(st.integers(0, 99)), draw(st.integers(0, 5000))),
                            draw(materials()), Transform(draw(vec3), draw(vec3), (1.0, 2.0, 0.5)),
                            draw(st.none() | vec3), draw(st.none() | col3))
                 for i in range(n))
    cams = tuple(CameraSpec(draw(vec3), (1e7, 0.0, 0.0), fov=draw(st.floats(1, 179)),
                            aperture_radius=draw(st.floats(0, 1)), focus_distance=draw(st.floats(0.1, 100)))
                 for _ in range(draw(st.integers(1, 3))))
    lights = (LightSpec("point", {"position": [0, 1, 2], "intensity": [1, 1, 1]}), LightSpec("envmap", {"probe": {"seed": 3}}))
    return SceneSpec(draw(st.sampled_from(["indoor", "outdoor"])), draw(st.integers(0, 2**32)), objs, lights, cams,
                     shutter=draw(unit))


@settings(max_examples=60, deadline=None)
@given(scenes())
def test_json_round_trip_is_exact(spec):
    text = spec.to_json()
    back = SceneSpec.from_json(text)
    assert back == spec
    assert back.to_json() == text


def test_derived_flags():
    cam = CameraSpec((0, 0, 5), (0, 0, 0))
    obj = ObjectSpec("a", MeshSpec("sphere"), MaterialSpec("diffuse"))
    still = SceneSpec("outdoor", 1, (obj,), (), (cam,))
    assert not still.has_motion and not still.has_defocus and still.num_frames == 1
    moving = SceneSpec("outdoor", 1, (ObjectSpec("a", MeshSpec("sphere"), MaterialSpec("diffuse"), velocity=(1, 0, 0)),), (),
                       (CameraSpec((0, 0, 5), (0, 0, 0), aperture_radius=0.1, focus_distance=5),))
    assert moving.has_motion and moving.has_defocus
    # zero velocity is not motion; a closed shutter gives no blur
    assert not SceneSpec("outdoor", 1, (ObjectSpec("a", MeshSpec("sphere"), MaterialSpec("diffuse"), velocity=(0, 0, 0)),),
                         (), (cam,)).has_motion
    assert not SceneSpec("outdoor", 1, moving.objects, (), (cam,), shutter=0.0).has_motion


@pytest.mark.parametrize("make, field", [
    (lambda: CameraSpec((0, 0, 1), (0, 0, 0), fov=0.0), "camera.fov"),
    (lambda: CameraSpec((0, 0, 1), (0, 0, 0), fov=180.0), "camera.fov"),
    (lambda: CameraSpec((0, 0, 1), (0, 0, 0), aperture_radius=-1), "camera.aperture_radius"),
    (lambda: CameraSpec((0, 0, 0), (0, 0, 0)), "camera.target"),
    (lambda: CameraSpec((0, 0, float("nan")), (0, 0, 0)), "camera.origin"),
    (lambda: MaterialSpec("velvet"), "material.kind"),
    (lambda: MaterialSpec("diffuse", base_color=(2, 0, 0)), "material.base_color"),
    (lambda: MaterialSpec("blend"), "blend"),
    (lambda: MeshSpec("teapot"), "mesh.kind"),
    (lambda: MeshSpec("sphere", triangle_budget=-3), "mesh.triangle_budget"),
    (lambda: Transform(scale=(1, 0, 1)), "transform.scale"),
    (lambda: SceneSpec("Moon base", 0, (), (), (CameraSpec((0, 0, 1), (0, 0, 0)),)), "scene.kind"),
    (lambda: SceneSpec("indoor", -1, (), (), (CameraSpec((0, 0, 1), (0, 0, 0)),)), "scene.seed"),
    (lambda: SceneSpec("indoor", 0, (), (), ()), "scene.cameras"),
    (lambda: LightSpec("laser"), "light.kind"),
])
def test_bad_values_name_the_field(make, field):
    with pytest.raises(SpecError, match=field.replace(".", r"\.")):
        make()


def test_unknown_json_field_and_bad_json_are_refused():
    spec = SceneSpec("indoor", 0, (), (), (CameraSpec((0, 0, 1), (0, 0, 0)),))
    d = json.loads(spec.to_json())
    d["cameras"][0]["zoom"] = 2
    with pytest.raises(SpecError, match="zoom"):
        SceneSpec.from_dict(d)
    with pytest.raises(SpecError, match="malformed"):
        SceneSpec.from_json("{not json")
    with pytest.raises(SpecError, match="frame 3 out of range"):
        spec.camera(3)
