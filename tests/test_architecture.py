"""The import graph reads in the data's order (docs/architecture.md): ``core`` at the ground, imported by
every stage and importing none; ``scene_gen`` and ``stores`` on it; ``pipeline`` (renders scenes into
stores) and ``training`` (reads stores) side by side above those, neither importing the other and training
never reaching into the scene generator; ``studies`` (what both renders and trains: the scaling study) on
top of both, imported by neither; and no cycle between modules,
imports inside functions and modules named as strings (``importlib.import_module``) included."""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("core", "scene_gen", "stores", "pipeline", "training", "studies")
ALLOWED = {                                 # package -> the packages it may import
    "core": set(),
    "scene_gen": {"core"},
    "stores": {"core"},
    "pipeline": {"core", "scene_gen", "stores"},
    "training": {"core", "stores"},         # a sibling of pipeline: neither imports the other
    "studies": {"core", "stores", "pipeline", "training"},   # what both renders and trains
}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> set[str]:
    """Every project module ``path`` imports, anywhere in the file (relative imports resolved)."""
    mod = _module_name(path)
    package = mod if path.name == "__init__.py" else mod.rsplit(".", 1)[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        names = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[:len(package.split(".")) - node.level + 1]
                base = ".".join(up + ([base] if base else []))
            names = [base] + [f"{base}.{a.name}" for a in node.names]
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value.isidentifier() is False \
                and all(part.isidentifier() for part in node.value.split(".")):
            names = [node.value]            # a module named as a string (importlib.import_module, a table of them)
        out |= {n for n in names if n.split(".")[0] in PACKAGES}
    return out


def _graph() -> dict[str, set[str]]:
    files = [p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")]
    mods = {_module_name(p): p for p in files}
    graph = {}
    for m, p in mods.items():
        deps = set()
        for name in _imports(p):        # ``from a.b import c``: the module a.b.c where it is one, else a.b
            while name and name not in mods:
                name = name.rpartition(".")[0]
            if name and name != m:
                deps.add(name)
        graph[m] = deps
    return graph


def test_packages_import_only_what_sits_below_them():
    wrong = sorted(f"{m} -> {d}" for m, deps in _graph().items() for d in deps
                   if d.split(".")[0] != m.split(".")[0] and d.split(".")[0] not in ALLOWED[m.split(".")[0]])
    assert not wrong, "imports against the floor plan:\n" + "\n".join(wrong)


def test_no_module_imports_itself_back():
    graph = _graph()
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
