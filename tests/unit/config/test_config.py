"""The input schema (fenics_elasto.config): every bad input is one line naming the key,
what was expected and what was given; good inputs normalise with the documented
defaults. Dicts and small TOML files only: no mesh, no solve."""

import copy
import datetime
import math

import pytest

from fenics_elasto.mesh import builtin as meshing
from fenics_elasto.config.problem import PROBLEM, check_gdim, read_problem, validate_problem
from fenics_elasto.config.scene_spec import SCENE_SPEC, read_scene_spec, validate_scene_spec
from fenics_elasto.config.toml import apply_overrides, parse_override, toml_text
from fenics_elasto.util.errors import UserError

DROP = object()  # in a patch: remove this key

BASE = {  # the letter A's problem, as tomllib reads it
    "mesh": "letter_a.msh",
    "materials": {"letter": {"E": 10.0, "nu": {"estimate": True, "initial": 0.3, "bounds": [0.0, 0.499]}}},
    "boundary": {"fixed": ["feet"], "loaded": ["top"], "matched": ["outline"],
                 "displacement": {"top": {"value": [0.4, -0.8]}}},
    "target": {"surface": "target.vtp"},
}


def patched(base: dict, patch: dict) -> dict:
    """``base`` deep-merged with ``patch`` (tables merge, other values replace, DROP removes)."""
    out = copy.deepcopy(base)
    for key, value in patch.items():
        if value is DROP:
            out.pop(key, None)
        elif isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = patched(out[key], value)
        else:
            out[key] = value
    return out


def problem(patch=None, overrides=(), command="estimate"):
    raw = patched(BASE, patch or {})
    overridden = apply_overrides(raw, overrides, PROBLEM, "problem.toml")
    return validate_problem(raw, "problem.toml", command, overridden=overridden)


def message(call) -> str:
    with pytest.raises(UserError) as err:
        call()
    text = str(err.value)
    assert "\n" not in text, text
    return text


def E(spec):
    return {"materials": {"letter": {"E": spec}}}


def NU(spec):
    return {"materials": {"letter": {"nu": spec}}}


def NU_TABLE(**keys):
    return {"materials": {"letter": {"nu": {"estimate": True, "initial": 0.3, "bounds": [0.0, 0.499], **keys}}}}


def OPT(**keys):
    return {"optimizer": keys}


# (patch, --set overrides, command, the message's start, the parts it must contain)
BAD_PROBLEMS = {
    # top level
    "mesh not a string": ({"mesh": 5}, (), "estimate", "problem.toml: mesh:", ["expected a mesh file", "got 5 (an integer)"]),
    "mesh missing": ({"mesh": DROP}, (), "estimate", "problem.toml: mesh:", ["missing"]),
    "mesh empty": ({"mesh": " "}, (), "estimate", "problem.toml: mesh:", ["empty string"]),
    "mesh a date": ({"mesh": datetime.date(1979, 5, 27)}, (), "estimate", "problem.toml: mesh:", ["1979-05-27 (a date/time)"]),
    "plane typo key": ({"plain": "stress"}, (), "estimate", "problem.toml: plain:", ["unknown key", "did you mean plane?"]),
    "plane wrong case": ({"plane": "Stress"}, (), "estimate", "problem.toml: plane:", ['did you mean "stress"?']),
    "plane a number": ({"plane": 2}, (), "estimate", "problem.toml: plane:", ['"strain" or "stress"', "got 2 (an integer)"]),
    "degree 3": ({"degree": 3}, (), "estimate", "problem.toml: degree:", ["expected 1 or 2, got 3"]),
    "degree true": ({"degree": True}, (), "estimate", "problem.toml: degree:", ["got true (a boolean)"]),
    "degree float": ({"degree": 2.0}, (), "estimate", "problem.toml: degree:", ["got 2.0 (a number)"]),
    "units a number": ({"units": 5}, (), "estimate", "problem.toml: units:", ["expected a string"]),
    "unknown top key, no near one": ({"colour": "red"}, (), "estimate", "problem.toml: colour:", ["unknown key", "known keys: mesh"]),
    # materials
    "materials a number": ({"materials": 5}, (), "estimate", "problem.toml: materials:", ["[materials.NAME] tables", "got 5"]),
    "materials empty": ({"materials": {"letter": DROP}}, (), "estimate", "problem.toml: [materials]:", ["got none"]),
    "materials missing": ({"materials": DROP}, (), "estimate", "problem.toml: [materials]:", ["missing"]),
    "material key case": ({"materials": {"letter": {"Nu": 0.45}}}, (), "estimate", "problem.toml: materials.letter.Nu:",
                          ["unknown key", "did you mean nu?"]),
    "material E missing": ({"materials": {"letter": {"E": DROP}}}, (), "estimate", "problem.toml: materials.letter.E:", ["missing"]),
    "material not a table": ({"materials": {"letter": 3}}, (), "estimate", "problem.toml: materials.letter:", ["expected a table"]),
    "E zero": (E(0), (), "estimate", "problem.toml: materials.letter.E:", ["expected a Young's modulus > 0, got 0"]),
    "E negative": (E(-1.5), (), "estimate", "problem.toml: materials.letter.E:", ["got -1.5"]),
    "E nan": (E(math.nan), (), "estimate", "problem.toml: materials.letter.E:", ["got nan"]),
    "E inf": (E(math.inf), (), "estimate", "problem.toml: materials.letter.E:", ["got inf"]),
    "E a string": (E("10"), (), "estimate", "problem.toml: materials.letter.E:", ['got "10" (a string)', "or a table"]),
    "E a boolean": (E(True), (), "estimate", "problem.toml: materials.letter.E:", ["got true (a boolean)"]),
    "E no initial": (E({"estimate": True}), (), "estimate", "problem.toml: materials.letter.E.initial:", ["missing"]),
    "E initial and value": (E({"initial": 1, "value": 2}), (), "estimate", "problem.toml: [materials.letter.E]:",
                            ["initial or value, not both"]),
    "E table typo": (E({"estimat": True, "initial": 5}), (), "estimate", "problem.toml: materials.letter.E.estimat:",
                     ["did you mean estimate?"]),
    "E lower bound 0": (E({"estimate": True, "initial": 5, "bounds": [0, 100]}), (), "estimate",
                        "problem.toml: materials.letter.E.bounds:", ["each a Young's modulus > 0, got [0.0, 100.0]"]),
    "E initial not positive": (E({"initial": -5}), (), "estimate", "problem.toml: materials.letter.E.initial:", ["got -5"]),
    "nu 0.5": (NU(0.5), (), "estimate", "problem.toml: materials.letter.nu:", ["expected a Poisson's ratio in (-1, 0.5), got 0.5"]),
    "nu -1": (NU(-1), (), "estimate", "problem.toml: materials.letter.nu:", ["got -1"]),
    "estimate a string": (NU_TABLE(estimate="false"), (), "estimate", "problem.toml: materials.letter.nu.estimate:",
                          ['expected true or false, got "false" (a string)']),
    "bounds reversed": (NU_TABLE(bounds=[0.4, 0.1]), (), "estimate", "problem.toml: materials.letter.nu.bounds:",
                        ["low < high", "[0.4, 0.1]"]),
    "bounds past 0.5": (NU_TABLE(bounds=[0.0, 0.6]), (), "estimate", "problem.toml: materials.letter.nu.bounds:",
                        ["each a Poisson's ratio in (-1, 0.5), got [0.0, 0.6]"]),
    "bounds of 3": (NU_TABLE(bounds=[0.0, 0.2, 0.4]), (), "estimate", "problem.toml: materials.letter.nu.bounds:",
                    ["expected a 2-vector"]),
    "initial outside bounds": (NU_TABLE(initial=0.48, bounds=[0.0, 0.45]), (), "estimate",
                               "problem.toml: materials.letter.nu.initial:", ["0.48 is outside bounds [0.0, 0.45]"]),
    "initial outside default bounds": (NU_TABLE(initial=-0.2, bounds=DROP), (), "estimate",
                                       "problem.toml: materials.letter.nu.initial:", ["default bounds [0.0, 0.499]", "give bounds"]),
    # boundary
    "boundary a string": ({"boundary": "x"}, (), "estimate", "problem.toml: boundary:", ['expected a table, got "x"']),
    "fixed a number": ({"boundary": {"fixed": 5}}, (), "estimate", "problem.toml: boundary.fixed:", ["got 5 (an integer)"]),
    "fixed holds a number": ({"boundary": {"fixed": ["feet", 3]}}, (), "estimate", "problem.toml: boundary.fixed:", ['["feet", 3]']),
    "fixed twice": ({"boundary": {"fixed": ["feet", "feet"]}}, (), "estimate", "problem.toml: boundary.fixed:", ['"feet" twice']),
    "fixed and loaded": ({"boundary": {"loaded": ["top", "feet"]}}, (), "estimate", "problem.toml: boundary:",
                         ['"feet" is both fixed and loaded']),
    "match_nodes typo": ({"boundary": {"match_nodes": "vertex"}}, (), "estimate", "problem.toml: boundary.match_nodes:",
                         ['did you mean "vertices"?']),
    "boundary key typo": ({"boundary": {"fixd": ["feet"]}}, (), "estimate", "problem.toml: boundary.fixd:", ["did you mean fixed?"]),
    "displacement table typo": ({"boundary": {"displacment": {"top": {}}}}, (), "estimate", "problem.toml: [boundary.displacment]:",
                                ["unknown table", "did you mean [boundary.displacement]?"]),
    "displacement key typo": ({"boundary": {"displacement": {"top": {"valu": [1, 0]}}}}, (), "simulate",
                              "problem.toml: boundary.displacement.top.valu:", ["did you mean value?"]),
    "displacement of 4": ({"boundary": {"displacement": {"top": {"value": [1, 2, 3, 4]}}}}, (), "simulate",
                          "problem.toml: boundary.displacement.top.value:", ["2-vector or 3-vector", "got [1, 2, 3, 4]"]),
    "displacement nan": ({"boundary": {"displacement": {"top": {"value": [1, math.nan]}}}}, (), "simulate",
                         "problem.toml: boundary.displacement.top.value:", ["not finite"]),
    "gradient not square": ({"boundary": {"displacement": {"top": {"gradient": [[1, 0], [0, 1], [0, 0]]}}}}, (), "simulate",
                            "problem.toml: boundary.displacement.top.gradient:", ["expected a 3-vector", "[1, 0]"]),
    "vector sizes differ": ({"boundary": {"displacement": {"top": {"center": [0, 0, 0]}}}}, (), "simulate",
                            "problem.toml: boundary.displacement.top.center:", ["expected size 2", "got 3"]),
    "scale a string": ({"boundary": {"displacement": {"top": {"scale": "0.1"}}}}, (), "simulate",
                       "problem.toml: boundary.displacement.top.scale:", ['got "0.1" (a string)']),
    "load not a vector": ({"boundary": {"load": {"top": "down"}}}, (), "simulate", "problem.toml: boundary.load.top:",
                          ['got "down" (a string)']),
    "fixed empty for estimate": ({"boundary": {"fixed": []}}, (), "estimate", "problem.toml: boundary.fixed:",
                                 ["estimate needs at least one group", "got []"]),
    "matched empty for estimate": ({"boundary": {"matched": []}}, (), "estimate", "problem.toml: boundary.matched:",
                                   ["estimate needs"]),
    "loaded empty for train": ({"boundary": {"loaded": []}}, (), "train", "problem.toml: boundary.loaded:", ["train needs"]),
    "nothing clamped in simulate": ({"boundary": {"fixed": [], "displacement": DROP, "load": {"top": [0, -1]}}}, (),
                                    "simulate", "problem.toml: boundary.fixed:", ["clamp at least one group"]),
    "nothing to simulate": ({"boundary": {"displacement": DROP}}, (), "simulate", "problem.toml:", ["nothing to simulate"]),
    # target
    "target a number": ({"target": 5}, (), "estimate", "problem.toml: target:", ["expected a table {surface, surfaces or labels", "got 5"]),
    "target.surface a number": ({"target": {"surface": 5}}, (), "estimate", "problem.toml: target.surface:", ["got 5"]),
    "surface and surfaces": ({"target": {"surfaces": {"outline": "o.vtp"}}}, (), "estimate", "problem.toml: [target]:",
                             ["surface or surfaces, not both"]),
    "target empty": ({"target": {"surface": DROP}}, (), "estimate", "problem.toml: [target]:",
                     ["give surface or surfaces or labels or landmarks"]),
    "no target for estimate": ({"target": DROP}, (), "estimate", "problem.toml: [target]:", ["missing"]),
    "surfaces empty": ({"target": {"surface": DROP, "surfaces": {}}}, (), "estimate", "problem.toml: [target.surfaces]:",
                       ["got none"]),
    "surfaces not files": ({"target": {"surface": DROP, "surfaces": {"outline": 1}}}, (), "estimate",
                           "problem.toml: target.surfaces.outline:", ["expected a surface file"]),
    "target key typo": ({"target": {"surfac": "t.vtp"}}, (), "estimate", "problem.toml: target.surfac:",
                        ["did you mean surface?"]),
    "landmark_weight 0": ({"target": {"landmark_weight": 0}}, (), "estimate", "problem.toml: target.landmark_weight:",
                          ["expected a number > 0, got 0"]),
    "noise negative": ({"target": {"noise": -0.1}}, (), "estimate", "problem.toml: target.noise:", ["got -0.1"]),
    "smooth unknown": ({"target": {"smooth": "yes"}}, (), "estimate", "problem.toml: target.smooth:", ["auto", "off"]),
    # several states: a list's item is named by its index (these ended in a TypeError)
    "state's force on a group not loaded": ({"target": DROP, "states": [
        {"name": "a", "target": {"surface": "a.vtp"}, "measured_force": {"feet": {"value": [0.0, 1.0], "noise": 0.1}}},
        {"name": "b", "target": {"surface": "b.vtp"}}]}, (), "estimate", "problem.toml: states[0].measured_force.feet:",
        ["not in boundary.loaded", '("top")']),  # the loaded groups listed
    "measured force on a misspelt group": ({"boundary": {"measured_force": {"topp": {"value": [0.0, 1.0], "noise": 0.1}}}},
                                           (), "estimate", "problem.toml: boundary.measured_force.topp:",
                                           ['not in boundary.loaded (did you mean "top"?)']),
    "state's key typo": ({"target": DROP, "states": [{"name": "a", "target": {"surface": "a.vtp"}},
                                                      {"name": "b", "target": {"surface": "b.vtp"}, "measured_forc": {}}]},
                         (), "estimate", "problem.toml: [states[1].measured_forc]:", ["did you mean [states[1].measured_force]?"]),
    # optimizer
    "optimizer a number": ({"optimizer": 5}, (), "estimate", "problem.toml: optimizer:", ["expected a table, got 5"]),
    "optimizer typo": ({"optimiser": {"scan": 3}}, (), "estimate", "problem.toml: [optimiser]:",
                       ["unknown table", "did you mean [optimizer]?"]),
    "scan a string": (OPT(scan="5"), (), "estimate", "problem.toml: optimizer.scan:",
                      ['expected an integer >= 1, got "5" (a string)']),
    "scan 0": (OPT(scan=0), (), "estimate", "problem.toml: optimizer.scan:", ["expected an integer >= 1, got 0"]),
    "scan -2": (OPT(scan=-2), (), "estimate", "problem.toml: optimizer.scan:", ["got -2"]),
    "scan a float": (OPT(scan=2.0), (), "estimate", "problem.toml: optimizer.scan:", ["got 2.0 (a number)"]),
    "outer_xtol -1": (OPT(outer_xtol=-1), (), "estimate", "problem.toml: optimizer.outer_xtol:", ["expected a number > 0, got -1"]),
    "inner_maxiter 0": (OPT(inner_maxiter=0), (), "estimate", "problem.toml: optimizer.inner_maxiter:", ["got 0"]),
    "outer_maxiter a bool": (OPT(outer_maxiter=True), (), "estimate", "problem.toml: optimizer.outer_maxiter:", ["(a boolean)"]),
    "inner_tol 1": (OPT(inner_tol=1), (), "estimate", "problem.toml: optimizer.inner_tol:", ["in (0, 1), got 1"]),
    "full_gn_limit -1": (OPT(full_gn_limit=-1), (), "estimate", "problem.toml: optimizer.full_gn_limit:", ["integer >= 0"]),
    "anchor -1": (OPT(anchor=-1e-3), (), "estimate", "problem.toml: optimizer.anchor:", ["number >= 0, got -0.001"]),
    "surrogate a string": (OPT(surrogate="yes"), (), "estimate", "problem.toml: optimizer.surrogate:", ['got "yes"']),
    "allow_undetermined 1": (OPT(allow_undetermined=1), (), "estimate", "problem.toml: optimizer.allow_undetermined:",
                             ["got 1 (an integer)"]),
    "inner unknown": (OPT(inner="gn"), (), "estimate", "problem.toml: optimizer.inner:", ['"gauss-newton"', 'got "gn"']),
    "inner typo": (OPT(inner="lbgfs"), (), "estimate", "problem.toml: optimizer.inner:", ['did you mean "lbfgs"?']),
    # reduction, solver
    "reduction typo": ({"reducton": {"bases": "b.npz"}}, (), "estimate", "problem.toml: [reducton]:",
                       ["did you mean [reduction]?"]),
    "reduction.bases a number": ({"reduction": {"bases": 5}}, (), "estimate", "problem.toml: reduction.bases:", ["got 5"]),
    "reduction without bases": ({"reduction": {"rank": 5}}, (), "estimate", "problem.toml: reduction.bases:", ["missing"]),
    "reduction.rank 0": ({"reduction": {"bases": "b.npz", "rank": 0}}, (), "estimate", "problem.toml: reduction.rank:",
                         ["integer >= 1, got 0"]),
    "reduction with lbfgs": ({"reduction": {"bases": "b.npz"}, "optimizer": {"inner": "lbfgs"}}, (), "estimate",
                             "problem.toml: optimizer.inner:", ['reduced bases need "gauss-newton"']),
    "solver method": ({"solver": {"method": "lu"}}, (), "estimate", "problem.toml: solver.method:", ['"direct"', 'got "lu"']),
    "solver rtol 0": ({"solver": {"rtol": 0}}, (), "estimate", "problem.toml: solver.rtol:", ["in (0, 1), got 0"]),
    "solver factor": ({"solver": {"factor": "ldl"}}, (), "estimate", "problem.toml: solver.factor:", ['"cholesky"', 'got "ldl"']),
    "solver blr": ({"solver": {"blr": 0.1}}, (), "estimate", "problem.toml: solver.blr:", ["block low-rank", "got 0.1"]),
    "solver blr a word": ({"solver": {"blr": "fast"}}, (), "estimate", "problem.toml: solver.blr:",
                          ['"auto" or a block low-rank tolerance', 'got "fast"']),
    "solver typo": ({"solvr": {}}, (), "estimate", "problem.toml: [solvr]:", ["did you mean [solver]?"]),
    "one line for a key with a newline": ({"materials": {"letter": {"n\nu": 0.3}}}, (), "estimate",
                                          'problem.toml: materials.letter."n\\nu":', ["unknown key"]),
    # --set
    "--set replaces a table": ({}, ["boundary=x"], "estimate", "problem.toml (--set 'boundary=x'): boundary:",
                               ['expected a table, got "x" (a string)']),
    "--set key typo": ({}, ["materials.letter.nuu=0.3"], "estimate",
                       "problem.toml (--set 'materials.letter.nuu=0.3'): materials.letter.nuu:", ["did you mean nu?"]),
    "--set table typo": ({}, ["optimiser.scan=3"], "estimate", "problem.toml (--set 'optimiser.scan=3'): [optimiser]:",
                         ["did you mean [optimizer]?"]),
    "--set material typo": ({}, ["materials.lettr.nu=0.3"], "estimate", "problem.toml (--set 'materials.lettr.nu=0.3'): "
                            "materials.lettr:", ["did you mean letter?"]),
    "--set bad value": ({}, ["optimizer.scan=0"], "estimate", "problem.toml (--set 'optimizer.scan=0'): optimizer.scan:",
                        ["got 0"]),
    "--set bare string": ({}, ["optimizer.scan=5x"], "estimate", "problem.toml (--set 'optimizer.scan=5x'): optimizer.scan:",
                          ['got "5x" (a string)']),
    "--set inside a string": ({}, ["plane.x=1"], "estimate", "problem.toml (--set 'plane.x=1'): plane:", ["not a table"]),
    "--set inside a leaf": ({}, ["degree.x=1"], "estimate", "problem.toml (--set 'degree.x=1'): degree:", ["has no key x"]),
    "--set no =": ({}, ["plane"], "estimate", "--set 'plane':", ["expected KEY=VALUE"]),
    "--set no key": ({}, ["=3"], "estimate", "--set '=3':", ["expected KEY=VALUE"]),
    "--set empty key part": ({}, ["optimizer..scan=3"], "estimate", "--set 'optimizer..scan=3':", ["expected KEY=VALUE"]),
    "--set two lines": ({}, ["optimizer.scan=1\nmesh='x'"], "estimate", "problem.toml (--set", ["optimizer.scan:", r"\n"]),
}


@pytest.mark.parametrize("case", list(BAD_PROBLEMS))
def test_bad_problem_is_one_line_naming_the_key(case):
    patch, overrides, command, start, parts = BAD_PROBLEMS[case]
    text = message(lambda: problem(patch, overrides, command))
    assert text.startswith(start), text
    for part in parts:
        assert part in text, text


def test_many_bad_inputs_covered():
    assert len(BAD_PROBLEMS) >= 40


def test_defaults_filled():
    config, warnings = validate_problem({"mesh": "m.msh", "materials": {"a": {"E": 1, "nu": 0.3}},
                                         "boundary": {"fixed": "f", "load": {"l": [0, 1]}}}, command="simulate")
    assert warnings == []
    assert config == {
        "mesh": "m.msh", "plane": "strain", "degree": 2, "curve": "auto", "units": None,
        "materials": {"a": {"E": {"value": 1.0, "estimate": False, "bounds": None},
                            "nu": {"value": 0.3, "estimate": False, "bounds": None}}},
        "boundary": {"fixed": ["f"], "loaded": [], "matched": [], "match_nodes": "auto",
                     "displacement": {}, "load": {"l": [0.0, 1.0]}, "pressure": {}, "measured_force": {}},
        "target": None,
        "states": None,
        "optimizer": {"inner": "auto", "inner_maxiter": 400, "outer_maxiter": 40, "outer_xtol": 1e-3, "scan": 5,
                      "inner_tol": 1e-6, "full_gn_limit": 1500, "anchor": 1e-4, "surrogate": True, "matched_motion": "auto", "state_noise": "residual",
                      "allow_undetermined": False},
        "uncertainty": {"mesh": "auto", "source_voxels": None},
        "reduction": None,
        "solver": {"method": "auto", "rtol": 1e-8, "factor": "lu", "blr": "auto"},
    }
    assert isinstance(config["materials"]["a"]["E"]["value"], float)


def test_default_bounds_of_estimated_constants():
    config, _ = problem({"materials": {"letter": {"E": {"estimate": True, "value": 30}, "nu": {"estimate": True, "initial": 0.2}}}})
    assert config["materials"]["letter"]["E"] == {"value": 30.0, "estimate": True, "bounds": [1.5, 600.0]}
    assert config["materials"]["letter"]["nu"] == {"value": 0.2, "estimate": True, "bounds": [0.0, 0.499]}


def test_estimate_ignores_simulate_only_tables_with_a_warning():
    patch = {"boundary": {"load": {"top": [0.0, -1.0]}}}
    for command in ("estimate", "train"):
        config, warnings = problem(patch, command=command)
        assert config["boundary"]["displacement"] == {} and config["boundary"]["load"] == {}
        assert warnings == [f"problem.toml: boundary.{key} is used by simulate only; {command} ignores it"
                            for key in ("displacement", "load")]
    config, warnings = problem(patch, command="simulate")
    assert warnings == [] and config["boundary"]["displacement"]["top"]["value"] == [0.4, -0.8]


def test_overrides():
    config, _ = problem(overrides=["materials.letter.nu=0.25", "target.surface=../truth/surface.vtp",
                                   "boundary.fixed=['feet', 'top']", "boundary.loaded=[]", "optimizer.surrogate=false"],
                        command="simulate")
    assert config["materials"]["letter"]["nu"] == {"value": 0.25, "estimate": False, "bounds": None}
    assert config["target"]["surface"] == "../truth/surface.vtp"
    assert config["boundary"]["fixed"] == ["feet", "top"] and config["optimizer"]["surrogate"] is False


def test_override_of_one_alternative_drops_the_other():
    config, _ = problem({"target": {"surface": DROP, "surfaces": {"outline": "o.vtp"}}}, ["target.surface=t.vtp"])
    assert config["target"]["surface"] == "t.vtp" and config["target"]["surfaces"] is None
    config, _ = problem(overrides=["materials.letter.nu.value=0.2"])  # alias of initial
    assert config["materials"]["letter"]["nu"]["value"] == 0.2


def test_override_estimates_a_fixed_constant_from_its_value():
    config, _ = problem(overrides=["materials.letter.E.estimate=true"])
    assert config["materials"]["letter"]["E"] == {"value": 10.0, "estimate": True, "bounds": [0.5, 200.0]}


def test_override_can_add_a_named_table():
    config, _ = problem(overrides=["materials.inclusion={E = 30, nu = 0.3}", "boundary.displacement.side.scale=0.1"],
                        command="simulate")
    assert config["materials"]["inclusion"]["E"]["value"] == 30.0
    assert config["boundary"]["displacement"]["side"] == {"value": None, "scale": 0.1, "gradient": None, "center": None,
                                                          "ripple": None}


def test_parse_override():
    assert parse_override("materials.prostate.E=50") == (["materials", "prostate", "E"], 50)
    assert parse_override(" a.b = [1, 2.5] ") == (["a", "b"], [1, 2.5])
    assert parse_override("a=true") == (["a"], True)
    assert parse_override("a='x=y'") == (["a"], "x=y")
    assert parse_override("a=../t.vtp") == (["a"], "../t.vtp")


def test_normalised_config_validates_to_itself():
    """So a scene can keep the normalised config and apply more --set to it."""
    config, _ = problem({"reduction": {"bases": "b.npz"}, "target": {"landmarks": "l.csv", "noise": 0.1}}, command="estimate")
    again, _ = validate_problem(copy.deepcopy(config), command="estimate")
    assert again == config
    apply_overrides(config, ["materials.letter.nu.initial=0.2"], PROBLEM)
    assert validate_problem(config)[0]["materials"]["letter"]["nu"]["value"] == 0.2


def test_check_gdim():
    config, _ = problem(command="simulate")
    check_gdim(config, 2, "p.toml")
    assert message(lambda: check_gdim(config, 3, "p.toml")) == (
        "p.toml: boundary.displacement.top.value: expected size 3 (the mesh is 3D), got 2")


def test_unknown_command_is_a_programming_error():
    with pytest.raises(ValueError):
        problem(command="simulat")


TEMPLATES = {  # meshes/*.toml, filled as meshing.py fills them
    "letter A": ("letter_a.toml", {}),
    "cantilever": ("cantilever.toml", {}),
    "inclusion": ("inclusion.toml", {}),
    "phantom": ("phantom.toml", {"inflation": 0.1, "inflation_percent": "10%", "cx": 0.0, "cy": -0.3, "cz": 2.6}),
}


def template(name: str) -> str:
    from string import Template

    file, values = TEMPLATES[name]
    return Template((meshing.GEO_DIR / file).read_text()).substitute(values)


@pytest.mark.parametrize("name", list(TEMPLATES))
def test_builtin_problem_files_validate(tmp_path, name):
    path = tmp_path / "problem.toml"
    path.write_text(template(name))
    assert read_problem(path, command="simulate")[1] == []
    if name == "cantilever":  # a forward scene: no target
        assert "[target]: missing" in message(lambda: read_problem(path, command="estimate"))
        return
    _, warnings = read_problem(path, command="estimate")
    assert warnings == [f"{path}: boundary.displacement is used by simulate only; estimate ignores it"]


def test_files(tmp_path):
    path = tmp_path / "problem.toml"
    assert message(lambda: read_problem(path)) == f"{path}: no such problem file"
    path.write_text("mesh = [")
    assert message(lambda: read_problem(path)).startswith(f"{path}: not valid TOML")
    path.write_text(template("letter A"))
    config, _ = read_problem(path, ["optimizer.scan=3"], command="estimate")
    assert config["optimizer"]["scan"] == 3
    assert message(lambda: read_problem(path, ["optimizer.scan=0"])).startswith(
        f"{path} (--set 'optimizer.scan=0'): optimizer.scan: expected an integer >= 1, got 0")


# --------------------------------------------------------------------------- scene spec

SPEC = {
    "units": "mm", "size": 6.0,
    "body": {"surface": "kidney.vtk"},
    "regions": {"prostate": {"surface": "prostate.stl"}},
    "cavities": {"bladder": {"surface": "bladder.stl"}},
    "patches": {"bones": {"side": {"point": [0.0, -40.0, 0.0], "normal": [0.0, -1.0, 0.0]}}},
}


def spec(patch=None, overrides=()):
    raw = patched(SPEC, patch or {})
    return validate_scene_spec(raw, "scene.toml", apply_overrides(raw, overrides, SCENE_SPEC, "scene.toml"))


def SIDE(**keys):
    return {"patches": {"bones": {"side": keys}}}


BAD_SPECS = {
    "units": ({"units": "inch"}, (), "scene.toml: units:", ['"mm", "cm", "m"', 'got "inch"']),
    "size 0": ({"size": 0}, (), "scene.toml: size:", ["number > 0, got 0"]),
    "organ_size a string": ({"organ_size": "2"}, (), "scene.toml: organ_size:", ['got "2" (a string)']),
    "no body": ({"body": DROP}, (), "scene.toml: [body]:", ["missing"]),
    "body of two shapes": ({"body": {"box": {"margin": 2}}}, (), "scene.toml: [body]:", ["surface or box, not both"]),
    "body of none": ({"body": {"surface": DROP}}, (), "scene.toml: [body]:", ["surface or label or box or ellipsoid"]),
    "box margin 0": ({"body": {"surface": DROP, "box": {"margin": 0}}}, (), "scene.toml: body.box.margin:", ["got 0"]),
    "box without margin": ({"body": {"surface": DROP, "box": {}}}, (), "scene.toml: body.box.margin:", ["missing"]),
    "box around nothing": ({"body": {"surface": DROP, "ellipsoid": {"margin": 2}}, "regions": DROP, "cavities": DROP}, (),
                           "scene.toml: body.ellipsoid:", ["there are none"]),
    "body typo": ({"body": {"materiel": "fat"}}, (), "scene.toml: body.materiel:", ["did you mean material?"]),
    "region typo": ({"region": {}}, (), "scene.toml: [region]:", ["did you mean [regions]?"]),
    "region without files": ({"regions": {"prostate": {"surface": []}}}, (), "scene.toml: regions.prostate.surface:",
                             ["at least one surface file"]),
    "region material key": ({"regions": {"prostate": {"material": "x"}}}, (), "scene.toml: regions.prostate.material:",
                            ["unknown key"]),
    "cavity of two files": ({"cavities": {"bladder": {"surface": ["a", "b"]}}}, (), "scene.toml: cavities.bladder.surface:",
                            ["expected a surface file"]),
    "bad group name": ({"cavities": {"my bladder": {"surface": "b.stl"}}}, (), 'scene.toml: cavities."my bladder":',
                       ["expected a group name"]),
    "numeric group name": ({"patches": {"3": {"side": {"point": [0, 0, 0], "normal": [1, 0, 0]}}}}, (),
                           "scene.toml: patches.3:", ["starting with a letter"]),
    "patch named outer": ({"patches": {"outer": {"side": {"point": [0, 0, 0], "normal": [1, 0, 0]}}}}, (),
                          "scene.toml: patches.outer:", ["clashes with the body's outer boundary"]),
    "patch named like a region surface": ({"patches": {"prostate_surface": {"side": {"point": [0, 0, 0], "normal": [1, 0, 0]}}}},
                                          (), "scene.toml: patches.prostate_surface:", ["facet group of regions.prostate"]),
    "cavity named like a region": ({"cavities": {"prostate": {"surface": "p.stl"}}}, (), "scene.toml: cavities.prostate:",
                                   ["clashes with the cell group of regions.prostate"]),
    "region named like the body": ({"body": {"material": "prostate"}}, (), "scene.toml: regions.prostate:",
                                   ["cell group of body.material"]),
    "normal zero": (SIDE(point=[0, 0, 0], normal=[0, 0, 0]), (), "scene.toml: patches.bones.side.normal:", ["nonzero"]),
    "point 2D": (SIDE(point=[0, 0], normal=[0, 0, 1]), (), "scene.toml: patches.bones.side.point:", ["3-vector"]),
    "side missing": ({"patches": {"bones": {"side": DROP}}}, (), "scene.toml: [patches.bones.side]:", ["missing"]),
    "--set replaces body": ({}, ["body=kidney.vtk"], "scene.toml (--set 'body=kidney.vtk'): body:", ["expected a table"]),
    "--set key typo": ({}, ["body.surfce=k.vtk"], "scene.toml (--set 'body.surfce=k.vtk'): body.surfce:",
                       ["did you mean surface?"]),
}


@pytest.mark.parametrize("case", list(BAD_SPECS))
def test_bad_scene_spec_is_one_line_naming_the_key(case):
    patch, overrides, start, parts = BAD_SPECS[case]
    text = message(lambda: spec(patch, overrides))
    assert text.startswith(start), text
    for part in parts:
        assert part in text, text


def test_scene_spec_defaults(tmp_path):
    path = tmp_path / "scene.toml"
    path.write_text('[body]\nbox = { margin = 20.0 }\n[regions.prostate]\nsurface = "p.stl"\n')
    assert read_scene_spec(path, ["body.box.margin=10"]) == {
        "units": "mm", "size": None, "organ_size": None, "labels": None,
        "body": {"surface": None, "label": None, "box": {"margin": 10.0}, "ellipsoid": None, "material": "tissue"},
        "regions": {"prostate": {"surface": ["p.stl"], "label": None}}, "cavities": {}, "patches": {},
    }
    assert spec(overrides=["body.box={margin=5}"])["body"]["surface"] is None  # one shape replaces the other


def test_target_forms():
    landmarks_only, _ = problem({"target": {"surface": DROP, "landmarks": "l.csv"}})
    assert landmarks_only["target"] == {"surface": None, "surfaces": None, "landmarks": "l.csv",
                                        "landmark_weight": None, "landmark_noise": None, "labels": None, "noise": None,
                                        "smooth": "auto", "displacement": None, "displacement_noise": None,
                                        "displacement_correlation": None, "displacement_frame": None}
    per_group, _ = problem({"target": {"surface": DROP, "surfaces": {"outline": "o.vtp"}, "landmarks": "l.csv",
                                       "landmark_weight": 2, "noise": 0.05}})
    assert per_group["target"]["surfaces"] == {"outline": "o.vtp"} and per_group["target"]["landmark_weight"] == 2.0


def test_toml_text_reads_back_as_written():
    """What toml_text writes, tomllib reads back equal: nested and empty tables, inline
    tables in arrays, matrices, inf, quotes, backslashes, non-ASCII and dotted keys."""
    import tomllib

    data = patched(BASE, {"boundary": {"displacement": {"top": {"gradient": [[0.1, 0.0], [0.0, -2e-5]]}}},
                          "target": {"surfaces": {"out line": 'a "b"\\c\u00fc.vtp'}, "surface": DROP},
                          "optimizer": {}, "x": {"y": [{"z": 1}], "w": math.inf, "flag": False}})
    assert tomllib.loads(toml_text(data)) == data


def test_a_rule_of_the_whole_file_names_no_empty_table():
    """'give target or states, not both' concerns the whole file: it read 'p.toml: []: give ...'."""
    from fenics_elasto.config.schema import Where
    from fenics_elasto.util.errors import UserError

    with pytest.raises(UserError) as refusal:
        Where("p.toml").fail("give target or states, not both", table=True)
    assert str(refusal.value) == "p.toml: give target or states, not both"


def test_a_force_inside_a_target_says_where_it_goes(tmp_path):
    """A state's force written inside its target (as fe.Target takes it) read 'unknown
    table; known keys: ...'; the line says where a measured force belongs."""
    from fenics_elasto.config.schema import Where
    from fenics_elasto.config.problem import TARGET
    from fenics_elasto.util.errors import UserError

    with pytest.raises(UserError, match=r"not a key of this table: a measured force goes in \[boundary.measured_force"):
        TARGET.check({"surface": "s.vtp", "measured_force": {"top": {"value": [0, 1], "noise": 0.1}}},
                     Where("p.toml", ("states", 0, "target")))
