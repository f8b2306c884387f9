"""The schema of problem.toml, and reading one: what each command needs and ignores.

Checks that need the mesh (does a named group exist, does a vector have the mesh's
dimension) belong to the scene loader; ``check_gdim`` does the second once the mesh
is known.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from pathlib import Path

from fenics_elasto.config.schema import (REQUIRED, ArrayOf, Boolean, Choice, Elastic, Integer, Key, LabelTargets, Matrix,
                                         Named, Names, Number, NumberOr, String, Table, Vector, VoxelEdges, Where, show,
                                         suggestion)
from fenics_elasto.config.toml import apply_overrides, read_toml

COMMANDS = ("simulate", "estimate", "train")
IN_MEMORY = "<in memory>"  # how [target] names what a Python Target gave as arrays, not files
SIMULATE_ONLY = ("displacement", "load", "pressure")  # [boundary] tables only `simulate` uses

def not_loaded(group: str, loaded: list[str]) -> str:
    """Why a measured force on ``group`` is refused, with the loaded group it may have meant."""
    guess = suggestion(group, loaded)
    return ("a measured force acts through a loaded group, and this one is not in boundary.loaded"
            + (f" (did you mean {show(guess)}?)" if guess else f" ({', '.join(map(show, loaded)) or 'none'})"))


def _check_boundary(boundary: dict, where: Where) -> dict:
    both = [g for g in boundary["fixed"] if g in boundary["loaded"]]
    if both:
        where.fail(f"group {show(both[0])} is both fixed and loaded; a facet is either clamped or loaded")
    unloaded = [g for g in boundary["measured_force"] if g not in boundary["loaded"]]
    if unloaded:
        where.at("measured_force").at(unloaded[0]).fail(not_loaded(unloaded[0], boundary["loaded"]))
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
    sized += [(where.at("measured_force").at(g).at("value"), len(f["value"]))
              for g, f in boundary["measured_force"].items()]
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

MEASURED_FORCE = Table({  # the total force applied through a loaded group, with its std (measured_force.py)
    "value": Key(Vector(), REQUIRED), "noise": Key(Number(gt=0), REQUIRED),
})

BOUNDARY = Table({
    "fixed": Key(Names(), []),
    "loaded": Key(Names(), []),
    "matched": Key(Names(), []),
    "match_nodes": Key(Choice("auto", "all", "vertices"), "auto"),
    "displacement": Key(Named(DISPLACEMENT, "GROUP = {value, scale, gradient, center}"), {}),
    "load": Key(Named(Vector(), "GROUP = total force vector"), {}),
    "pressure": Key(Named(Number(), "GROUP = pressure (pushes the wall into the body)"), {}),
    "measured_force": Key(Named(MEASURED_FORCE, "GROUP = {value, noise}"), {}),
}, after=_check_boundary)

TARGET = Table({
    "surface": Key(String("a surface file")),
    "surfaces": Key(Named(String("a surface file"), "GROUP = surface file", minimum=1)),
    "landmarks": Key(String("a landmarks file")),
    "landmark_weight": Key(Number(gt=0)),
    "landmark_noise": Key(Number(gt=0)),
    "noise": Key(Number(gt=0)),
    "labels": Key(LabelTargets()),  # the deformed state's label map: GROUP = label(s), image = "..."
    "displacement": Key(String("a displacement field file")),  # points with vectors, or a vector image
    "displacement_noise": Key(Number(gt=0)),
    "displacement_correlation": Key(Number(gt=0)),  # the field's correlation length (displacement_field.py)
    "displacement_frame": Key(Choice("world", "itk")),  # its vectors' frame, "world" if not given (files/displacements.py)
    "smooth": Key(Choice("auto", "off"), "auto"),
}, exclusive=[("surface", "surfaces", "labels")],
   one_of=("surface", "surfaces", "labels", "landmarks", "displacement"),
   expected="a table {surface, surfaces or labels, landmarks, displacement, landmark_weight, landmark_noise, "
            "displacement_noise, displacement_correlation, displacement_frame, noise, smooth}",
   elsewhere={"measured_force": "a measured force goes in [boundary.measured_force.GROUP], or in a [[states]] "
                                "table beside its target (measured_force = {GROUP = {value, noise}})"})

def _check_states(states: list, where: Where) -> list:
    names = [state["name"] for state in states]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        where.fail(f"state name {show(twice[0])} is given twice; each state needs its own name")
    return states


STATE = Table({  # one state of the body: its own target and unknown forces, the materials shared
    "name": Key(String("a state name"), REQUIRED),
    "target": Key(TARGET, REQUIRED),
    "measured_force": Key(Named(MEASURED_FORCE, "GROUP = {value, noise}"), {}),
})

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
    "matched_motion": Key(Choice("auto", "on", "off"), "auto"),
    "state_noise": Key(Choice("residual", "alike"), "residual"),
    "allow_undetermined": Key(Boolean(), False),
})

PROBLEM = Table({
    "mesh": Key(String("a mesh file"), REQUIRED),
    "plane": Key(Choice("strain", "stress"), "strain"),
    "degree": Key(Choice(1, 2), 2),
    "curve": Key(Choice("auto", "off"), "auto"),  # a straight-sided mesh of curved surfaces: curved on load
    "units": Key(String()),
    "materials": Key(Named(MATERIAL, "[materials.NAME] tables", minimum=1), REQUIRED),
    "boundary": Key(BOUNDARY, {}),
    "target": Key(TARGET),
    "states": Key(ArrayOf(STATE, "[[states]] tables {name, target}")),
    "optimizer": Key(OPTIMIZER, {}),
    # the source mesh's own error, from a solve one degree higher at the answer: corrected and counted
    # ("auto": in 3D), or not
    "uncertainty": Key(Table({"mesh": Key(Choice("auto", "on", "off"), "auto"),
                              # the voxels of the label map the source was segmented from (uncertainty/voxels.py):
                              # spacings along x, y, z, or the three edges as rows
                              "source_voxels": Key(VoxelEdges())}), {}),
    "reduction": Key(Table({"bases": Key(String("a bases file"), REQUIRED), "rank": Key(Integer(ge=1))})),
    "solver": Key(Table({
        "method": Key(Choice("auto", "direct", "iterative"), "auto"),
        "rtol": Key(Number(gt=0, lt=1), 1e-8),  # every solve: ||b - K x|| <= rtol ||b||
        "factor": Key(Choice("lu", "cholesky"), "lu"),  # direct only
        # direct only: "auto" compresses where a factorization serves few solves (model/solvers.py)
        "blr": Key(NumberOr("auto", ge=0, le=1e-2, noun="a block low-rank tolerance (0: off)"), "auto"),
    }), {}),
}, exclusive=[("target", "states")], after=lambda c, where: {
    **c, "states": None if c["states"] is None else _check_states(c["states"], where.at("states"))})

# What each command needs in [boundary], and why.
# The keys of problem.toml whose values are file names (relative to the problem file's folder)
FILE_KEYS = {("mesh",), ("target", "surface"), ("target", "landmarks"), ("target", "labels", "image"),
             ("target", "displacement"),
             ("reduction", "bases")}


def is_file_key(keys: tuple[str, ...]) -> bool:
    """Does the value at these dotted keys name a file? (``target.surfaces.GROUP`` too, and
    a state's target keys: ``states.I.target...``.)"""
    if keys[:1] == ("states",) and len(keys) > 2:
        return is_file_key(keys[2:])
    return keys in FILE_KEYS or (keys[:2] == ("target", "surfaces") and len(keys) == 3)


def map_files(keys: tuple[str, ...], value, change: Callable[[str], str]):
    """``value`` (found at ``keys`` of a problem table) with ``change`` applied to every
    file name in it; tables are walked, path-like values read as strings."""
    if isinstance(value, os.PathLike):
        value = os.fspath(value)
    if isinstance(value, Mapping):
        return {k: map_files(keys + (str(k),), v, change) for k, v in value.items()}
    if isinstance(value, list) and keys == ("states",):
        return [map_files(keys + (str(i),), v, change) for i, v in enumerate(value)]
    return change(value) if isinstance(value, str) and is_file_key(keys) else value


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
        if config["target"] is None and config["states"] is None:
            where.at("target").fail("missing; estimate needs surface, surfaces, landmarks or displacement "
                                    "(or [[states]], each with its target)", table=True)
        if config["states"] is not None and boundary["measured_force"]:
            where.at("boundary").at("measured_force").fail("with [[states]], a force is measured in one state: "
                                                           "give it as that state's measured_force")
        for i, state in enumerate(config["states"] or []):
            unloaded = [g for g in state["measured_force"] if g not in boundary["loaded"]]
            if unloaded:
                where.at("states").at(i).at("measured_force").at(unloaded[0]).fail(
                    not_loaded(unloaded[0], boundary["loaded"]))
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
