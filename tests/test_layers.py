"""The shape of the package: imports go one way, nothing imports in a circle, no class or function grows too big."""

from __future__ import annotations

import ast
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "spiral"

LAYERS: list[set[str]] = [
    {"spiral"},  # spiral/__init__.py: the version string, and the CPU arithmetic set before torch computes
    {"core"},
    {"config"},
    {"sim"},
    {"env"},
    {"train", "baselines"},
    {"selfplay", "adapters"},
    {"eval"},
    {"pipeline"},
    {"cli"},
]
"""Layers from the bottom up. A module imports its own package and packages of lower layers only, never a package
of its own layer (``train`` and ``baselines`` know nothing of each other) or of a higher one, inside functions
included. ``core`` holds the contracts every layer shares and sits below ``config``: config's specs read the race
formats from ``core.scenario``. The gymnasium adapter (``adapters``) sits above ``baselines`` because it offers the
SE-IBR planner as an opponent; ``spiral.env`` registers its gymnasium id by an entry-point string, which gymnasium
imports only when an env is made. The one import that goes up: ``spiral/__init__.py`` applies
``spiral.core.numerics`` (which imports nothing of spiral's), because torch reads the CPU arithmetic's settings when
it first computes, and importing spiral is the first thing a user of it does."""
ROOT_SETS_NUMERICS = ("spiral", "spiral.core.numerics")
"""The package root's import of the CPU arithmetic: importer and imported module."""
MAX_CLASS_LINES = 200
MAX_FUNCTION_LINES = 60


@dataclass(frozen=True)
class Import:
    """One import statement of a spiral module that names another spiral module."""

    source: str
    target: str
    line: int


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def _package(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def _rank(package: str) -> int:
    return next(i for i, layer in enumerate(LAYERS) if package in layer)


def _resolve(name: str, modules: dict[str, Path]) -> str | None:
    """The spiral module an imported dotted name refers to (a module, else the package or module defining it)."""
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def _imports(modules: dict[str, Path]) -> list[Import]:
    """Every import of a spiral module by a spiral module, at any depth (functions, ``TYPE_CHECKING`` blocks)."""
    found = []
    for source, path in modules.items():
        is_package = path.name == "__init__.py"
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            names: list[str] = []
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = source.split(".")[: len(source.split(".")) - node.level + is_package]
                    base = ".".join([*anchor, *([base] if base else [])])
                names = [f"{base}.{alias.name}" for alias in node.names]
            for name in names:
                target = _resolve(name, modules) if name.split(".")[0] == "spiral" else None
                if target is not None and target != source:
                    found.append(Import(source, target, node.lineno))
    return found


def _cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one node (Tarjan), each as a sorted list."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(edges.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return out


@pytest.fixture(scope="module")
def imports() -> list[Import]:
    """Every import between spiral modules."""
    return _imports(_modules())


def test_every_package_has_a_layer():
    """Place every package of spiral in exactly one layer."""
    packages = {_package(m) for m in _modules()}
    layered = [p for layer in LAYERS for p in layer]
    assert sorted(layered) == sorted(set(layered))
    assert packages == set(layered)


def test_imports_go_down_the_layers(imports):
    """Import only from the own package or a lower layer, inside functions too."""
    bad = [f"{i.source}:{i.line} imports {i.target} ({_package(i.source)} may not import {_package(i.target)})"
           for i in imports
           if _package(i.source) != _package(i.target) and _rank(_package(i.target)) >= _rank(_package(i.source))
           and (i.source, i.target) != ROOT_SETS_NUMERICS]
    assert not bad, "\n".join(bad)


def test_no_package_imports_in_a_circle(imports):
    """Keep the graph of packages free of cycles."""
    edges: dict[str, set[str]] = {}
    for i in imports:
        if _package(i.source) != _package(i.target):
            edges.setdefault(_package(i.source), set()).add(_package(i.target))
    cycles = _cycles(edges)
    assert not cycles, "packages importing each other: " + "; ".join(" <-> ".join(c) for c in cycles)


def test_no_module_imports_in_a_circle(imports):
    """Keep the graph of modules free of cycles, imports for type checking and inside functions included."""
    edges: dict[str, set[str]] = {}
    for i in imports:
        edges.setdefault(i.source, set()).add(i.target)
    cycles = _cycles(edges)
    assert not cycles, "modules importing each other: " + "; ".join(" <-> ".join(c) for c in cycles)


def test_the_bottom_layers_load_without_torch():
    """Import the specs, the scenario table and the simulator without loading torch, rsl-rl or tensordict."""
    code = ("import sys, spiral.config, spiral.core.scenario, spiral.sim; "
            "print(sorted(m for m in ('torch', 'rsl_rl', 'tensordict') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout.strip() == "[]"


def _is_warp_kernel(node: ast.AST) -> bool:
    for deco in getattr(node, "decorator_list", []):
        target = deco.func if isinstance(deco, ast.Call) else deco
        if isinstance(target, ast.Attribute) and target.attr in ("kernel", "func"):
            return True
    return False


def _oversized() -> list[str]:
    """``path:line kind name (lines)`` of every class over 200 lines and function over 60, decorators included."""
    found = []
    for module, path in _modules().items():
        stack: list[tuple[ast.AST, str]] = [(ast.parse(path.read_text(), str(path)), "")]
        while stack:
            node, prefix = stack.pop()
            for child in ast.iter_child_nodes(node):
                if not isinstance(child, (ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
                    stack.append((child, prefix))
                    continue
                first = min([child.lineno, *(d.lineno for d in child.decorator_list)])
                lines = child.end_lineno - first + 1
                is_class = isinstance(child, ast.ClassDef)
                limit = MAX_CLASS_LINES if is_class else MAX_FUNCTION_LINES
                if lines > limit and not _is_warp_kernel(child):
                    found.append(f"{module}:{child.lineno} {'class' if is_class else 'function'} "
                                 f"{prefix}{child.name} ({lines} lines > {limit})")
                stack.append((child, f"{prefix}{child.name}."))
    return sorted(found)


def test_no_class_over_200_lines_and_no_function_over_60():
    """Keep every class to 200 lines and every function to 60 (Warp kernels and funcs excepted)."""
    oversized = _oversized()
    assert not oversized, "\n".join(oversized)


def test_the_import_walk_sees_imports_inside_functions_and_type_checking_blocks(tmp_path):
    """Find an import inside a function and one under ``if TYPE_CHECKING``, and report a two-module cycle."""
    source = ("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from spiral.eval import x\n"
              "def f():\n    from spiral.pipeline.runner import PipelineRunner\n")
    tree = ast.parse(source)
    seen = [n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    assert seen == ["typing", "spiral.eval", "spiral.pipeline.runner"]
    assert _cycles({"a": {"b"}, "b": {"a", "c"}, "c": set()}) == [["a", "b"]]
