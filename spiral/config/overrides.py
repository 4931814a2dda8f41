"""Settings given on the command line (``--set path.to.field=value``), applied to a spec file's data before it is
validated, and the run name that keeps a variant's folders apart from the file's own."""

from __future__ import annotations

import copy
import hashlib
import re
from collections.abc import Sequence
from typing import Any

import yaml

from spiral.config.errors import SpecError

__all__ = ["Override", "apply_overrides", "parse_override", "variant_name"]

Override = tuple[tuple[str, ...], Any]
"""A parsed override: the dotted path's keys and the value (parsed as YAML)."""


def parse_override(text: str) -> Override:
    """``"a.b.c=value"`` → ``(("a", "b", "c"), value)``, the value parsed as YAML (``600`` is an int, ``null`` None,
    ``{solo: 0.1}`` a mapping).

    Raises:
        SpecError: naming the override when it has no ``=``, an empty key or a value that is not YAML.
    """
    path, sep, raw = text.partition("=")
    keys = tuple(path.strip().split("."))
    if not sep or not all(keys):
        raise SpecError([f"--set {text}: expected path.to.field=value"])
    try:
        value = yaml.safe_load(raw)
    except yaml.YAMLError as exc:
        raise SpecError([f"--set {text}: the value is not YAML: {getattr(exc, 'problem', None) or exc}"]) from exc
    return keys, value


def apply_overrides(data: dict[str, Any], overrides: Sequence[str], *, source: str) -> dict[str, Any]:
    """``data`` (a spec file's mapping) with each override set, in order. A key under a list of named entries (a
    pipeline's ``stages``) selects the entry of that ``name``; missing tables on the way are created, so that the
    spec's validation judges the result (an unknown field is refused there, naming it).

    Raises:
        SpecError: naming ``source`` and the override when its path runs through a value that is not a table or
            names no entry of a list.
    """
    data = _unshared(data)
    for text in overrides:
        keys, value = parse_override(text)
        node: Any = data
        for depth, key in enumerate(keys[:-1]):
            node = _child(node, key, f"{source}: --set {text}: {'.'.join(keys[:depth + 1])}")
        where = f"{source}: --set {text}: {'.'.join(keys[:-1])}"
        if isinstance(node, list):
            raise SpecError([f"{where}: set a field of one entry, e.g. {'.'.join(keys[:-1])}.<name>.<field>"])
        if not isinstance(node, dict):
            raise SpecError([f"{where}: is {type(node).__name__}, not a table"])
        node[keys[-1]] = value
    return data


def _unshared(node: Any) -> Any:
    """A copy of ``node`` in which no two places hold the same table or list. A YAML anchor (``*env2v2``) or merge key
    (``<<: *multi``) loads as one object referenced from every place that names it, and ``copy.deepcopy`` keeps that
    sharing; a setting given for one stage must not reach the others that named the same anchor."""
    if isinstance(node, dict):
        return {key: _unshared(value) for key, value in node.items()}
    if isinstance(node, list):
        return [_unshared(value) for value in node]
    return copy.copy(node)


def _child(node: Any, key: str, where: str) -> Any:
    """The table under ``key`` of ``node`` (created when absent), or the entry named ``key`` of a list."""
    if isinstance(node, list):
        named = [entry for entry in node if isinstance(entry, dict) and entry.get("name") == key]
        if not named:
            names = [str(entry.get("name")) for entry in node if isinstance(entry, dict)]
            raise SpecError([f"{where}: no entry named {key!r} (entries: {', '.join(names)})"])
        return named[0]
    if not isinstance(node, dict):
        raise SpecError([f"{where}: is {type(node).__name__}, not a table"])
    if node.get(key) is None:
        node[key] = {}
    return node[key]


def variant_name(name: str, overrides: Sequence[str]) -> str:
    """The run name of ``name`` with ``overrides``: the name itself without any, else the name and the overrides in a
    file-name-safe form (``full`` with ``seed=1`` → ``full-seed-1``), shortened to a hash when long, so that two
    variants or seeds of one pipeline never share a run or checkpoint folder."""
    if not overrides:
        return name
    label = "_".join(re.sub(r"[^A-Za-z0-9._]+", "-", text).strip("-") for text in overrides)
    if len(label) > 48:
        label = hashlib.sha256("\n".join(overrides).encode()).hexdigest()[:12]
    return f"{name}-{label}"
