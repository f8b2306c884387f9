"""The schema toolkit: typed nodes that check a value and explain what is wrong.

Every key a user can write is declared once, with its type, range and default, out of
these nodes (``problem.PROBLEM``, ``scene_spec.SCENE_SPEC``). Checking returns the value
normalised -- every key present, defaults filled, numbers as float, a single group name
as a one-element list, material constants as ``{value, estimate, bounds}`` -- or raises a
``UserError`` of one line that starts with the file (and the ``--set`` at fault, if any)
and the dotted key, says what was expected and what was given, and suggests the nearest
known key or value for a typo.

The toolkit is plain Python, not pydantic or msgspec: the nodes are a few dozen lines,
the messages come out exactly in this project's one-line form (file, the --set that gave
a value, dotted key, range, "did you mean"), and the cross-key rules (alternatives,
bounds around the initial value, group names that must not clash) sit next to the keys
they concern. pydantic v2's errors carry a location and a type but neither the --set
at fault nor a suggestion for a typo, so each of the catalogue's 230 lines would need
translating back from them -- about as much code as the nodes (docs: "Configuration").
"""

from __future__ import annotations

import difflib
import json
import math
import re
from dataclasses import dataclass, field

from fenics_elasto.util.errors import UserError

REQUIRED = object()  # a Key default: the key must be given

# --------------------------------------------------------------------------- messages


def show(value) -> str:
    """A value as TOML would spell it, on one line, shortened if long."""
    if isinstance(value, bool):
        text = "true" if value else "false"
    elif isinstance(value, str):
        text = json.dumps(value, ensure_ascii=False)
    elif isinstance(value, (list, tuple)):
        text = "[" + ", ".join(map(show, value)) + "]"
    elif isinstance(value, dict):
        text = "{" + ", ".join(f"{key_text(k)} = {show(v)}" for k, v in value.items()) + "}"
    else:
        text = str(value)
    return text if len(text) <= 60 else text[:57] + "..."


def kind(value) -> str:
    kinds = ((bool, "a boolean"), (int, "an integer"), (float, "a number"), (str, "a string"),
             ((list, tuple), "a list"), (dict, "a table"))
    return next((name for types, name in kinds if isinstance(value, types)), "a date/time")


def given(value) -> str:
    return f"{show(value)} ({kind(value)})"


def key_text(key) -> str:
    return str(key) if re.fullmatch(r"[A-Za-z0-9_-]+", str(key)) else json.dumps(str(key), ensure_ascii=False)


def suggestion(word: str, known) -> str | None:
    """The known word nearest to a typo (case differences count as no difference)."""
    lowered = {str(k).lower(): k for k in known}
    close = difflib.get_close_matches(str(word).lower(), list(lowered), n=1, cutoff=0.6)
    return lowered[close[0]] if close else None


@dataclass(frozen=True)
class Where:
    """A key path in one input, for messages. ``overrides`` maps the key paths set by
    ``--set`` to their text, so a bad value is blamed on the override that gave it."""

    source: str
    keys: tuple = ()
    overrides: dict = field(default_factory=dict, compare=False)

    def at(self, key) -> Where:
        return Where(self.source, self.keys + (key,), self.overrides)

    def label(self) -> str:
        for n in range(len(self.keys), 0, -1):
            if self.keys[:n] in self.overrides:
                return f"{self.source} ({self.overrides[self.keys[:n]]})"
        return self.source

    def path(self, table: bool = False) -> str:
        """The keys dotted, a list's item by its index: ``states[0].measured_force``."""
        dotted = ""
        for key in self.keys:
            dotted += f"[{key}]" if isinstance(key, int) else ("." if dotted else "") + key_text(key)
        return f"[{dotted}]" if table and dotted else dotted

    def fail(self, text: str, table: bool = False):
        path = self.path(table)
        raise UserError(f"{self.label()}: {path}: {text}" if path else f"{self.label()}: {text}")


# --------------------------------------------------------------------------- nodes


class Node:
    """One kind of value. ``check`` returns it normalised or fails with a message."""

    expected = "a value"

    def check(self, value, where: Where):
        raise NotImplementedError

    def table(self):
        """The Table or Named an override may set keys inside, or None for a leaf."""
        return None

    def promote(self, value):
        """A dict standing for a scalar given where an override goes deeper, or None."""
        return None


def _range_text(gt, ge, lt, le) -> str:
    low = f"({gt:g}" if gt is not None else f"[{ge:g}" if ge is not None else None
    high = f"{lt:g})" if lt is not None else f"{le:g}]" if le is not None else None
    if low and high:
        return f" in {low}, {high}"
    if low:
        return f" {'>' if low[0] == '(' else '>='} {low[1:]}"
    return f" {'<' if high[-1] == ')' else '<='} {high[:-1]}" if high else ""


class Number(Node):
    """A finite number (an integer is taken as a float), optionally within a range."""

    noun = "a number"

    def __init__(self, gt=None, ge=None, lt=None, le=None, noun: str | None = None):
        self.bounds = (gt, ge, lt, le)
        self.noun = noun or self.noun
        self.expected = self.noun + _range_text(gt, ge, lt, le)

    def is_type(self, value) -> bool:
        return isinstance(value, (int, float)) and not isinstance(value, bool)

    def within(self, value) -> bool:
        gt, ge, lt, le = self.bounds
        finite = isinstance(value, int) or math.isfinite(value)
        return finite and all((
            gt is None or value > gt, ge is None or value >= ge, lt is None or value < lt, le is None or value <= le))

    def check(self, value, where):
        if not self.is_type(value):
            where.fail(f"expected {self.expected}, got {given(value)}")
        if not self.within(value):
            where.fail(f"expected {self.expected}, got {show(value)}")
        return float(value)


class NumberOr(Number):
    """A number within a range, or one of a few words standing for a rule ("auto")."""

    def __init__(self, *words: str, **bounds):
        super().__init__(**bounds)
        self.words = words
        self.expected = " or ".join([show(w) for w in words] + [self.expected])

    def check(self, value, where):
        if isinstance(value, str) and value in self.words:
            return value
        return super().check(value, where)


class Integer(Number):
    noun = "an integer"

    def is_type(self, value) -> bool:
        return isinstance(value, int) and not isinstance(value, bool)

    def check(self, value, where):
        super().check(value, where)
        return int(value)


class Boolean(Node):
    expected = "true or false"

    def check(self, value, where):
        if not isinstance(value, bool):
            where.fail(f"expected {self.expected}, got {given(value)}")
        return value


class String(Node):
    def __init__(self, what: str = ""):
        self.expected = f"{what} (a string)" if what else "a string"

    def check(self, value, where):
        if not isinstance(value, str):
            where.fail(f"expected {self.expected}, got {given(value)}")
        if not value.strip():
            where.fail(f"expected {self.expected}, got an empty string")
        return value


class GroupName(Node):
    """A name for a gmsh physical group. It starts with a letter: gmsh calls unnamed
    groups by their number, so a name of digits could clash."""

    expected = "a group name (letters, digits, '_' and '-', starting with a letter)"

    def check(self, value, where):
        if not (isinstance(value, str) and re.fullmatch(r"[A-Za-z][A-Za-z0-9_-]*", value)):
            where.fail(f"expected {self.expected}, got {given(value)}")
        return value


class Choice(Node):
    """One of a few values (strings or integers: ``true`` is not ``1``)."""

    def __init__(self, *options):
        self.options = options
        shown = [show(o) for o in options]
        self.expected = " or ".join(shown) if len(shown) == 2 else "one of " + ", ".join(shown)

    def check(self, value, where):
        if any(type(value) is type(o) and value == o for o in self.options):
            return value
        near = suggestion(value, [o for o in self.options if isinstance(o, str)]) if isinstance(value, str) else None
        hint = f"; did you mean {show(near)}?" if near is not None else ""
        where.fail(f"expected {self.expected}, got {given(value)}{hint}")


class Names(Node):
    """Names (of groups, files): a list of strings, or one string for a one-element list."""

    def __init__(self, noun: str = "group name", nonempty: bool = False):
        self.noun, self.nonempty = noun, nonempty
        self.expected = f"a {noun} or a list of {noun}s"

    def check(self, value, where):
        names = [value] if isinstance(value, str) else value
        if not isinstance(names, (list, tuple)) or not all(isinstance(n, str) and n.strip() for n in names):
            where.fail(f"expected {self.expected}, got {given(value)}")
        if self.nonempty and not names:
            where.fail(f"expected at least one {self.noun}, got {show(value)}")
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            where.fail(f"lists {show(twice[0])} twice")
        return list(names)


class Labels(Node):
    """Label values of a label-map image: a positive integer, or a list of them (0 is the
    background by convention)."""

    expected = "a label (an integer >= 1) or a list of labels"

    def check(self, value, where):
        labels = [value] if not isinstance(value, (list, tuple)) else list(value)
        if not labels or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 1 for v in labels):
            where.fail(f"expected {self.expected}, got {given(value)}")
        twice = sorted({v for v in labels if labels.count(v) > 1})
        if twice:
            where.fail(f"lists label {twice[0]} twice")
        return labels


class Vector(Node):
    """A list of finite numbers of one of the allowed lengths."""

    def __init__(self, sizes=(2, 3), nonzero: bool = False):
        self.sizes, self.nonzero = sizes, nonzero
        self.expected = "a " + " or ".join(f"{n}-vector" for n in sizes) + " of numbers"

    def check(self, value, where):
        number = Number()
        if not (isinstance(value, (list, tuple)) and len(value) in self.sizes
                and all(number.is_type(v) for v in value)):
            where.fail(f"expected {self.expected}, got {given(value)}")
        if not all(number.within(v) for v in value):
            where.fail(f"expected {self.expected}, got {show(value)} (not finite)")
        if self.nonzero and not any(value):
            where.fail(f"expected a nonzero vector, got {show(value)}")
        return [float(v) for v in value]


class Matrix(Node):
    """A square matrix of finite numbers, as a list of rows."""

    def __init__(self, sizes=(2, 3)):
        self.sizes = sizes
        self.expected = "a " + " or ".join(f"{n}x{n}" for n in sizes) + " matrix (a list of rows)"

    def check(self, value, where):
        if not (isinstance(value, (list, tuple)) and len(value) in self.sizes):
            where.fail(f"expected {self.expected}, got {given(value)}")
        return [Vector((len(value),)).check(row, where) for row in value]


class VoxelEdges(Node):
    """A label map's voxel: its three spacings along x, y, z (positive), or its three
    edges in world coordinates as rows (an oblique image's affine columns)."""

    expected = "3 positive spacings [sx, sy, sz], or the voxel's three edges as rows (a 3x3 matrix)"

    def check(self, value, where):
        if isinstance(value, (list, tuple)) and value and all(isinstance(row, (list, tuple)) for row in value):
            edges = Matrix((3,)).check(value, where)
            (a, b, c), (d, e, f), (g, h, i) = edges
            if a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g) == 0:
                where.fail(f"expected {self.expected}, got {show(value)} (the edges span no volume)")
            return edges
        spacings = Vector((3,)).check(value, where) if isinstance(value, (list, tuple)) else where.fail(
            f"expected {self.expected}, got {given(value)}")
        if min(spacings) <= 0:
            where.fail(f"expected {self.expected}, got {show(value)}")
        return spacings


@dataclass(frozen=True)
class Key:
    """A table's key: its node, and its default (REQUIRED; None: absent; anything
    else: checked like a given value, so ``{}`` fills a sub-table's defaults)."""

    node: Node
    default: object = None


class Table(Node):
    """A table with known keys. ``exclusive``: groups of keys of which at most one may be
    given (an override of one drops the others); ``one_of``: at least one must be;
    ``after(checked, where)`` adds the rules that span several keys."""

    def __init__(self, keys: dict, exclusive=(), one_of=(), after=None, expected="a table", elsewhere=None):
        """``elsewhere``: {key: where it belongs}, for keys users put in this table by mistake."""
        self.keys, self.exclusive, self.one_of, self.after = keys, exclusive, one_of, after
        self.expected, self.elsewhere = expected, elsewhere or {}

    def table(self):
        return self

    def child(self, name, where: Where, value=None) -> Node:
        if name not in self.keys:
            self.unknown(name, value, where)
        return self.keys[name].node

    def siblings(self, name) -> list:
        return [other for group in self.exclusive if name in group for other in group if other != name]

    def unknown(self, name, value, where: Where):
        as_table = isinstance(value, dict)
        if name in self.elsewhere:
            where.fail(f"not a key of this table: {self.elsewhere[name]}", table=as_table)
        near = suggestion(name, self.keys)
        if near is None:
            hint = "; known keys: " + ", ".join(self.keys)
        elif isinstance(self.keys[near].node, (Table, Named)):
            hint = f"; did you mean {Where('', where.keys[:-1] + (near,)).path(table=True)}?"
        else:
            hint = f"; did you mean {key_text(near)}?"
        where.fail(f"unknown {'table' if as_table else 'key'}{hint}", table=as_table)

    def check(self, value, where):
        if not isinstance(value, dict):
            where.fail(f"expected {self.expected}, got {given(value)}")
        for name, item in value.items():
            if name not in self.keys:
                self.unknown(name, item, where.at(name))
        present = [k for k in self.keys if value.get(k) is not None]
        for group in self.exclusive:
            both = [k for k in group if k in present]
            if len(both) > 1:
                where.fail(f"give {' or '.join(both)}, not both", table=True)
        if self.one_of and not set(self.one_of) & set(present):
            where.fail(f"give {' or '.join(self.one_of)}", table=True)
        checked = {name: self.check_key(name, value.get(name), where.at(name)) for name in self.keys}
        return self.after(checked, where) if self.after else checked

    def check_key(self, name, value, where):
        key = self.keys[name]
        if value is None:
            if key.default is REQUIRED:
                where.fail(f"missing; expected {key.node.expected}", table=isinstance(key.node, (Table, Named)))
            value = key.default
        return None if value is None else key.node.check(value, where)


class Named(Node):
    """A table of named entries of one kind (``[materials.NAME]``...); with ``group_names``
    each NAME must be a valid group name."""

    def __init__(self, item: Node, what: str, minimum: int = 0, group_names: bool = False):
        self.item, self.minimum, self.what, self.group_names = item, minimum, what, group_names
        self.expected = f"a table of {what}"

    def table(self):
        return self

    def child(self, name, where: Where, value=None) -> Node:
        if self.group_names:
            GroupName().check(name, where)
        return self.item

    def siblings(self, name) -> list:
        return []

    def check(self, value, where):
        if not isinstance(value, dict):
            where.fail(f"expected {self.expected}, got {given(value)}")
        if len(value) < self.minimum:
            where.fail(f"expected {self.expected}, got none", table=True)
        return {name: self.child(name, where.at(name)).check(item, where.at(name)) for name, item in value.items()}


class ArrayOf(Node):
    """An array of tables of one kind (``[[states]]``), each checked at its index; set
    whole by an override."""

    def __init__(self, item: Node, what: str, minimum: int = 1):
        self.item, self.minimum = item, minimum
        self.expected = f"an array of {what}"

    def check(self, value, where):
        if not isinstance(value, list) or len(value) < self.minimum:
            where.fail(f"expected {self.expected} (at least {self.minimum}), got {given(value)}")
        return [self.item.check(item, where.at(i)) for i, item in enumerate(value)]


class LabelTargets(Named):
    """``[target.labels]``: ``image = "..."`` (the deformed state's label map) and
    ``GROUP = label or [labels]`` per matched facet group (its target: the boundary of
    those labels' union)."""

    def __init__(self):
        super().__init__(Labels(), "GROUP = label or [labels], and image = \"...\"", minimum=2)

    def child(self, name, where: Where, value=None) -> Node:
        return String("a label-map image") if name == "image" else super().child(name, where, value)

    def check(self, value, where):
        out = super().check(value, where)
        if "image" not in out:
            where.at("image").fail('missing; expected the deformed state\'s label-map image = "..."')
        return out


class Elastic(Node):
    """A material constant: a number (fixed), or ``{estimate, initial (alias value),
    bounds}``; normalised to ``{value, estimate, bounds}`` (bounds None when fixed and
    not given). Estimated without bounds: ``default_bounds(initial)``."""

    def __init__(self, valid: Number, default_bounds):
        self.valid, self.default_bounds = valid, default_bounds
        self.expected = f"{valid.expected} or a table {{estimate, initial, bounds}}"
        self.spec = Table({
            "estimate": Key(Boolean(), False), "initial": Key(Number()), "value": Key(Number()),
            "bounds": Key(Vector((2,))),
        }, exclusive=[("initial", "value")], after=self._settle, expected=self.expected)

    def table(self):
        return self.spec

    def promote(self, value):
        return {"initial": value}

    def check(self, value, where):
        if isinstance(value, dict):
            return self.spec.check(value, where)
        if not self.valid.is_type(value):
            where.fail(f"expected {self.expected}, got {given(value)}")
        return {"value": self.valid.check(value, where), "estimate": False, "bounds": None}

    def _settle(self, spec: dict, where: Where) -> dict:
        name = "value" if spec["value"] is not None else "initial"
        value = spec[name]
        if value is None:
            where.at("initial").fail(f"missing; expected {self.valid.expected} (the fixed or starting value)")
        value = self.valid.check(value, where.at(name))
        bounds = spec["bounds"]
        if bounds is not None:
            if not all(self.valid.within(b) for b in bounds):
                where.at("bounds").fail(f"expected [low, high], each {self.valid.expected}, got {show(bounds)}")
            if not bounds[0] < bounds[1]:
                where.at("bounds").fail(f"expected [low, high] with low < high, got {show(bounds)}")
        elif spec["estimate"]:
            bounds = list(self.default_bounds(value))
        if bounds is not None and not bounds[0] <= value <= bounds[1]:
            given_bounds = "bounds" if spec["bounds"] is not None else "the default bounds"
            hint = "" if spec["bounds"] is not None else "; give bounds"
            where.at(name).fail(f"{show(value)} is outside {given_bounds} {show(bounds)}{hint}")
        return {"value": value, "estimate": spec["estimate"], "bounds": bounds}
