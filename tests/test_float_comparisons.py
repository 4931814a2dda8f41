"""Exact float comparisons in the tests: only in same-machine bit-identity tests.

Floats from float32 arithmetic, Warp kernels or torch can round differently on another x86-64 CPU (MKL, oneDNN and
ATen pick kernels by instruction set), so the suite compares them with a tolerance. An exact comparison stays only in
a test marked ``@pytest.mark.bitwise`` (two runs of the same thing on one host). An ``==``/``!=`` with a float
literal is excused by nothing else; an exact-comparison call (``torch.equal``, ``np.array_equal``, ...) may also stay on
a line commented ``# exact: <reason>``, for integer or boolean data only. The check reads the test sources as syntax
trees; it imports nothing of spiral.
"""

from __future__ import annotations

import ast
import io
import re
import textwrap
import tokenize
from pathlib import Path

TESTS = Path(__file__).resolve().parent

EXACT_CALLS = frozenset({"equal", "array_equal", "array_equiv", "assert_array_equal", "assert_equal"})
"""Names (bare or after a dot) of calls that compare exactly: ``torch.equal``, ``t.equal``, ``np.array_equal``,
``np.testing.assert_array_equal``, ``np.testing.assert_equal``."""

EXACT_COMMENT = re.compile(r"#\s*exact:\s*\S")


def _is_bitwise_mark(node: ast.expr) -> bool:
    """Whether a decorator (or a ``pytestmark`` entry) is ``pytest.mark.bitwise``, called or not."""
    if isinstance(node, ast.Call):
        node = node.func
    return isinstance(node, ast.Attribute) and node.attr == "bitwise" and (
        isinstance(node.value, ast.Attribute) and node.value.attr == "mark")


def _module_is_bitwise(tree: ast.Module) -> bool:
    """Whether the module sets ``pytestmark`` to the bitwise mark or to a list holding it."""
    for stmt in tree.body:
        if isinstance(stmt, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "pytestmark" for t in stmt.targets):
            marks = stmt.value.elts if isinstance(stmt.value, (ast.List, ast.Tuple)) else [stmt.value]
            if any(_is_bitwise_mark(m) for m in marks):
                return True
    return False


def _has_float_literal(node: ast.expr) -> bool:
    """Whether ``node`` is a float literal, possibly signed, or a list/tuple/set/dict display, arithmetic or
    conditional expression holding one (a call such as ``pytest.approx(...)`` is not looked into)."""
    if isinstance(node, ast.Constant):
        return isinstance(node.value, float)
    if isinstance(node, ast.UnaryOp):
        return _has_float_literal(node.operand)
    if isinstance(node, (ast.List, ast.Tuple, ast.Set)):
        return any(_has_float_literal(e) for e in node.elts)
    if isinstance(node, ast.Dict):
        return any(_has_float_literal(e) for e in (*node.keys, *node.values) if e is not None)
    if isinstance(node, ast.BinOp):
        return _has_float_literal(node.left) or _has_float_literal(node.right)
    if isinstance(node, ast.Starred):
        return _has_float_literal(node.value)
    if isinstance(node, ast.IfExp):
        return _has_float_literal(node.body) or _has_float_literal(node.orelse)
    return False


def _is_approx(node: ast.expr) -> bool:
    """Whether ``node`` is a call of ``approx`` (``pytest.approx`` or a bare import)."""
    if not isinstance(node, ast.Call):
        return False
    func = node.func
    return (isinstance(func, ast.Attribute) and func.attr == "approx") or (
        isinstance(func, ast.Name) and func.id == "approx")


def _is_exact(node: ast.AST) -> bool:
    """Whether ``node`` is an exact-comparison call or an ``==``/``!=`` with a float literal on one side."""
    if isinstance(node, ast.Call):
        func = node.func
        name = func.attr if isinstance(func, ast.Attribute) else func.id if isinstance(func, ast.Name) else None
        return name in EXACT_CALLS
    if isinstance(node, ast.Compare):
        operands = [node.left, *node.comparators]
        for op, left, right in zip(node.ops, operands[:-1], operands[1:], strict=True):
            if (isinstance(op, (ast.Eq, ast.NotEq)) and not (_is_approx(left) or _is_approx(right))
                    and (_has_float_literal(left) or _has_float_literal(right))):
                return True
    return False


def _exact_comment_lines(source: str) -> set[int]:
    """Line numbers that carry an ``# exact: <reason>`` comment."""
    tokens = tokenize.generate_tokens(io.StringIO(source).readline)
    return {tok.start[0] for tok in tokens if tok.type == tokenize.COMMENT and EXACT_COMMENT.match(tok.string)}


def exact_comparisons(source: str) -> list[int]:
    """Lines of ``source`` with an exact float comparison outside a bitwise test: any ``==``/``!=`` with a float
    literal, and any exact-comparison call without an ``# exact:`` comment on a line of its statement (for a compound
    statement, of its header up to the comparison)."""
    tree = ast.parse(source)
    commented = _exact_comment_lines(source)
    flagged: set[int] = set()

    def visit(node: ast.AST, stmt: ast.stmt | None) -> None:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and any(
                _is_bitwise_mark(d) for d in node.decorator_list):
            return
        if isinstance(node, ast.stmt):
            stmt = node
        if stmt is not None and _is_exact(node):
            compound = hasattr(stmt, "body")
            last = node.end_lineno if compound else stmt.end_lineno
            if not isinstance(node, ast.Call) or not commented.intersection(range(stmt.lineno, last + 1)):
                flagged.add(node.lineno)
        for child in ast.iter_child_nodes(node):
            visit(child, stmt)

    if not _module_is_bitwise(tree):
        visit(tree, None)
    return sorted(flagged)


def test_exact_float_comparisons_are_marked_bitwise_or_give_a_reason():
    """Compare floats in the tests with a tolerance, except in bitwise tests; ``# exact:`` excuses only calls."""
    found = [f"{path.relative_to(TESTS.parent)}:{line}"
             for path in sorted(TESTS.rglob("*.py"))
             for line in exact_comparisons(path.read_text(encoding="utf-8"))]
    assert not found, ("exact comparisons outside @pytest.mark.bitwise (float literal, or a call without "
                       "'# exact: <reason>'):\n" + "\n".join(found))


def test_checker_flags_only_unmarked_exact_comparisons():
    """Flag torch.equal, the numpy equality helpers and ``==``/``!=`` with a float literal (negative, in a list, dict
    or conditional), but not in a bitwise test, not against pytest.approx, and not for integers; an ``# exact:``
    comment on a line of the statement excuses the calls only, never a float literal."""
    source = textwrap.dedent('''\
        import numpy as np
        import pytest
        import torch

        def test_flagged(a, b, d):
            assert torch.equal(a, b)
            np.testing.assert_array_equal(a, b)
            assert np.array_equal(a, b)
            assert d["share"] == -1.0
            assert d == {"mean_share": 1.0}
            assert a.tolist() != [0.0, 2]
            assert a.tolist() == [0.0] * 3
            # exact: a comment on a line of its own excuses nothing
            assert a == (0.0 if b else 1)

        @pytest.mark.bitwise
        def test_bitwise(a, b):
            assert torch.equal(a, b) and a.sum() == 0.5

        def test_reasoned(a, b):
            assert torch.equal(a, b)  # exact: integer data
            np.testing.assert_array_equal(
                a, b)  # exact: boolean masks
            assert a.tolist() == [
                1.0, 2.0]  # exact: set by the test
            if a == 0.5:  # exact: written, not computed
                pass

        def test_tolerant(a, b):
            assert a == pytest.approx(0.5)
            assert [0.5, 1.0] == pytest.approx(a)
            assert a.count == 3 and b != "x"
            torch.testing.assert_close(a, b)
        ''')
    assert exact_comparisons(source) == [6, 7, 8, 9, 10, 11, 12, 14, 24, 26]
