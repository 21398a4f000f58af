"""The import graph reads in the data's order (docs/architecture.md): ``core`` at the ground, imported by
every stage and importing none; ``scene_gen`` and ``stores`` on it; ``pipeline`` (renders scenes into
stores) and ``training`` (reads stores) side by side above those, neither importing the other and training
never reaching into the scene generator; ``studies`` (what both renders and trains: the scaling study,
bench-scale) on top of all of them, imported by none; and no cycle between modules,
imports inside functions and modules named as strings (``importlib.import_module``) included, and those
built from f-strings: ``f"{__name__}.{m.name}"`` (a registry that imports every module of its folder)
stands for every module of the folder. Two more ways one module reaches another count as imports: an
entry point of pyproject.toml (the module holding the group's name, which loads the group, imports every
module the group's entry points name) and a program it starts (``[sys.executable, "-m", "pipeline", ...]``:
the module depends on ``pipeline.__main__``)."""
from __future__ import annotations

import ast
import builtins
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("core", "scene_gen", "stores", "pipeline", "training", "studies")
ALLOWED = {                                 # package -> the packages it may import
    "core": set(),
    "scene_gen": {"core"},
    "stores": {"core"},
    "pipeline": {"core", "scene_gen", "stores"},
    "training": {"core", "stores"},         # a sibling of pipeline: neither imports the other
    "studies": {"core", "scene_gen", "stores", "pipeline", "training"},   # what both renders and trains: all below
}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _pattern(node: ast.JoinedStr, mod: str, package: str) -> str | None:
    """A module name built from an f-string as a pattern (``*``: any one name), ``__name__`` and
    ``__package__`` filled in; None when it names no project package."""
    parts = []
    for v in node.values:
        if isinstance(v, ast.Constant):
            parts.append(str(v.value))
        elif isinstance(v.value, ast.Name) and v.value.id in ("__name__", "__package__"):
            parts.append(mod if v.value.id == "__name__" else package)
        else:
            parts.append("*")
    name = "".join(parts)
    ok = all(p == "*" or p.isidentifier() for p in name.split("."))
    return name if ok and "*" in name and name.split(".")[0] in PACKAGES else None


def _entry_points() -> dict[str, set[str]]:
    """pyproject.toml's entry-point groups: group name -> the project modules its entry points name."""
    import tomllib
    groups = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"].get("entry-points", {})
    return {g: {v.partition(":")[0].strip() for v in eps.values()} for g, eps in groups.items()}


def _programs(tree: ast.AST) -> set[str]:
    """The modules a file starts as new programs, ``python -m NAME`` (as ``NAME.__main__``): the item after
    ``"-m"`` in a list, tuple or call's arguments, a string or a parameter of the function it sits in (as
    ``[sys.executable, "-m", *args]``: then every call of that function in the file names the module)."""
    out, params = set(), []
    for fn in [n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))] + [None]:
        positional = [a.arg for a in fn.args.posonlyargs + fn.args.args] if fn else []
        star = fn.args.vararg.arg if fn and fn.args.vararg else None
        for node in ast.walk(fn or tree):
            items = node.elts if isinstance(node, (ast.List, ast.Tuple)) else \
                node.args if isinstance(node, ast.Call) else []
            for i, item in enumerate(items[:-1]):
                if not (isinstance(item, ast.Constant) and item.value == "-m"):
                    continue
                nxt = items[i + 1]
                name = getattr(nxt.value if isinstance(nxt, ast.Starred) else nxt, "id", None)
                if isinstance(nxt, ast.Constant) and isinstance(nxt.value, str):
                    out.add(nxt.value)
                elif fn and name == star:
                    params.append((fn.name, len(positional)))
                elif fn and name in positional:
                    params.append((fn.name, positional.index(name)))
    for node in ast.walk(tree):                     # the calls of a function that starts ``python -m ARG``
        called = getattr(node.func, "id", getattr(node.func, "attr", None)) if isinstance(node, ast.Call) else None
        for fname, pos in params:
            if called == fname and len(node.args) > pos and isinstance(node.args[pos], ast.Constant):
                out.add(str(node.args[pos].value))
    return {f"{n}.__main__" for n in out}


def _imports(path: Path, programs: bool = True) -> set[str]:
    """Every project module ``path`` imports, anywhere in the file (relative imports resolved), loads
    through an entry-point group it names (:func:`_entry_points`) or starts as a program
    (:func:`_programs`); a name holding ``*`` is a pattern (:func:`_pattern`)."""
    mod = _module_name(path)
    package = mod if path.name == "__init__.py" else mod.rsplit(".", 1)[0]
    tree, groups = ast.parse(path.read_text()), _entry_points()
    out = {n for n in _programs(tree) if n.split(".")[0] in PACKAGES} if programs else set()
    for node in ast.walk(tree):
        names = []
        if isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.JoinedStr) and \
                getattr(node.func, "attr", getattr(node.func, "id", "")) in ("import_module", "__import__"):
            names = [n for n in [_pattern(node.args[0], mod, package)] if n]
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[:len(package.split(".")) - node.level + 1]
                base = ".".join(up + ([base] if base else []))
            names = [base] + [f"{base}.{a.name}" for a in node.names]
        elif isinstance(node, ast.Constant) and node.value in groups:
            names = sorted(groups[node.value])      # an entry-point group: loading it imports what it names
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value.isidentifier() is False \
                and all(part.isidentifier() for part in node.value.split(".")):
            names = [node.value]            # a module named as a string (importlib.import_module, a table of them)
        out |= {n for n in names if n.split(".")[0] in PACKAGES}
    return out


def _graph(plugins: set | None = None, programs: bool = True) -> dict[str, set[str]]:
    """Module -> the project modules it imports (and, with ``programs``, starts). ``plugins`` (when given)
    collects ``(plugin, registry)``: a module that ``registry`` imports through a pattern (it finds the
    modules of its folder)."""
    files = [p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")]
    mods = {_module_name(p): p for p in files}
    graph = {}
    for m, p in mods.items():
        deps = set()
        for name in _imports(p, programs):        # ``from a.b import c``: the module a.b.c where it is one, else a.b
            if "*" in name:
                rx = re.compile(re.escape(name).replace(r"\*", r"[^.]+") + "$")
                found = {n for n in mods if rx.match(n) and n != m}
                deps |= found
                if plugins is not None:
                    plugins |= {(n, m) for n in found}
                continue
            while name and name not in mods:
                name = name.rpartition(".")[0]
            if name and name != m:
                deps.add(name)
        graph[m] = deps
    return graph


# The edges against the floor plan it keeps on purpose, each with why.
INTENDED = {
    # The export formats are plug-ins found by name (the entry-point group stores.export.PLUGINS): stores
    # lists them without importing anything (test_registries_import_their_plugins_only_when_asked) and
    # loads pipeline's noisebase writer only when that format is asked for, as a registry loads its
    # plug-ins. Noisebase re-traces the samples, so its writer needs the renderer above the stores, and
    # `python -m stores export` and `python -m pipeline export` offer the same formats.
    ("stores.export", "pipeline.noisebase"),
}


def _against_the_plan() -> set[tuple[str, str]]:
    return {(m, d) for m, deps in _graph().items() for d in deps
            if d.split(".")[0] != m.split(".")[0] and d.split(".")[0] not in ALLOWED[m.split(".")[0]]}


def test_packages_import_only_what_sits_below_them():
    wrong = sorted(f"{m} -> {d}" for m, d in _against_the_plan() - INTENDED)
    assert not wrong, "imports against the floor plan:\n" + "\n".join(wrong)
    stale = sorted(f"{m} -> {d}" for m, d in INTENDED - _against_the_plan())
    assert not stale, "INTENDED lists edges that are gone:\n" + "\n".join(stale)


def test_entry_points_and_started_programs_count_as_imports():
    """The noisebase export, an entry point (pyproject.toml) that stores.export loads by its group's name,
    is an edge of stores.export; a module that runs ``python -m PACKAGE`` depends on ``PACKAGE.__main__``,
    whether it names the package in the list or passes it to a helper that starts ``[..., "-m", *args]``."""
    assert _entry_points()["denoise_datagen.export_formats"] == {"pipeline.noisebase"}
    assert "pipeline.noisebase" in _graph()["stores.export"]
    assert "pipeline.__main__" in _graph()["pipeline.bench_render"]
    tree = ast.parse('import subprocess, sys\n'
                     'def prog(*args):\n    return subprocess.run([sys.executable, "-m", *args])\n'
                     'def one(pkg, x):\n    subprocess.run([sys.executable, "-m", pkg, x])\n'
                     'prog("scene_gen", "spec")\none("studies", "scaling")\n'
                     'subprocess.Popen(("python", "-m", "training", "train"))\n')
    assert _programs(tree) == {"scene_gen.__main__", "studies.__main__", "training.__main__"}


def test_no_module_imports_itself_back():
    """No cycle, but a plugin's import of the registry that finds it (the registry's decorator): the
    registry imports its plugins only when first asked, and nothing else may lead back through them."""
    plugins: set = set()
    graph = _graph(plugins, programs=False)     # a program started is a new process: it imports nothing here
    for plugin, registry in plugins:
        graph[plugin].discard(registry)
    index, low, stack, on, cycles = {}, {}, [], set(), []

    def visit(v):                                       # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))
    for v in sorted(graph):
        if v not in index:
            visit(v)
    assert not cycles, f"import cycles: {cycles}"


def test_imports_built_from_f_strings_are_followed():
    """A registry that imports its folder's modules by an f-string imports each of them here, and they
    are its plugins; the scene spec imports no family (it sat in a cycle through them: spec ->
    families -> indoor -> layout -> spec)."""
    plugins: set = set()
    graph = _graph(plugins)
    assert {"scene_gen.families.indoor", "scene_gen.families.outdoor"} <= graph["scene_gen.families"]
    assert {"training.models.layer", "training.models.nbg"} <= graph["training.models.registry"]
    assert ("scene_gen.families.indoor", "scene_gen.families") in plugins
    assert ("training.models.wskpn", "training.models.registry") in plugins
    assert not {d for d in graph["scene_gen.spec"] if d.startswith("scene_gen.families")}
    tree = ast.parse('import importlib\nimportlib.import_module(f"{__name__}.{m}")\nprint(f"{x}.y")')
    call, fmt = tree.body[1].value, tree.body[2].value.args[0]
    assert _pattern(call.args[0], "training.models", "training.models") == "training.models.*"
    assert _pattern(fmt, "training.models", "training.models") is None       # not a project module


def test_every_error_class_derives_from_the_projects_base():
    """docs/architecture.md: core.errors holds the base classes every stage's errors derive from. A class
    whose bases are Python's exceptions only (``class X(RuntimeError)``) escapes the exit-code mapping."""
    # warnings are no errors, and an interrupt stays one (exit 130), so those keep Python's bases
    plain = {n for n in dir(builtins) if isinstance(getattr(builtins, n), type)
             and issubclass(getattr(builtins, n), BaseException)
             and not issubclass(getattr(builtins, n), (Warning, KeyboardInterrupt))}
    stray = []
    for pkg in PACKAGES:
        for p in (ROOT / pkg).rglob("*.py"):
            for node in ast.walk(ast.parse(p.read_text())):
                if isinstance(node, ast.ClassDef) and node.bases and node.name != "ProjectError":
                    bases = [b.id if isinstance(b, ast.Name) else getattr(b, "attr", "") for b in node.bases]
                    if bases and all(b in plain for b in bases):
                        stray.append(f"{p.relative_to(ROOT)}: {node.name}({', '.join(bases)})")
    assert not stray, "error classes outside the project's hierarchy:\n" + "\n".join(stray)


def test_stores_import_no_torch():
    """docs/architecture.md: the stores' readers and writers import no torch (the store benchmark does)."""
    torch_users = sorted(str(p.relative_to(ROOT)) for p in (ROOT / "stores").rglob("*.py")
                         if any(n.split(".")[0] == "torch" for n in _all_imports(p)))
    assert torch_users == ["stores/bench.py"], torch_users


def _all_imports(path: Path) -> set[str]:
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and not node.level:
            out.add(node.module or "")
    return out


def _fresh(code: str) -> str:
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    return r.stdout.strip()


def test_registries_import_their_plugins_only_when_asked():
    """docs/architecture.md: a registry imports its plugins when first asked, not when imported (so a
    plugin's import of its registry is no cycle), and the export formats are listed without importing
    the pipeline that holds the noisebase writer (an entry point, loaded when the format is used)."""
    out = _fresh("import sys, scene_gen.families as F, training.models.registry as R\n"
                 "before = [m for m in sys.modules if m.startswith(('scene_gen.families.', 'training.models.'))"
                 " and m not in ('training.models.registry', 'training.models.common')]\n"
                 "F.family_names(); R.names()\n"
                 "print(before, 'scene_gen.families.indoor' in sys.modules, 'training.models.nbg' in sys.modules)")
    assert out == "[] True True", out
    out = _fresh("import sys\nfrom stores.export import writers\nw = writers()\n"
                 "print('noisebase' in w, sorted(m for m in sys.modules if m.split('.')[0] == 'pipeline'))")
    assert out == "True []", out


def test_no_function_is_over_60_lines():
    """Every function of the project (tests aside) reads in one screen."""
    long = []
    for pkg in PACKAGES + ("scripts",):
        for p in (ROOT / pkg).rglob("*.py"):
            for node in ast.walk(ast.parse(p.read_text())):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    n = node.end_lineno - node.lineno + 1
                    if n > 60:
                        long.append(f"{p.relative_to(ROOT)}:{node.lineno} {node.name} ({n} lines)")
    assert not long, "functions over 60 lines:\n" + "\n".join(long)


def test_pyflakes_finds_nothing_in_the_packages():
    """No unused import, undefined name or placeholder-less f-string in any package (pyflakes, which reads no
    ``noqa``: an import kept for its side effect is an ``importlib.import_module`` call)."""
    import io

    from pyflakes import api, reporter
    out, err = io.StringIO(), io.StringIO()
    found = api.checkRecursive([str(ROOT / p) for p in PACKAGES], reporter.Reporter(out, err))
    assert found == 0 and not err.getvalue(), out.getvalue() + err.getvalue()


def test_library_code_reads_no_test_hook_from_the_environment():
    """A test reaches into a run through a seam it replaces (``tests/procs.pause_at``, ``setting``), never
    through an environment variable that library code reads: no name holding ``TEST`` is read from
    ``os.environ`` / ``os.getenv`` in the packages."""
    found = []
    for pkg in PACKAGES:
        for p in (ROOT / pkg).rglob("*.py"):
            for node in ast.walk(ast.parse(p.read_text())):
                if isinstance(node, ast.Constant) and isinstance(node.value, str) \
                        and re.fullmatch(r"[A-Z0-9_]*TEST[A-Z0-9_]*", node.value):
                    found.append(f"{p.relative_to(ROOT)}:{node.lineno} {node.value}")
    assert not found, "environment variables for tests read in library code:\n" + "\n".join(found)


def test_no_module_is_over_700_lines():
    """Every module of the packages reads as one subject: none is over 700 lines."""
    long = [f"{p.relative_to(ROOT)} ({n} lines)" for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")
            if (n := len(p.read_text().splitlines())) > 700]
    assert not long, "modules over 700 lines:\n" + "\n".join(long)


def _version_operands(node: ast.Compare) -> list[str]:
    """The names in a comparison's operands that name a store's schema version (``version``,
    ``self.version``, ``version_of(root)``, ``attrs["schema_version"]``, ``attrs.get("schema_version")``;
    not TLS or package versions)."""
    out = []
    for op in [node.left, *node.comparators]:
        for n in ast.walk(op):
            if isinstance(n, ast.Name):
                out.append(n.id)
            elif isinstance(n, ast.Attribute):
                out.append(n.attr)
            elif isinstance(n, ast.Subscript) and isinstance(n.slice, ast.Constant):
                out.append(str(n.slice.value))
            elif isinstance(n, ast.Call) and n.args and isinstance(n.args[0], ast.Constant):
                out.append(str(n.args[0].value))
    return [s for s in out if s in ("version", "version_of") or "schema_version" in s.lower()]


def test_only_the_upgrade_module_branches_on_a_schema_version():
    """Older stores come through one door (``stores.upgrade``): no module of stores, pipeline or
    training outside it compares a schema version."""
    found = []
    for pkg in ("stores", "pipeline", "training"):
        for p in (ROOT / pkg).rglob("*.py"):
            if p.relative_to(ROOT).as_posix().startswith("stores/upgrade/"):
                continue
            for node in ast.walk(ast.parse(p.read_text())):
                if isinstance(node, ast.Compare) and (names := _version_operands(node)):
                    found.append(f"{p.relative_to(ROOT)}:{node.lineno} {', '.join(names)}")
    assert not found, "comparisons of a version outside stores/upgrade/:\n" + "\n".join(found)
    # the test sees such a branch: the upgrade package's own
    text = (ROOT / "stores" / "upgrade" / "__init__.py").read_text()
    assert any(isinstance(n, ast.Compare) and _version_operands(n) for n in ast.walk(ast.parse(text)))
