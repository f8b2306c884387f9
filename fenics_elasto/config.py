"""The one schema of every input: problem.toml, scene specs and ``--set`` overrides.

Every key a user can write is declared here once, with its type, range and default
(``PROBLEM`` and ``SCENE_SPEC`` below). ``read_problem`` and ``read_scene_spec`` parse
a file, apply its ``--set KEY=VALUE`` overrides to the raw TOML and check the result
against the schema; they return it normalised: every key present, defaults filled,
numbers as float, a single group name as a one-element list, material constants as
``{value, estimate, bounds}``. Anything else is a ``UserError`` of one line that starts
with the file (and the ``--set`` at fault, if any) and the dotted key, says what was
expected and what was given, and suggests the nearest known key or value for a typo.

Checks that need the mesh (does a named group exist, does a vector have the mesh's
dimension) belong to the scene loader; ``check_gdim`` does the second once the mesh
is known.

The schema is plain Python, not jsonschema or pydantic: the nodes are a few dozen
lines, the messages come out exactly in this project's one-line form, and the
cross-key rules (alternatives, bounds around the initial value, group names that
must not clash) sit next to the keys they concern.
"""

from __future__ import annotations

import difflib
import json
import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from fenics_elasto.errors import UserError

COMMANDS = ("simulate", "estimate", "train")
SIMULATE_ONLY = ("displacement", "load", "pressure")  # [boundary] tables only `simulate` uses
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
    return key if re.fullmatch(r"[A-Za-z0-9_-]+", str(key)) else json.dumps(str(key), ensure_ascii=False)


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
                return f"{self.source} (--set {self.overrides[self.keys[:n]]!r})"
        return self.source

    def path(self, table: bool = False) -> str:
        dotted = ".".join(map(key_text, self.keys))
        return f"[{dotted}]" if table else dotted

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

    def __init__(self, keys: dict, exclusive=(), one_of=(), after=None, expected="a table"):
        self.keys, self.exclusive, self.one_of, self.after = keys, exclusive, one_of, after
        self.expected = expected

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


# --------------------------------------------------------------------------- problem.toml


def _check_boundary(boundary: dict, where: Where) -> dict:
    both = [g for g in boundary["fixed"] if g in boundary["loaded"]]
    if both:
        where.fail(f"group {show(both[0])} is both fixed and loaded; a facet is either clamped or loaded")
    _check_sizes(boundary, None, where)
    return boundary


def check_gdim(config: dict, gdim: int, source: str = "problem.toml", overridden: dict | None = None) -> None:
    """Once the mesh is read: every ``[boundary.displacement]`` / ``[boundary.load]``
    vector and matrix has the mesh's dimension ``gdim``."""
    _check_sizes(config["boundary"], gdim, Where(str(source), (), overridden or {}).at("boundary"))


def _check_sizes(boundary: dict, gdim: int | None, where: Where) -> None:
    """Every vector and matrix of ``[boundary.displacement]`` / ``[boundary.load]`` has
    one size: ``gdim`` if given, else the first one's."""
    sized = [(where.at("load").at(g), len(v)) for g, v in boundary["load"].items()]
    for group, spec in boundary["displacement"].items():
        at = where.at("displacement").at(group)
        sized += [(at.at(k), len(spec[k])) for k in ("value", "gradient", "center") if spec[k] is not None]
    for at, size in sized:
        reference = gdim or sized[0][1]
        if size != reference:
            why = f"the mesh is {gdim}D" if gdim else f"as {sized[0][0].path()}"
            at.fail(f"expected size {reference} ({why}), got {size}")


def _default_E_bounds(value: float):
    return value / 20, value * 20


def _default_nu_bounds(value: float):
    return 0.0, 0.499


MATERIAL = Table({
    "E": Key(Elastic(Number(gt=0, noun="a Young's modulus"), _default_E_bounds), REQUIRED),
    "nu": Key(Elastic(Number(gt=-1, lt=0.5, noun="a Poisson's ratio"), _default_nu_bounds), REQUIRED),
})

RIPPLE = Table({  # a smooth random displacement field (fields.py): amplitude x a unit-variance field
    "amplitude": Key(Number(ge=0), REQUIRED), "length": Key(Number(gt=0), REQUIRED), "seed": Key(Integer(ge=0), 0),
})

DISPLACEMENT = Table({  # u(x) = value + (gradient + scale I)(x - center) [+ ripple]; scene.py fills zeros
    "value": Key(Vector()), "scale": Key(Number(), 0.0), "gradient": Key(Matrix()), "center": Key(Vector()),
    "ripple": Key(RIPPLE),
})

BOUNDARY = Table({
    "fixed": Key(Names(), []),
    "loaded": Key(Names(), []),
    "matched": Key(Names(), []),
    "match_nodes": Key(Choice("auto", "all", "vertices"), "auto"),
    "displacement": Key(Named(DISPLACEMENT, "GROUP = {value, scale, gradient, center}"), {}),
    "load": Key(Named(Vector(), "GROUP = total force vector"), {}),
    "pressure": Key(Named(Number(), "GROUP = pressure (pushes the wall into the body)"), {}),
}, after=_check_boundary)

TARGET = Table({
    "surface": Key(String("a surface file")),
    "surfaces": Key(Named(String("a surface file"), "GROUP = surface file", minimum=1)),
    "landmarks": Key(String("a landmarks file")),
    "landmark_weight": Key(Number(gt=0)),
    "noise": Key(Number(gt=0)),
    "smooth": Key(Choice("auto", "off"), "auto"),
}, exclusive=[("surface", "surfaces")], one_of=("surface", "surfaces", "landmarks"),
   expected="a table {surface or surfaces, landmarks, landmark_weight, noise, smooth}")

OPTIMIZER = Table({
    "inner": Key(Choice("auto", "gauss-newton", "lbfgs", "lbfgs-forces"), "auto"),
    "inner_maxiter": Key(Integer(ge=1), 400),
    "outer_maxiter": Key(Integer(ge=1), 40),
    "outer_xtol": Key(Number(gt=0), 1e-3),
    "scan": Key(Integer(ge=1), 5),
    "inner_tol": Key(Number(gt=0, lt=1), 1e-6),
    "full_gn_limit": Key(Integer(ge=0), 1500),
    "anchor": Key(Number(ge=0), 1e-4),
    "surrogate": Key(Boolean(), True),
    "allow_undetermined": Key(Boolean(), False),
})

PROBLEM = Table({
    "mesh": Key(String("a mesh file"), REQUIRED),
    "plane": Key(Choice("strain", "stress"), "strain"),
    "degree": Key(Choice(1, 2), 2),
    "units": Key(String()),
    "materials": Key(Named(MATERIAL, "[materials.NAME] tables", minimum=1), REQUIRED),
    "boundary": Key(BOUNDARY, {}),
    "target": Key(TARGET),
    "optimizer": Key(OPTIMIZER, {}),
    "reduction": Key(Table({"bases": Key(String("a bases file"), REQUIRED), "rank": Key(Integer(ge=1))})),
    "solver": Key(Table({
        "method": Key(Choice("auto", "direct", "iterative"), "auto"),
        "rtol": Key(Number(gt=0, lt=1), 1e-8),  # every solve: ||b - K x|| <= rtol ||b||
        "factor": Key(Choice("lu", "cholesky"), "lu"),  # direct only
        "blr": Key(Number(ge=0, le=1e-2, noun="a block low-rank tolerance (0: off)"), 0.0),  # direct only
    }), {}),
})

# What each command needs in [boundary], and why.
NEEDED_GROUPS = {
    "estimate": {"fixed": "a clamped group (else the body moves freely)",
                 "loaded": "a group carrying the unknown forces",
                 "matched": "a group compared with the target"},
    "train": {"fixed": "a clamped group (else the body moves freely)",
              "loaded": "a group carrying the unknown forces"},
}


def _command_checks(config: dict, command: str, where: Where) -> list[str]:
    """What ``command`` needs and ignores; the warnings for what it ignores."""
    boundary, at = config["boundary"], where.at("boundary")
    if command == "simulate":
        if not (boundary["load"] or boundary["displacement"] or boundary["pressure"]):
            where.fail("nothing to simulate: add [boundary.load], [boundary.pressure] or [boundary.displacement]")
        if not (boundary["fixed"] or boundary["displacement"]):
            at.at("fixed").fail("clamp at least one group (fixed or [boundary.displacement]), got []")
        return []
    warnings = []
    for key in SIMULATE_ONLY:
        if boundary[key]:
            warnings.append(f"{where.source}: boundary.{key} is used by simulate only; {command} ignores it")
            boundary[key] = {}
    for key, what in NEEDED_GROUPS[command].items():
        if not boundary[key]:
            at.at(key).fail(f"{command} needs at least one group: {what}; got []")
    if command == "estimate":
        if config["target"] is None:
            where.at("target").fail("missing; estimate needs surface, surfaces or landmarks", table=True)
        if config["reduction"] is not None and config["optimizer"]["inner"] not in ("auto", "gauss-newton"):
            where.at("optimizer").at("inner").fail(
                f'reduced bases need "gauss-newton" (or "auto"), got {show(config["optimizer"]["inner"])}')
    return warnings


def validate_problem(raw: dict, source: str = "problem.toml", command: str | None = "estimate",
                     gdim: int | None = None, overridden: dict | None = None) -> tuple[dict, list[str]]:
    """Check a problem's raw TOML dict for ``command``: (normalised config, warnings).

    ``command`` None checks types and ranges only (a scene loaded for any use, from
    Python); ``overridden``: what ``apply_overrides`` returned, to blame bad values on
    their --set.
    """
    if command is not None and command not in COMMANDS:
        raise ValueError(f"command must be one of {COMMANDS}, got {command!r}")
    where = Where(str(source), (), overridden or {})
    config = PROBLEM.check(raw, where)
    if gdim is not None:
        _check_sizes(config["boundary"], gdim, where.at("boundary"))
    return config, [] if command is None else _command_checks(config, command, where)


def read_problem(path, overrides=(), command: str | None = "estimate",
                 gdim: int | None = None) -> tuple[dict, list[str]]:
    """Read, override and check ``problem.toml``: (normalised config, warnings)."""
    raw = read_toml(Path(path), "problem file")
    overridden = apply_overrides(raw, overrides, PROBLEM, str(path))
    return validate_problem(raw, str(path), command, gdim, overridden)


# --------------------------------------------------------------------------- scene spec


def _check_spec(spec: dict, where: Where) -> dict:
    """Group names must not clash; a box or ellipsoid needs something to surround."""
    owners = {}

    def claim(name, at: Where, role: str):
        if name in owners:
            at.fail(f"group name {show(name)} ({role}) clashes with {owners[name]}")
        owners[name] = f"the {role} of {at.path()}" if at.keys else role

    claim("outer", where, "the body's outer boundary")
    claim(spec["body"]["material"], where.at("body").at("material"), "cell group")
    for name in spec["regions"]:
        claim(name, where.at("regions").at(name), "cell group")
        claim(f"{name}_surface", where.at("regions").at(name), "facet group")
    for section in ("cavities", "patches"):
        for name in spec[section]:
            claim(name, where.at(section).at(name), "facet group")
    for shape in ("box", "ellipsoid"):
        if spec["body"][shape] is not None and not (spec["regions"] or spec["cavities"]):
            where.at("body").at(shape).fail("surrounds the regions and cavities, but there are none")
    return spec


def _margin():
    return Table({"margin": Key(Number(gt=0), REQUIRED)})


SCENE_SPEC = Table({
    "units": Key(Choice("mm", "cm", "m"), "mm"),
    "size": Key(Number(gt=0)),
    "organ_size": Key(Number(gt=0)),
    "body": Key(Table({
        "surface": Key(String("a surface file")), "box": Key(_margin()), "ellipsoid": Key(_margin()),
        "material": Key(GroupName(), "tissue"),
    }, exclusive=[("surface", "box", "ellipsoid")], one_of=("surface", "box", "ellipsoid"),
        expected="a table {surface, box or ellipsoid; material}"), REQUIRED),
    "regions": Key(Named(Table({"surface": Key(Names("surface file", nonempty=True), REQUIRED)}), "[regions.NAME] tables",
                         group_names=True), {}),
    "cavities": Key(Named(Table({"surface": Key(String("a surface file"), REQUIRED)}), "[cavities.NAME] tables",
                          group_names=True), {}),
    "patches": Key(Named(Table({"side": Key(Table({
        "point": Key(Vector((3,)), REQUIRED), "normal": Key(Vector((3,), nonzero=True), REQUIRED),
    }, expected="a table {point, normal}"), REQUIRED)}), "[patches.NAME] tables", group_names=True), {}),
}, after=_check_spec)


def validate_scene_spec(raw: dict, source: str = "scene.toml", overridden: dict | None = None) -> dict:
    return SCENE_SPEC.check(raw, Where(str(source), (), overridden or {}))


def read_scene_spec(path, overrides=()) -> dict:
    """Read, override and check a scene spec (``fenics-elasto scene``): the normalised spec."""
    raw = read_toml(Path(path), "scene spec")
    overridden = apply_overrides(raw, overrides, SCENE_SPEC, str(path))
    return validate_scene_spec(raw, str(path), overridden)


# --------------------------------------------------------------------------- files and --set


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
    lines: list[str] = []
    _toml_table(data, (), lines)
    return "\n".join(lines).lstrip("\n") + "\n"


def _toml_table(table: dict, keys: tuple, lines: list) -> None:
    values = [(k, v) for k, v in table.items() if not isinstance(v, dict)]
    tables = [(k, v) for k, v in table.items() if isinstance(v, dict)]
    if keys and (values or not tables):  # a header only where it holds values (or is empty)
        lines += ["", "[" + ".".join(map(_toml_key, keys)) + "]"]
    lines += [f"{_toml_key(k)} = {_toml_value(v)}" for k, v in values]
    for k, v in tables:
        _toml_table(v, keys + (k,), lines)


def _toml_key(key: str) -> str:
    return key if re.fullmatch(r"[A-Za-z0-9_-]+", key) else json.dumps(key)


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)  # inf and nan are TOML too
    if isinstance(value, str):
        return json.dumps(value)  # a JSON string is a TOML basic string
    if isinstance(value, list):
        return "[" + ", ".join(map(_toml_value, value)) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{_toml_key(k)} = {_toml_value(v)}" for k, v in value.items()) + "}"
    raise TypeError(f"no TOML form for {type(value).__name__}")


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


def apply_overrides(config: dict, overrides, schema: Table = PROBLEM, source: str = "") -> dict:
    """Set each override in the raw ``config`` (in place), the key path checked against
    ``schema``; returns {key path: override text} for ``validate_*``.

    An override is ``"KEY=VALUE"`` text (``--set``), or from Python a (dotted key, value)
    pair -- ``overrides`` may be a dict of them: ``{"materials.prostate.E": 50.0}``.
    """
    overridden = {}
    for item in (overrides.items() if isinstance(overrides, dict) else overrides):
        if isinstance(item, str):
            text, (keys, value) = item, parse_override(item)
        else:
            text, keys, value = f"{item[0]}={item[1]!r}", item[0].split("."), item[1]
        _set(config, keys, value, schema, Where(f"{source} (--set {text!r})" if source else f"--set {text!r}"))
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
        inner = table.get(key)
        if inner is None:
            inner = {}
        elif not isinstance(inner, dict):
            inner = node.promote(inner) if node.table() is not None else None
            if inner is None:
                here.fail(f"is {given(table[key])}, not a table; it has no key {key_text(keys[depth + 1])}")
        table[key] = inner
        table, where = inner, here
