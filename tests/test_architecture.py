"""The package's shape: no import cycles, imports run one way between sub-packages, and
importing a module does nothing but define names (no registration, no config change)."""

import ast
import pathlib
import subprocess
import sys

import pytest

PKG = pathlib.Path(__file__).resolve().parents[1] / "eyefem"

LAYERS = {  # a sub-package may import only from those below it (lower number)
    "fem": 0, "solve": 1, "io": 2, "verify": 1, "eye": 3, "problems": 3, "catalog": 4,
    "run": 4, "api": 5, "study": 6, "cli": 7,
}
"""eyefem/<group>: the layer of each group; a module imports only from its own group or
a lower layer (fem <- solve <- io <- eye, problems <- catalog, run <- api <- study <- cli)."""


def _modules():
    out = {}
    for path in PKG.rglob("*.py"):
        rel = path.relative_to(PKG.parent).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _imports(path):
    """Every eyefem module a file imports, at module level or inside functions."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module.startswith("eyefem"):
                found.add(node.module)
                found.update(f"{node.module}.{a.name}" for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level:
            raise AssertionError(f"{path}: relative import; use absolute eyefem.* imports")
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.startswith("eyefem"))
    return found


def _graph():
    mods = _modules()
    return {m: {i for i in _imports(p) if i in mods and i != m} for m, p in mods.items()}


def _group(mod):
    parts = mod.split(".")
    return parts[1] if len(parts) > 1 else None


def test_no_module_imports_itself_back_through_a_cycle():
    graph = _graph()
    state, cycles = {}, []

    def visit(m, stack):
        state[m] = 1
        for n in sorted(graph[m]):
            if _group(n) is None:  # the package's __init__ re-exports lazily
                continue
            if state.get(n) == 1:
                cycles.append(stack[stack.index(n):] + [n])
            elif n not in state:
                visit(n, stack + [n])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    assert not cycles, "import cycles: " + "; ".join(" -> ".join(c) for c in cycles)


def test_sub_packages_import_only_downwards():
    bad = []
    for m, deps in _graph().items():
        g = _group(m)
        if g is None:
            continue
        for d in deps:
            h = _group(d)
            if h is None or h == g:
                continue
            if LAYERS[h] >= LAYERS[g]:
                bad.append(f"{m} -> {d}")
    assert not bad, "imports against the layering (" + ", ".join(
        f"{k}={v}" for k, v in LAYERS.items()) + "): " + "; ".join(sorted(bad))


def test_no_private_name_is_imported_across_sub_packages():
    bad = []
    mods = _modules()
    for m, path in mods.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("eyefem"):
                if _group(node.module) == _group(m):
                    continue
                bad += [f"{m}: {node.module}.{a.name}" for a in node.names
                        if a.name.startswith("_") and a.name != "__version__"]
    assert not bad, "private names imported across sub-packages: " + "; ".join(bad)


def test_every_group_is_known():
    groups = {_group(m) for m in _modules()} - {None}
    assert groups <= set(LAYERS), f"sub-packages without a layer: {groups - set(LAYERS)}"


@pytest.mark.parametrize("group", sorted(k for k in LAYERS if k not in ("api", "catalog")))
def test_importing_a_sub_package_has_no_side_effects(group):
    """Import every module of a group in a fresh interpreter: x64 stays off, nothing is
    logged or printed, no tangent check is registered anywhere."""
    mods = sorted(m for m in _modules() if _group(m) == group)
    code = ("import importlib, jax, sys\n"
            f"for m in {mods!r}: importlib.import_module(m)\n"
            "assert not jax.config.jax_enable_x64, 'x64 switched on at import'\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout == "", f"printed at import: {res.stdout[:500]}"
