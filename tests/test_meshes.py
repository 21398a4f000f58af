"""scene_gen.meshes: validity of every kind, determinism, decimation, budgets, user models."""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from scene_gen import meshes as M
from scene_gen.errors import MeshError, SpecError
from scene_gen.spec import MeshSpec

ROOT = Path(__file__).resolve().parents[1]

PROCEDURAL = [
    MeshSpec("sphere"), MeshSpec("box", {"extents": [2.0, 1.0, 0.5]}), MeshSpec("cylinder"),
    MeshSpec("capsule"), MeshSpec("cone"), MeshSpec("torus"), MeshSpec("plane", {"resolution": 4}),
    MeshSpec("plane", {"resolution": 8, "bend": 0.5}),
    *[MeshSpec("revolve", seed=s) for s in range(5)],              # several profile styles
    *[MeshSpec("extrude", {"bevel": 0.1 * (s % 2)}, seed=s) for s in range(5)],
    MeshSpec("extrude", {"outline": [[0, 0], [2, 0], [2, 2], [1.5, 2], [1.5, 0.5], [0.5, 0.5], [0.5, 2], [0, 2]],
                         "height": 0.5}),                          # U shape: not star-shaped
    *[MeshSpec("blob", seed=s) for s in range(2)],
    *[MeshSpec("boolean", {"op": op}, seed=i, children=(MeshSpec("box"), MeshSpec("sphere", {"subdivisions": 2})))
      for i, op in enumerate(M.BOOLEAN_OPS)],
    MeshSpec("boolean", {"op": "union", "b_scale": 0.6, "b_offset": [0.0, 0.9, 0.0]},
             children=(MeshSpec("cylinder"), MeshSpec("torus"))),
]
OPEN_KINDS = ("plane",)


def _ids(specs):
    return [f"{s.kind}-{s.seed}-{i}" for i, s in enumerate(specs)]


def _face_normals(m: M.MeshData) -> tuple[np.ndarray, np.ndarray]:
    t = m.vertices.astype(np.float64)[m.faces]
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    a = np.linalg.norm(n, axis=1)
    return n / np.maximum(a, 1e-300)[:, None], a / 2


def _closed(m: M.MeshData) -> trimesh.Trimesh:
    """The mesh with split seam vertices merged again (trimesh's own merge as an oracle)."""
    return trimesh.Trimesh(m.vertices.astype(np.float64), m.faces, process=True)


def assert_valid(m: M.MeshData, *, closed: bool, bound: float = 1.0 + 1e-5):
    assert m.vertices.dtype == np.float32 and m.vertices.shape[1] == 3
    assert m.faces.dtype == np.int32 and m.faces.shape[1] == 3 and m.num_triangles > 0
    assert np.isfinite(m.vertices).all()
    assert m.faces.min() >= 0 and m.faces.max() < len(m.vertices)
    assert len(np.unique(m.faces)) == len(m.vertices), "unreferenced vertices"
    fn, area = _face_normals(m)
    assert area.min() > 1e-9, "degenerate triangle"
    assert np.abs(m.vertices).max() <= bound
    assert m.uv is not None and m.uv.shape == (len(m.vertices), 2) and np.isfinite(m.uv).all()
    assert m.normals is not None and m.normals.shape == m.vertices.shape
    np.testing.assert_allclose(np.linalg.norm(m.normals, axis=1), 1.0, atol=1e-5)
    # shading normals lean the same way as the winding (no flipped faces)
    assert (np.einsum("ij,ij->i", m.normals[m.faces].mean(axis=1), fn) > 0).all()
    if closed:
        tm = _closed(m)
        assert tm.is_watertight and tm.is_winding_consistent
        assert tm.volume > 0, "faces must wind counter-clockwise seen from outside"
    assert not m.vertices.flags.writeable and not m.faces.flags.writeable


@pytest.mark.parametrize("spec", PROCEDURAL, ids=_ids(PROCEDURAL))
def test_every_kind_builds_a_valid_mesh(spec):
    m = M.build(spec)
    assert_valid(m, closed=spec.kind not in OPEN_KINDS)
    b = m.bounds
    if spec.kind != "plane":      # normalised: centred, largest half-extent exactly 1
        np.testing.assert_allclose((b[0] + b[1]) / 2, 0.0, atol=1e-5)
        assert abs(float((b[1] - b[0]).max()) / 2 - 1.0) < 1e-5


def test_primitive_shapes_match_analytic_oracles():
    s = M.build(MeshSpec("sphere", {"subdivisions": 3}))
    np.testing.assert_allclose(np.linalg.norm(s.vertices, axis=1), 1.0, atol=1e-5)
    np.testing.assert_allclose(np.einsum("ij,ij->i", s.normals, s.vertices), 1.0, atol=2e-3)  # radial normals
    box = M.build(MeshSpec("box", {"extents": [2.0, 1.0, 0.5]}))
    assert box.num_triangles == 12
    assert _closed(box).volume == pytest.approx(2.0 * 1.0 * 0.5)     # largest half-extent already 1
    # flat-shaded box: every normal is an axis direction
    assert np.allclose(np.sort(np.abs(box.normals), axis=1), [0, 0, 1], atol=1e-6)
    n = 32
    cyl = M.build(MeshSpec("cylinder", {"sections": n}))
    polygon_area = 0.5 * n * math.sin(2 * math.pi / n)
    assert _closed(cyl).volume == pytest.approx(polygon_area * 2.0, rel=1e-5)
    np.testing.assert_allclose(cyl.bounds, [[-1, -1, -1], [1, 1, 1]], atol=1e-6)   # y axis up
    side = np.abs(cyl.normals[:, 1]) < 1e-6      # smooth sides: radial normals, caps split off
    np.testing.assert_allclose(np.linalg.norm(cyl.normals[side][:, [0, 2]], axis=1), 1.0, atol=1e-5)
    torus = M.build(MeshSpec("torus", {"major_radius": 1.0, "minor_radius": 0.25}))
    np.testing.assert_allclose(torus.bounds[1], [1.0, 0.2, 1.0], atol=1e-5)      # (R+r) -> 1, r/(R+r) = 0.2
    plane = M.build(MeshSpec("plane", {"resolution": 3}))
    assert plane.num_triangles == 18 and np.all(plane.vertices[:, 1] == 0)
    np.testing.assert_allclose(plane.normals, np.tile([0, 1, 0], (len(plane.normals), 1)), atol=1e-6)
    fn, _ = _face_normals(plane)
    assert (fn[:, 1] > 0.999).all()


def test_extrude_uses_the_given_outline_and_height():
    sq = [[-1, -1], [1, -1], [1, 1], [-1, 1]]
    m = M.build(MeshSpec("extrude", {"outline": sq, "height": 1.0}))
    assert _closed(m).volume == pytest.approx(2 * 2 * 1.0)           # a 2 x 1 x 2 box (half-extent 1)
    u = M.build(MeshSpec("extrude", {"outline": [[0, 0], [2, 0], [2, 2], [1.5, 2], [1.5, 0.5], [0.5, 0.5],
                                                   [0.5, 2], [0, 2]], "height": 0.5}))
    area = 4 - 1 * 1.5                                                 # 2 x 2 square minus the 1 x 1.5 notch
    assert _closed(u).volume == pytest.approx(area * 0.5)              # already half-extent 1
    with pytest.raises(SpecError, match="outline"):
        M.build(MeshSpec("extrude", {"outline": [[0, 0], [1, 1], [1, 0], [0, 1]]}))   # bow tie


def test_same_spec_same_bytes_and_cache():
    spec = MeshSpec("boolean", {"op": "difference"}, seed=3,
                    children=(MeshSpec("blob", seed=4), MeshSpec("cylinder")), triangle_budget=400)
    a = M.build(spec)
    assert M.build(spec) is a                                  # served from the cache
    M.cache_clear()
    b = M.build(MeshSpec.from_dict(json.loads(json.dumps(spec.to_dict()))))
    assert b is not a and a.digest() == b.digest()
    for x, y in ((a.vertices, b.vertices), (a.faces, b.faces), (a.normals, b.normals), (a.uv, b.uv)):
        assert x.tobytes() == y.tobytes()


def test_seeds_change_random_kinds():
    for kind in ("revolve", "extrude", "blob"):
        digests = {M.build(MeshSpec(kind, seed=s)).digest() for s in range(4)}
        assert len(digests) == 4, kind


CROSS_PROCESS = [
    MeshSpec("blob", seed=11), MeshSpec("revolve", seed=12), MeshSpec("extrude", {"bevel": 0.2}, seed=13),
    MeshSpec("boolean", {"op": "union"}, seed=14, children=(MeshSpec("torus"), MeshSpec("capsule"))),
    MeshSpec("blob", seed=15, triangle_budget=300),
]


def test_identical_bytes_across_processes():
    code = ("import json, sys\nfrom scene_gen import meshes\nfrom scene_gen.spec import MeshSpec\n"
            "specs = [MeshSpec.from_dict(d) for d in json.loads(sys.stdin.read())]\n"
            "print(json.dumps([meshes.build(s).digest() for s in specs]))\n")
    payload = json.dumps([s.to_dict() for s in CROSS_PROCESS])
    outs = []
    for seed in ("0", "1"):      # different hash seeds: no dependence on set/dict ordering
        r = subprocess.run([sys.executable, "-c", code], input=payload, capture_output=True, text=True,
                           cwd=ROOT, env={"PYTHONHASHSEED": seed, "PATH": "/usr/bin:/bin"}, timeout=120)
        assert r.returncode == 0, r.stderr
        outs.append(json.loads(r.stdout.strip().splitlines()[-1]))
    assert outs[0] == outs[1] == [M.build(s).digest() for s in CROSS_PROCESS]


def _hausdorff(a: M.MeshData, b: M.MeshData, n: int = 1500) -> float:
    """Symmetric Hausdorff distance estimated from surface samples and vertices, exact point-to-mesh."""
    ta, tb = _closed(a), _closed(b)
    pa = np.concatenate([trimesh.sample.sample_surface(ta, n, seed=0)[0], ta.vertices])
    pb = np.concatenate([trimesh.sample.sample_surface(tb, n, seed=1)[0], tb.vertices])
    da = trimesh.proximity.closest_point(tb, pa)[1]
    db = trimesh.proximity.closest_point(ta, pb)[1]
    return float(max(da.max(), db.max()))


@pytest.mark.parametrize("spec, budget, max_dist", [
    (MeshSpec("sphere", {"subdivisions": 4}), 300, 0.04),
    (MeshSpec("blob", seed=5), 300, 0.05),
    (MeshSpec("torus"), 400, 0.05),
    (MeshSpec("boolean", {"op": "difference"}, children=(MeshSpec("box"), MeshSpec("sphere"))), 300, 0.05),
])
def test_decimation_cuts_triangles_and_keeps_the_silhouette(spec, budget, max_dist):
    full = M.build(spec)
    low = M.build(MeshSpec(spec.kind, spec.params, spec.seed, budget, spec.children))
    assert full.num_triangles > 2 * budget
    assert budget // 2 <= low.num_triangles <= budget
    assert_valid(low, closed=True, bound=1.05)
    h = _hausdorff(full, low)
    assert h < max_dist, f"Hausdorff {h:.4f} for {spec.kind} at {budget} triangles"
    # the bounding boxes (the silhouette's extent from every axis view) barely move
    np.testing.assert_allclose(low.bounds, full.bounds, atol=max_dist)
    # a much coarser decimation deviates more: the distance measures something
    assert _hausdorff(full, M.build(MeshSpec(spec.kind, spec.params, spec.seed, 40, spec.children))) > h


def test_public_decimate_on_split_meshdata():
    m = M.build(MeshSpec("capsule"))
    d = M.decimate(m, 200)
    assert d.num_triangles <= 200
    assert_valid(d, closed=True, bound=1.05)
    assert M.decimate(m, 10**6) is m
    with pytest.raises(SpecError):
        M.decimate(m, 0)


def test_triangle_budget_is_monotone_and_bounded():
    radii = np.concatenate([[0.0], np.geomspace(0.01, 1e5, 300)])
    b = [M.triangle_budget(r) for r in radii]
    assert all(isinstance(x, int) for x in b)
    assert all(x <= y for x, y in zip(b, b[1:]))
    assert b[0] == 32 and b[-1] == 20000
    assert M.triangle_budget(10.0, tris_per_px=1.0, min=8, max=100) == 100
    assert M.triangle_budget(2.0, tris_per_px=1.0, min=8, max=100) == math.ceil(math.pi * 4)
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(SpecError, match="projected_radius_px"):
            M.triangle_budget(bad)
    # a far (small) object gets fewer triangles than a near one, and decimation honours it
    spec = MeshSpec("blob", seed=2)
    far = M.build(MeshSpec("blob", seed=2, triangle_budget=M.triangle_budget(4.0)))
    near = M.build(MeshSpec("blob", seed=2, triangle_budget=M.triangle_budget(60.0)))
    assert far.num_triangles <= M.triangle_budget(4.0) < near.num_triangles <= M.build(spec).num_triangles


def _write_models(folder: Path) -> dict[str, int]:
    """Valid OBJ, PLY and a two-part GLB scene; returns their triangle counts."""
    ring = trimesh.creation.annulus(r_min=0.5, r_max=1.0, height=0.5) \
        if hasattr(trimesh.creation, "annulus") else trimesh.creation.box()
    ring.apply_scale(3.0)
    ring.apply_translation((5.0, 2.0, -1.0))
    ring.export(folder / "ring.obj")
    ring.export(folder / "ring.ply")
    scene = trimesh.Scene()
    scene.add_geometry(trimesh.creation.box(), transform=trimesh.transformations.translation_matrix((3, 0, 0)))
    scene.add_geometry(trimesh.creation.icosphere(2))
    (folder / "sub").mkdir()
    scene.export(folder / "sub" / "pair.glb")
    return {"ring.obj": len(ring.faces), "ring.ply": len(ring.faces), "sub/pair.glb": 12 + 320}


def _write_broken(folder: Path) -> list[Path]:
    bad = [folder / "garbage.obj", folder / "garbage.ply", folder / "truncated.glb", folder / "points.obj"]
    bad[0].write_text("this is not an obj\nv 1 2\nf 9 9 9\n")
    bad[1].write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\n\x00\xff\xfe garbage")
    bad[2].write_bytes(b"glTF\x02\x00\x00\x00junk")
    bad[3].write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")          # vertices but no faces
    return bad


def test_user_models_are_loaded_and_normalised(tmp_path):
    counts = _write_models(tmp_path)
    (tmp_path / "readme.txt").write_text("not a model")
    found = M.scan_model_folder(tmp_path)
    assert found == sorted(str(tmp_path / k) for k in counts)
    for rel, n in counts.items():
        m = M.build(MeshSpec("file", {"path": str(tmp_path / rel)}))
        assert m.num_triangles == n                           # scene parts concatenated
        assert_valid(m, closed=True)
        assert abs(float(np.ptp(m.bounds, axis=0).max()) / 2 - 1.0) < 1e-5
        np.testing.assert_allclose(m.bounds.sum(axis=0) / 2, 0.0, atol=1e-5)
    zup = M.build(MeshSpec("file", {"path": str(tmp_path / "ring.obj"), "up": "z"}))
    yup = M.build(MeshSpec("file", {"path": str(tmp_path / "ring.obj")}))
    np.testing.assert_allclose(zup.bounds[:, 1], yup.bounds[:, 2], atol=1e-5)      # old z is the new y
    small = M.build(MeshSpec("file", {"path": str(tmp_path / "sub" / "pair.glb")}, triangle_budget=100))
    assert small.num_triangles <= 100


def test_broken_user_models_are_skipped_with_a_warning_and_fail_build(tmp_path):
    counts = _write_models(tmp_path)
    bad = _write_broken(tmp_path)
    with pytest.warns(M.BrokenModelWarning) as rec:
        found = M.scan_model_folder(tmp_path)
    assert found == sorted(str(tmp_path / k) for k in counts)
    messages = [str(w.message) for w in rec]
    for p in bad:
        assert sum(str(p) in msg for msg in messages) == 1, (p, messages)
        with pytest.raises(MeshError, match=p.name):
            M.build(MeshSpec("file", {"path": str(p)}))
    with pytest.raises(MeshError, match="missing.obj"):
        M.build(MeshSpec("file", {"path": str(tmp_path / "missing.obj")}))
    with pytest.raises(MeshError, match="nowhere"):
        M.scan_model_folder(tmp_path / "nowhere")


@pytest.mark.parametrize("spec, field", [
    (MeshSpec("sphere", {"subdivisions": 9}), "subdivisions"),
    (MeshSpec("cylinder", {"radius": -1.0}), "radius"),
    (MeshSpec("torus", {"major_radius": 0.5, "minor_radius": 0.7}), "minor_radius"),
    (MeshSpec("box", {"extents": [1, 0, 1]}), "extents"),
    (MeshSpec("boolean", {"op": "xor"}, children=(MeshSpec("box"), MeshSpec("sphere"))), "op"),
    (MeshSpec("boolean", children=(MeshSpec("plane"), MeshSpec("sphere"))), "closed"),
    (MeshSpec("revolve", {"profile": [[-1, 0], [1, 1]]}), "profile"),
    (MeshSpec("file", {}), "path"),
])
def test_bad_params_name_the_field(spec, field):
    with pytest.raises(SpecError, match=field):
        M.build(spec)


def test_empty_boolean_is_a_mesh_error():
    spec = MeshSpec("boolean", {"op": "intersection", "b_scale": 0.2, "b_offset": [5.0, 0.0, 0.0]},
                    children=(MeshSpec("box"), MeshSpec("sphere")))
    with pytest.raises(MeshError, match="empty"):
        M.build(spec)


def test_first_pymeshlab_import_from_a_thread_is_refused_not_heap_corruption():
    import subprocess
    import sys
    code = ("import threading\nfrom scene_gen import meshes\nfrom scene_gen.errors import MeshError\n"
            "from scene_gen.spec import MeshSpec\nout = []\n"
            "def work():\n    try:\n        meshes.build(MeshSpec('sphere', triangle_budget=50))\n        out.append('built')\n"
            "    except MeshError as e:\n        out.append(str(e))\n"
            "t = threading.Thread(target=work); t.start(); t.join(); print(out[0])\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert "main thread" in r.stdout and "pipeline.worker_init" in r.stdout, (r.stdout, r.stderr)
    assert "malloc" not in r.stderr
    # with the preload imported first, the same work in a thread succeeds cleanly
    r = subprocess.run([sys.executable, "-c", "import pipeline.worker_init\n" + code], capture_output=True, text=True,
                       timeout=120)
    assert r.stdout.strip() == "built" and "malloc" not in r.stderr, (r.stdout, r.stderr)
