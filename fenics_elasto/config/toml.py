"""TOML files and ``--set KEY=VALUE`` overrides.

``apply_overrides`` sets each override in the raw TOML dict before it is checked, the
key path walked down the schema (so a typo is caught where it is made, and blamed on
its ``--set``). Writing TOML is tomli-w's (MIT): problem files the toolkit derives.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import tomli_w

from fenics_elasto.config.schema import Named, Table, Where, given, key_text, suggestion
from fenics_elasto.util.errors import UserError

def read_toml(path: Path, what: str = "problem file") -> dict:
    if not path.is_file():
        raise UserError(f"{path}: is a directory, not a {what}" if path.is_dir() else f"{path}: no such {what}")
    try:
        return tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
        raise UserError(f"{path}: not valid TOML ({err})") from None


def toml_text(data: dict) -> str:
    """``data`` -- tables, arrays, strings, numbers, booleans, as ``read_toml`` gives
    them -- written back as TOML (comments are not kept: the dict has none)."""
    return tomli_w.dumps(data)


def parse_override(text: str) -> tuple[list[str], object]:
    """``materials.prostate.E=50`` -> (["materials", "prostate", "E"], 50.0).

    The value is read as a TOML value; what is not one (``../truth/surface.vtp``) is
    taken as a bare string.
    """
    key, sep, value = text.partition("=")
    keys = [k.strip() for k in key.split(".")]
    if not sep or not all(keys):
        raise UserError(f"--set {text!r}: expected KEY=VALUE (like optimizer.scan=3)")
    try:
        parsed = tomllib.loads(f"v = {value}")
    except tomllib.TOMLDecodeError:
        parsed = {}
    return keys, parsed["v"] if list(parsed) == ["v"] else value.strip()


def apply_overrides(config: dict, overrides, schema: Table, source: str = "") -> dict:
    """Set each override in the raw ``config`` (in place), the key path checked against
    ``schema``; returns {key path: how the override was given, for messages} for ``validate_*``.

    An override is ``"KEY=VALUE"`` text (``--set``), or from Python a (dotted key, value)
    pair -- ``overrides`` may be a dict of them: ``{"materials.prostate.E": 50.0}``.
    """
    overridden = {}
    for item in (overrides.items() if isinstance(overrides, dict) else overrides):
        if isinstance(item, str):
            (keys, value), text = parse_override(item), f"--set {item!r}"
        else:  # from Python: named as the user wrote it, not as a --set they never typed
            keys, value, text = item[0].split("."), item[1], f"{item[0]} = {item[1]!r} from Python"
        _set(config, keys, value, schema, Where(f"{source} ({text})" if source else text))
        overridden[tuple(keys)] = text
    return overridden


def _set(config: dict, keys: list, value, schema: Table, where: Where) -> None:
    """Walk ``keys`` down the schema and the dict together; set the last one to ``value``.

    A key of an exclusive group drops its siblings (``target.surface`` replaces
    ``target.surfaces``); a fixed constant promoted to a table keeps its value
    (``materials.m.E.estimate=true`` on ``E = 10`` starts the estimate at 10).
    """
    node, table = schema, config
    for depth, key in enumerate(keys):
        shape = node.table()
        if shape is None:
            where.fail(f"is {node.expected}, not a table; it has no key {key_text(key)}")
        here, last = where.at(key), depth == len(keys) - 1
        node = shape.child(key, here, None if last else {})
        if isinstance(shape, Named) and not last and key not in table:
            near = suggestion(key, table)
            if near is not None:
                here.fail(f"no such entry; did you mean {key_text(near)}? (a new one is set whole: "
                          f"--set '{here.path()}={{...}}')")
        for other in shape.siblings(key):
            table.pop(other, None)
        if last:
            table[key] = value
            return
        inner: dict | None = table.get(key)
        if inner is None:
            inner = {}
        elif not isinstance(inner, dict):
            promoted = node.promote(inner) if node.table() is not None else None
            if promoted is None:
                here.fail(f"is {given(table[key])}, not a table; it has no key {key_text(keys[depth + 1])}")
            inner = promoted
        table[key] = inner
        assert inner is not None
        table, where = inner, here
