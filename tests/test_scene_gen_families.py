"""Scene families as plugins (scene_gen.families) and the shape of scene_gen's imports.

A family is one file in ``scene_gen/families/``: its name, seed index, layout function and settings
reach the scene kinds, SceneGenConfig, the seeds and the command line from
there. scene_gen's modules import each other at module level without cycles, and never import the
packages built on it (stores, pipeline, training).
"""
from __future__ import annotations

import ast
import dataclasses
import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from scene_gen import families
from scene_gen.config import ConfigError, SceneGenConfig
from scene_gen.families import Setting, family_names, get_family, register_family
from scene_gen.sampling import sample_scene
from scene_gen.spec import SpecError

ROOT = Path(__file__).resolve().parent.parent
PKG = ROOT / "scene_gen"


def _run(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)


# ---------------------------------------------------------------------------------------------
# the registry

def test_families_are_registered_in_seed_order():
    import scene_gen.families.indoor as indoor
    import scene_gen.families.outdoor as outdoor
    from scene_gen import spec
    assert family_names() == ("indoor", "outdoor") and family_names() is family_names()
    # a spec names its family; it is checked as a name, not against the registry (it renders anywhere)
    with pytest.raises(SpecError, match=r"scene.kind must be a scene family's name \(a lower-case identifier\), got 'Under Water'"):
        dataclasses.replace(sample_scene(3, "indoor"), kind="Under Water")
    assert dataclasses.replace(sample_scene(3, "indoor"), kind="underwater").kind == "underwater"
    assert get_family("indoor").layout is indoor.layout_indoor and get_family("indoor").seed_index == 0
    assert get_family("outdoor").layout is outdoor.layout_outdoor and get_family("outdoor").seed_index == 1
    assert list(families.family_settings()) == ["indoor_objects", "p_lamps", "p_panels_in_view", "outdoor_objects",
                                                "p_sunsky", "p_sun_in_view"]
    with pytest.raises(ConfigError, match=r"scene kind must be one of \('indoor', 'outdoor'\), got 'underwater'"):
        get_family("underwater")


def test_a_scene_is_drawn_from_its_familys_seed_index():
    """SeedSequence([seed, seed_index]) feeds the layout's stream: the spec of a seed follows its family's index."""
    calls = []

    def spy(rng, r_cam, cfg, fov, res, user_models):
        calls.append(float(rng.uniform()))
        raise RuntimeError("stop")

    fam = get_family("outdoor")
    families.FAMILIES["outdoor"] = families.Family("outdoor", fam.seed_index, spy, fam.settings)
    try:
        with pytest.raises(RuntimeError, match="stop"):
            sample_scene(3, "outdoor")
    finally:
        families.FAMILIES["outdoor"] = fam
    ss = np.random.SeedSequence([3, 1])
    assert calls == [float(np.random.default_rng(ss.spawn(6)[1]).uniform())]


def test_registration_refuses_clashes():
    def layout(*a):
        return None
    with pytest.raises(ConfigError, match="already registered by scene_gen.families.outdoor"):
        register_family("outdoor", seed_index=7)(layout)
    with pytest.raises(ConfigError, match="seed_index 1 is already the scene family 'outdoor'"):
        register_family("underwater", seed_index=1)(layout)
    with pytest.raises(ConfigError, match="setting 'p_sunsky' is already the scene family 'outdoor'"):
        register_family("underwater", seed_index=7, settings={"p_sunsky": Setting(0.5, "probability")})(layout)
    with pytest.raises(ConfigError, match="lower-case identifier"):
        register_family("Under Water", seed_index=7)(layout)
    with pytest.raises(ConfigError, match="seed_index must be an integer >= 0"):
        register_family("underwater", seed_index=-1)(layout)
    with pytest.raises(ConfigError, match="after scene_gen.config was built"):
        register_family("underwater", seed_index=7, settings={"fish": Setting(3, "int", 0, 9)})(layout)
    with pytest.raises(ConfigError, match="needs integers lo <= hi"):
        Setting(3, "int")
    assert family_names() == ("indoor", "outdoor")


def test_family_settings_are_config_fields():
    cfg = SceneGenConfig()
    assert (cfg.indoor_objects, cfg.outdoor_objects, cfg.p_sunsky) == (50, 75, 0.5)
    d = SceneGenConfig(outdoor_objects=6, p_sunsky=1.0).to_dict()
    assert d["outdoor_objects"] == 6 and d["p_sunsky"] == 1.0 and SceneGenConfig.from_dict(d).outdoor_objects == 6
    with pytest.raises(ConfigError, match=r"scene_gen.p_sunsky must be a probability in \[0, 1\], got 2"):
        SceneGenConfig(p_sunsky=2)
    with pytest.raises(ConfigError, match=r"scene_gen.indoor_objects must be an integer in \[0, 10000\], got -3"):
        SceneGenConfig.from_dict({"indoor_objects": -3})
    assert "indoor_objects" in SceneGenConfig.__doc__ and "p_sunsky" in SceneGenConfig.__doc__


NEW_FAMILY = '''
"""A test family: one sphere on a floor."""
import numpy as np

from scene_gen.families import Setting, register_family
from scene_gen.layout import Layout, Placed
from scene_gen.materials import diffuse
from scene_gen.spec import LightSpec, MeshSpec, Transform


@register_family("lab", seed_index=7, settings={"lab_spheres": Setting(1, "int", 0, 3, "spheres")})
def layout_lab(rng, r_cam, cfg, fov, res, user_models):
    objs = [Placed("floor", MeshSpec("plane", {"resolution": 1}), diffuse((0.5, 0.5, 0.5)), Transform(scale=(9, 9, 9)),
                   radius=20.0, keep=True, movable=False, budget=False)]
    for i in range(cfg.lab_spheres):
        objs.append(Placed(f"obj_{i}", MeshSpec("sphere"), diffuse((0.8, 0.2, 0.2)),
                           Transform((float(rng.uniform(-1, 1)), 0.5, 0.0), scale=(0.5, 0.5, 0.5)), radius=0.5))
    return Layout(objs, [LightSpec("constant", {"radiance": [1.0, 1.0, 1.0]})], np.array([0.0, 1.0, 4.0]),
                  np.array([0.0, 0.5, 0.0]), camera_step=0.1)
'''


def test_a_family_is_one_file(tmp_path):
    """A module dropped into the families' folder is a scene kind everywhere: kinds, SceneSpec, config,
    seeds, sample_scene and the command line (the folder is extended here instead of written to)."""
    (tmp_path / "lab.py").write_text(NEW_FAMILY)
    code = textwrap.dedent(f"""
        import json
        import scene_gen.families as F
        F.__path__.append({str(tmp_path)!r})
        from scene_gen import spec
        from scene_gen.commands import build_parser
        from scene_gen.config import SceneGenConfig
        from scene_gen.sampling import sample_scene
        s = sample_scene(4, "lab", config=SceneGenConfig(lab_spheres=2))
        assert spec.SceneSpec.from_json(s.to_json()) == s
        assert sample_scene(4, "lab", config=SceneGenConfig(lab_spheres=2)) == s
        args = build_parser().parse_args(["spec", "--kind", "lab"])
        print(json.dumps({{"kinds": F.family_names(), "objects": [o.name for o in s.objects],
                          "default": SceneGenConfig().lab_spheres, "seed_index": F.get_family("lab").seed_index,
                          "kind": args.kind}}))
    """)
    r = _run(code)
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out == {"kinds": ["indoor", "outdoor", "lab"], "objects": ["floor", "obj_0", "obj_1"], "default": 1,
                   "seed_index": 7, "kind": "lab"}


# ---------------------------------------------------------------------------------------------
# imports

def _modules() -> dict[str, Path]:
    out = {}
    for p in sorted(PKG.rglob("*.py")):
        parts = p.relative_to(ROOT).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = p
    return out


def _imports(tree: ast.AST, package: str) -> list[tuple[str, int, bool]]:
    """(imported module, line, at module level) of every import statement; ``from scene_gen import x``
    names the module ``scene_gen.x`` when it is one."""
    mods = _modules()
    out = []

    def walk(node, top):
        for n in ast.iter_child_nodes(node):
            names = []
            if isinstance(n, ast.Import):
                names = [a.name for a in n.names]
            elif isinstance(n, ast.ImportFrom):
                parts = package.split(".")
                base = n.module if n.level == 0 else ".".join(parts[:len(parts) - n.level + 1] + [n.module or ""])
                names = [f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base for a in n.names]
            out.extend((m, n.lineno, top) for m in names)
            walk(n, top and not isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)))

    walk(tree, True)
    return out


def test_scene_gen_imports_its_modules_at_module_level_without_cycles():
    mods = _modules()
    graph, late = {}, []
    for name, path in mods.items():
        package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
        deps = set()
        for m, line, top in _imports(ast.parse(path.read_text()), package):
            if m.split(".")[0] in ("stores", "pipeline", "training"):
                late.append(f"{name}:{line} imports {m}, a package built on scene_gen")
            if m in mods and m != name:
                if top:
                    deps.add(m)
                else:
                    late.append(f"{name}:{line} imports {m} inside a function")
        graph[name] = deps
    assert not late, sorted(set(late))
    state: dict[str, int] = {}

    def visit(n, path):
        state[n] = 1
        for d in sorted(graph[n]):
            if state.get(d) == 1:
                raise AssertionError(f"import cycle: {' -> '.join(path + [n, d])}")
            if d not in state:
                visit(d, path + [n])
        state[n] = 2

    for n in sorted(graph):
        if n not in state:
            visit(n, [])


def test_every_module_imports_first():
    """Each module imported first in a fresh interpreter state (no import order hides a cycle)."""
    names = sorted(m for m in _modules() if not m.endswith("__main__"))
    code = textwrap.dedent(f"""
        import importlib, sys
        bad = []
        for name in {names!r}:
            for m in [m for m in sys.modules if m == "scene_gen" or m.startswith("scene_gen.")]:
                del sys.modules[m]
            try:
                importlib.import_module(name)
            except Exception as e:
                bad.append(f"{{name}}: {{type(e).__name__}}: {{e}}")
        print(bad)
    """)
    r = _run(code)
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.strip().splitlines()[-1] == "[]"
