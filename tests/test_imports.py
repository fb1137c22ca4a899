"""The package's import graph: every module imports, and no two modules import each other.

The graph is read from the source (every ``import`` statement, also those inside functions, so a
lazy cycle counts as a cycle), with ``from a.b import c`` pointing at ``a.b.c`` when that is a
module and at ``a.b`` otherwise.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import minimdm

PKG = Path(minimdm.__file__).resolve().parent


def _module_name(path: Path) -> str:
    parts = path.relative_to(PKG.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_name(p): p for p in sorted(PKG.rglob("*.py"))}


def _imports(name: str, path: Path) -> set[str]:
    """The minimdm modules that ``name`` imports explicitly."""
    is_pkg = path.name == "__init__.py"
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against this module's package
                base = name.split(".")
                base = base[: len(base) - node.level + (1 if is_pkg else 0)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            for a in node.names:
                sub = f"{mod}.{a.name}"
                out.add(sub if sub in MODULES else mod)
    return {m for m in out if m in MODULES and m != name}


GRAPH = {name: _imports(name, path) for name, path in MODULES.items()}


def _find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}  # 1: on the stack, 2: done
    stack: list[str] = []

    def visit(u: str) -> list[str] | None:
        state[u] = 1
        stack.append(u)
        for v in sorted(graph[u]):
            if state.get(v) == 1:
                return stack[stack.index(v) :] + [v]
            if v not in state and (c := visit(v)):
                return c
        stack.pop()
        state[u] = 2
        return None

    for u in sorted(graph):
        if u not in state and (c := visit(u)):
            return c
    return None


def test_graph_sees_the_library():
    assert len(MODULES) > 30
    assert "minimdm.amdm.sampling" in GRAPH["minimdm.control.core"]
    assert "minimdm.diffusion" in GRAPH["minimdm.amdm.sampling"]


def test_cycle_finder_finds_a_cycle():
    assert _find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _find_cycle({"a": {"b"}, "b": set()}) is None


def test_no_import_cycles():
    cycle = _find_cycle(GRAPH)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_algorithms_do_not_import_the_studies():
    bad = sorted(
        (m, d)
        for m, deps in GRAPH.items()
        if not m.startswith("minimdm.studies")
        for d in deps
        if d.startswith("minimdm.studies")
    )
    assert not bad, f"library modules import study harnesses: {bad}"


def test_every_module_imports_in_a_fresh_interpreter():
    code = "import importlib, sys\nfor m in sys.argv[1:]:\n    importlib.import_module(m)\n"
    r = subprocess.run(
        [sys.executable, "-c", code, *sorted(MODULES)],
        capture_output=True,
        text=True,
        env={"VTK_DEFAULT_OPENGL_WINDOW": "vtkEGLRenderWindow", "PATH": "/usr/bin:/bin"},
    )
    assert r.returncode == 0, r.stderr[-3000:]


def _fresh(code: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=PKG.parent
    )


def test_import_minimdm_is_light_and_has_no_side_effects():
    code = (
        "import os, sys\nbefore = dict(os.environ)\nimport minimdm\n"
        "heavy = sorted(m for m in ('torch', 'gymnasium', 'stable_baselines3', 'pyvista') "
        "if m in sys.modules)\n"
        "print(heavy, dict(os.environ) == before)\n"
    )
    r = _fresh(code)
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.split() == ["[]", "True"], r.stdout


def test_every_shipped_kind_is_found_without_importing_its_module_first():
    from minimdm import checkpoint

    for kind, module in checkpoint.KIND_MODULES.items():
        assert module in MODULES, (kind, module)
    code = (
        "import sys\nfrom minimdm.checkpoint import KIND_MODULES, build_model\n"
        "for kind, module in KIND_MODULES.items():\n"
        "    try:\n        build_model({'kind': kind, 'config': {'no_such_field': 1}})\n"
        "    except ValueError as e:\n"
        "        assert 'does not build' in str(e), (kind, e)\n"
        "    assert module in sys.modules, (kind, module)\n"
        "print('ok')\n"
    )
    r = _fresh(code)
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.strip() == "ok"
