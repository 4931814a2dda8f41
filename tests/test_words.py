"""Spot checks of the glossary (docs/architecture.md, "Words"): one word per thing in the code.

A method (``spiral eval --method NAME=CHECKPOINT``) is named ``method`` in the evaluation layer, never ``approach``,
``agent`` or ``key``; what a method races is its ``checkpoint`` (a path, or ``se-ibr``) and, loaded, its
policy (``MethodPolicy``). What a race is (solo, 1v1 or 2v2) is a scenario, not a "race format". And no two classes
of the package share a name.
"""

from __future__ import annotations

import ast
import re
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "spiral"

NOT_A_METHOD = re.compile(r"closest[_ ]approach|approach_horizon_s", re.IGNORECASE)
"""The observation feature (and its geometry) that says "approach" about two drones, not about a method."""


def _sources(*folders: str) -> dict[Path, str]:
    return {path: path.read_text() for folder in folders for path in sorted((PACKAGE / folder).rglob("*.py"))}


def _identifiers(tree: ast.AST) -> set[str]:
    """Every name a module defines or uses: variables, attributes, functions, classes, parameters, keywords."""
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Name):
            names.add(node.id)
        elif isinstance(node, ast.Attribute):
            names.add(node.attr)
        elif isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            names.add(node.name)
        elif isinstance(node, ast.arg | ast.keyword) and node.arg is not None:
            names.add(node.arg)
    return names


def test_the_evaluation_layer_never_says_approach_for_a_method():
    """No identifier, string, docstring or comment of spiral/eval or spiral/pipeline says "approach" (a method), but
    for the closest-approach observation feature."""
    found = [f"{path.relative_to(ROOT)}:{text[:match.start()].count(chr(10)) + 1}"
             for path, source in _sources("eval", "pipeline").items()
             for text in [NOT_A_METHOD.sub("", source)]
             for match in re.finditer("approach", text, re.IGNORECASE)]
    assert found == []


def test_the_evaluation_layer_names_no_parameter_or_variable_agent_or_key_for_a_method():
    """A method's name is ``method``, what it races ``checkpoint``, loaded a policy: nothing in spiral/eval is
    named ``agent`` (``load_agent``, ``agents``, ``Agent`` ...), and no parameter is named ``key``."""
    agent_names, key_parameters = [], []
    for path, source in _sources("eval").items():
        tree = ast.parse(source)
        agent_names += [f"{path.relative_to(ROOT)}: {name}" for name in _identifiers(tree)
                        if "agent" in name.lower().split("_")]
        key_parameters += [f"{path.relative_to(ROOT)}: {node.name}" for node in ast.walk(tree)
                           if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
                           and "key" in {a.arg for a in ast.walk(node.args) if isinstance(a, ast.arg)}]
    assert agent_names == []
    assert key_parameters == []


def test_the_report_writes_the_method_column_and_the_pipeline_sections_name_the_method():
    """The report's CSV has a ``method`` column and a pairing step's section names its ``method``: what code writes
    and reads is spelt as the glossary spells it."""
    from spiral.eval.report import _CSV_FIELDS

    assert "method" in _CSV_FIELDS and "approach" not in _CSV_FIELDS
    tree = ast.parse((PACKAGE / "pipeline" / "report_steps.py").read_text())
    section_keys = {key.value for node in ast.walk(tree) if isinstance(node, ast.Dict)
                    for key in node.keys if isinstance(key, ast.Constant)}
    assert {"scenario", "method", "against"} <= section_keys


def test_prose_says_scenario_not_race_format():
    """What a race is (solo, 1v1 or 2v2) is a scenario everywhere in spiral/: no docstring or comment says "race
    format"."""
    found = [f"{path.relative_to(ROOT)}:{n}" for path, source in _sources(".").items()
             for n, line in enumerate(source.splitlines(), 1) if re.search(r"race\s+formats?\b", line, re.I)]
    assert found == []


def test_no_class_name_is_defined_twice_in_the_package():
    """One name per thing: two classes of spiral (private ones included) never share a name."""
    where: dict[str, list[str]] = defaultdict(list)
    for path, source in _sources(".").items():
        for node in ast.walk(ast.parse(source)):
            if isinstance(node, ast.ClassDef):
                where[node.name].append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert {name: places for name, places in where.items() if len(places) > 1} == {}
