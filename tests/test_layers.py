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
included. ``core`` holds the contracts every layer shares and sits below ``config``: config's specs read the
scenarios from ``core.scenario``. The gymnasium adapter (``adapters``) sits above ``baselines`` because it offers the
SE-IBR planner as an opponent; ``spiral.env`` registers its gymnasium id by an entry-point string, which gymnasium
imports only when an env is made. The one import that goes up: ``spiral/__init__.py`` applies
``spiral.core.numerics`` (which imports nothing of spiral's), because torch reads the CPU arithmetic's settings when
it first computes, and importing spiral is the first thing a user of it does."""
ROOT_SETS_NUMERICS = ("spiral", "spiral.core.numerics")
"""The package root's import of the CPU arithmetic: importer and imported module."""
MAX_CLASS_LINES = 200
"""Longest class, decorators included."""
MAX_FUNCTION_LINES = 40
"""Longest function, from its ``def`` to its last line (docstring included)."""
MAX_PARAMETERS = 8
"""Most parameters of a function besides ``self`` or ``cls``; more means a config object is missing."""


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


def _definitions() -> list[tuple[str, str, ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef]]:
    """``(module, qualified name, node)`` of every class and function of the package, nested ones included."""
    found = []
    for module, path in _modules().items():
        stack: list[tuple[ast.AST, str]] = [(ast.parse(path.read_text(), str(path)), "")]
        while stack:
            node, prefix = stack.pop()
            for child in ast.iter_child_nodes(node):
                if not isinstance(child, (ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
                    stack.append((child, prefix))
                    continue
                found.append((module, f"{prefix}{child.name}", child))
                stack.append((child, f"{prefix}{child.name}."))
    return found


def _is_cli_command(module: str, node: ast.AST) -> bool:
    """A typer command of ``spiral.cli`` (decorated with ``<app>.command(...)``): its options are its parameters."""
    return module == "spiral.cli" and any(
        isinstance(d, ast.Call) and isinstance(d.func, ast.Attribute) and d.func.attr == "command"
        for d in getattr(node, "decorator_list", []))


def _parameters(node: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """Parameters of a function besides a leading ``self`` or ``cls`` (``*args`` and ``**kwargs`` count one each)."""
    args = node.args
    named = [*args.posonlyargs, *args.args]
    count = len(named) + len(args.kwonlyargs) + (args.vararg is not None) + (args.kwarg is not None)
    return count - (1 if named and named[0].arg in ("self", "cls") else 0)


def _oversized() -> list[str]:
    """``path:line class name (lines)`` of every class over 200 lines, decorators included."""
    found = []
    for module, name, node in _definitions():
        first = min([node.lineno, *(d.lineno for d in node.decorator_list)])
        lines = node.end_lineno - first + 1
        if isinstance(node, ast.ClassDef) and lines > MAX_CLASS_LINES:
            found.append(f"{module}:{node.lineno} class {name} ({lines} lines > {MAX_CLASS_LINES})")
    return sorted(found)


def _overgrown_functions() -> list[str]:
    """``path:line function name (what)`` of every function over 40 lines or with over 8 parameters; Warp kernels
    and funcs aside, and the CLI's typer commands may take more parameters."""
    found = []
    for module, name, node in _definitions():
        if isinstance(node, ast.ClassDef) or _is_warp_kernel(node):
            continue
        lines, params = node.end_lineno - node.lineno + 1, _parameters(node)
        if lines > MAX_FUNCTION_LINES:
            found.append(f"{module}:{node.lineno} function {name} ({lines} lines > {MAX_FUNCTION_LINES})")
        if params > MAX_PARAMETERS and not _is_cli_command(module, node):
            found.append(f"{module}:{node.lineno} function {name} ({params} parameters > {MAX_PARAMETERS})")
    return sorted(found)


def test_no_class_over_200_lines():
    """Keep every class to 200 lines, decorators included."""
    oversized = _oversized()
    assert not oversized, "\n".join(oversized)


def test_no_function_over_40_lines_or_8_parameters():
    """Keep every function to 40 lines from its ``def`` and 8 parameters besides ``self`` or ``cls`` (Warp kernels
    and funcs excepted; the CLI's typer commands take their options as parameters)."""
    overgrown = _overgrown_functions()
    assert not overgrown, "\n".join(overgrown)


def test_the_size_checks_count_lines_from_the_def_and_parameters_besides_self():
    """Count a decorated method's lines from its ``def`` and its parameters without ``self``, keyword-only and
    ``**kwargs`` included."""
    tree = ast.parse("class A:\n    @property\n    def f(self, a, /, b, *, c, **d):\n        return 1\n")
    method = tree.body[0].body[0]
    assert method.end_lineno - method.lineno + 1 == 2
    assert _parameters(method) == 4
    assert _is_cli_command("spiral.cli", ast.parse("@app.command('x')\ndef g(): pass\n").body[0])


def test_the_import_walk_sees_imports_inside_functions_and_type_checking_blocks(tmp_path):
    """Find an import inside a function and one under ``if TYPE_CHECKING``, and report a two-module cycle."""
    source = ("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from spiral.eval import x\n"
              "def f():\n    from spiral.pipeline.runner import PipelineRunner\n")
    tree = ast.parse(source)
    seen = [n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    assert seen == ["typing", "spiral.eval", "spiral.pipeline.runner"]
    assert _cycles({"a": {"b"}, "b": {"a", "c"}, "c": set()}) == [["a", "b"]]
