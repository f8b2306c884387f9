"""The catalogue: bad and edge inputs through every command, each refused in one line.

Every row runs the real command line in this process (``fenics_elasto.cli.main``) and
asserts the contract: exit status 2 and exactly one line on stderr -- ``error: ...``
naming the culprit (the file, the key or the group: the row's words) -- or exit 0
with the row's ``warning: ...`` line. stderr is captured at the file-descriptor level,
so a VTK or gmsh message printed from C before the error line fails the row too. A
fault in the input files must be found before the work: each row gets 10 s (loose,
for a busy machine; most take well under one); the slowest are listed at the end.

Kinds of rows: the mesh and scene commands (sizes, seeds, atlases, surface files),
problem files and --set overrides (the schema, through the CLI), meshes gmsh reads
but DOLFINx must not get (catalogue_files.py), targets, landmarks and bases, train's
examples, render's folders, output places (an existing file, /proc, /dev/full, a
read-only tmpfs, a busy folder). Subprocesses only where a row needs one: MPI, and
signals through the real CLI at the end of the file.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from collections.abc import Callable

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import catalogue_files as files  # noqa: E402
from conftest import BIN, run_cli  # noqa: E402
from fenics_elasto.app.cli import main  # noqa: E402

LIMIT_S = 10.0
TIMES: dict[str, float] = {}


@dataclass
class Case:
    """A row: ``argv(env)`` builds the command line; ``words`` must be in the output line."""

    id: str
    argv: Callable
    words: tuple = ()
    warning: bool = False  # exit 0 with a warning line instead of exit 2 with an error line


def case(id, argv, *words, warning=False):
    return pytest.param(Case(id, argv, words, warning), id=id)


class Env:
    """Paths the rows use: built-in scenes, a simulated letter A, bad files."""

    def __init__(self, root: Path, scenes: dict):
        self.root, self.scenes = root, scenes
        self.letter, self.phantom, self.cantilever = scenes["letter-a"], scenes["prostate-phantom"], scenes["cantilever"]
        self.bad = root / "bad"
        self.bad.mkdir()
        self.n = 0

    def out(self) -> Path:
        self.n += 1
        return self.root / "out" / f"o{self.n}"

    def problem(self, name: str, edit: Callable[[str], str], scene: str = "letter-a") -> Path:
        """A copy of a built-in scene's problem.toml, edited, beside its mesh."""
        source = self.scenes[scene]
        path = source.parent / f"catalogue_{name}.toml"
        path.write_text(edit(source.read_text()))
        return path

    def simulate(self, problem, *sets):
        return ["simulate", problem, "--out", self.out(), *[a for s in sets for a in ("--set", s)]]

    def estimate(self, *sets, problem=None):
        target = f"target.surface='{self.truth / 'surface.vtp'}'"
        return ["estimate", problem or self.letter, "--out", self.out(), "--set", target,
                *[a for s in sets for a in ("--set", s)]]

    def target(self, path) -> list:
        return ["estimate", self.letter, "--out", self.out(), "--set", f"target.surface='{path}'"]

    def train(self, *examples, rank=1, problem=None, out=None):
        return ["train", problem or self.letter, "--examples", *examples, "--rank", rank, "--out", out or self.out() / "b.npz"]


@pytest.fixture(scope="module")
def env(scenes, tmp_path_factory, request):
    from fenics_elasto.app.commands import run_simulate, run_train

    e = Env(tmp_path_factory.mktemp("catalogue"), scenes)
    e.truth = e.root / "truth"
    run_simulate(e.letter, e.truth, ["materials.letter.nu=0.25"])
    e.bases = e.root / "bases.npz"
    run_train([(e.letter, [e.truth])], e.bases, 1)
    e.cubes = files.bad_cubes(e.bad / "cubes")
    yield e
    slowest = sorted(TIMES.items(), key=lambda item: -item[1])[:8]
    reporter = request.config.pluginmanager.get_plugin("terminalreporter")
    if reporter is not None:
        reporter.write_line(f"\ncatalogue: {len(TIMES)} rows, {sum(TIMES.values()):.1f} s; slowest: "
                            + ", ".join(f"{name} {seconds:.2f} s" for name, seconds in slowest))


def run(case: Case, argv, capfd) -> str:
    start = time.perf_counter()
    code = main([str(a) for a in argv])
    TIMES[case.id] = time.perf_counter() - start
    out, err = capfd.readouterr()
    lines = err.strip().splitlines()
    if case.warning:
        assert code == 0, err
        assert any(line.startswith("warning: ") and all(w in line for w in case.words) for line in lines), err
        return err
    assert code == 2, (out, err)
    assert len(lines) == 1 and lines[0].startswith("error: "), err  # one line, nothing printed before it
    if os.environ.get("CATALOGUE_LINES"):
        with open(os.environ["CATALOGUE_LINES"], "a") as f:
            f.write(f"{case.id}: {lines[0]}\n")
    for word in case.words:
        assert str(word) in lines[0], lines[0]
    assert TIMES[case.id] < LIMIT_S, f"{case.id}: {TIMES[case.id]:.1f} s to refuse"
    return lines[0]


# =========================================================================== mesh

MESH = [
    case("mesh-unknown-scene", lambda e: ["mesh", "teapot", "--out", e.out()], "teapot", "letter-a"),
    case("mesh-size-zero", lambda e: ["mesh", "letter-a", "--out", e.out(), "--size", 0], "--size"),
    case("mesh-size-negative", lambda e: ["mesh", "cantilever", "--out", e.out(), "--size", -0.5], "--size"),
    case("mesh-size-nan", lambda e: ["mesh", "letter-a", "--out", e.out(), "--size", "nan"], "--size", "nan"),
    case("mesh-size-inf", lambda e: ["mesh", "letter-a", "--out", e.out(), "--size", "inf"], "--size", "inf"),
    case("mesh-size-1e-4-memory", lambda e: ["mesh", "letter-a", "--out", e.out(), "--size", 1e-4],
         "letter-a --size 0.0001", "triangles", "GB", "available"),
    case("mesh-size-1e-3-memory", lambda e: ["mesh", "letter-a", "--out", e.out(), "--size", 1e-3],
         "letter-a --size 0.001", "use a size >="),
    case("mesh-inclusion-tiny", lambda e: ["mesh", "inclusion", "--out", e.out(), "--size", 1e-4], "inclusion", "GB"),
    case("mesh-cantilever-tiny", lambda e: ["mesh", "cantilever", "--out", e.out(), "--size", 2e-4], "cantilever", "GB"),
    case("mesh-phantom-memory", lambda e: ["mesh", "prostate-phantom", "--out", e.out(), "--size", 0.05],
         "prostate-phantom --size 0.05", "tetrahedra", "GB"),
    case("mesh-phantom-coarse-3", lambda e: ["mesh", "prostate-phantom", "--out", e.out(), "--size", 3],
         "prostate-phantom --size 3", "rectum", "--size <="),
    case("mesh-phantom-coarse-10", lambda e: ["mesh", "prostate-phantom", "--out", e.out(), "--size", 10], "do not resolve"),
    case("mesh-phantom-coarse-organs", lambda e: ["mesh", "prostate-phantom", "--out", e.out(), "--size", 1.6,
                                                  "--organ-size", 0.9], "--organ-size"),
    case("mesh-phantom-coarse-prostate", lambda e: ["mesh", "prostate-phantom", "--out", e.out(), "--size", 2.4,
                                                    "--organ-size", 0.3, "--prostate-size", 1.0], "prostate"),
    case("mesh-seed-negative", lambda e: ["mesh", "prostate-phantom", "--out", e.out(), "--seed", -1], "--seed", "-1"),
    case("mesh-seed-letter", lambda e: ["mesh", "letter-a", "--out", e.out(), "--seed", 3], "--seed", "prostate-phantom"),
    case("mesh-organ-size-letter", lambda e: ["mesh", "letter-a", "--out", e.out(), "--organ-size", 0.2], "--organ-size"),
    case("mesh-organ-size-zero", lambda e: ["mesh", "prostate-phantom", "--out", e.out(), "--organ-size", 0], "--organ-size"),
    case("mesh-organ-size-above-1", lambda e: ["mesh", "prostate-phantom", "--out", e.out(), "--organ-size", 1.5],
         "--organ-size"),
    case("mesh-prostate-size-nan", lambda e: ["mesh", "prostate-phantom", "--out", e.out(), "--prostate-size", "nan"],
         "--prostate-size"),
    case("mesh-atlas-letter", lambda e: ["mesh", "letter-a", "--out", e.out(), "--atlas", e.phantom.parent / "phantom.msh"],
         "--atlas"),
    case("mesh-atlas-missing", lambda e: ["mesh", "prostate-phantom", "--out", e.out(), "--atlas", e.bad / "none.msh"],
         "none.msh"),
    case("mesh-atlas-garbage-text", lambda e: ["mesh", "prostate-phantom", "--out", e.out(), "--atlas",
                                               files.text(e.bad / "garbage.msh", "garbage\n")], "garbage.msh"),
    case("mesh-atlas-binary", lambda e: ["mesh", "prostate-phantom", "--out", e.out(), "--atlas",
                                         files.garbage(e.bad / "binary.msh")], "binary.msh"),
    case("mesh-atlas-empty", lambda e: ["mesh", "prostate-phantom", "--out", e.out(), "--atlas",
                                        files.text(e.bad / "empty.msh", "")], "empty.msh"),
    case("mesh-atlas-2d", lambda e: ["mesh", "prostate-phantom", "--out", e.out(), "--atlas",
                                     e.letter.parent / "letter_a.msh"], "letter_a.msh", "3D"),
    case("mesh-atlas-truncated", lambda e: ["mesh", "prostate-phantom", "--out", e.out(), "--atlas",
                                            files.truncated(e.phantom.parent / "phantom.msh", e.bad / "half.msh")],
         "half.msh"),
    case("mesh-atlas-without-bladder", lambda e: ["mesh", "prostate-phantom", "--out", e.out(), "--atlas",
                                                  e.cubes["good"].with_suffix(".msh")], "good.msh", "bladder"),
    case("mesh-atlas-off-mesh-group", lambda e: ["mesh", "prostate-phantom", "--out", e.out(), "--atlas",
                                                 e.cubes["off_mesh"].with_suffix(".msh")], "off_mesh.msh", "sides"),
]


@pytest.mark.parametrize("row", MESH)
def test_mesh(env, capfd, row):
    run(row, row.argv(env), capfd)


# =========================================================================== problem files and --set


def letter_set(*sets):
    return lambda e: e.simulate(e.letter, *sets)


SCHEMA = [
    case("set-E-zero", letter_set("materials.letter.E=0.0"), "materials.letter.E", "Young"),
    case("set-E-negative", letter_set("materials.letter.E=-3"), "materials.letter.E"),
    case("set-E-string", letter_set("materials.letter.E='stiff'"), "materials.letter.E", "string"),
    case("set-E-nan", letter_set("materials.letter.E=nan"), "materials.letter.E", "nan"),
    case("set-E-inf", letter_set("materials.letter.E=inf"), "materials.letter.E"),
    case("set-E-bool", letter_set("materials.letter.E=true"), "materials.letter.E", "boolean"),
    case("set-nu-half", letter_set("materials.letter.nu=0.5"), "materials.letter.nu", "Poisson"),
    case("set-nu-minus-one", letter_set("materials.letter.nu=-1"), "materials.letter.nu"),
    case("set-nu-bounds-above", letter_set("materials.letter.nu={estimate=true, initial=0.3, bounds=[0.1, 0.6]}"),
         "materials.letter.nu.bounds"),
    case("set-nu-bounds-reversed", letter_set("materials.letter.nu={estimate=true, initial=0.3, bounds=[0.4, 0.1]}"),
         "low < high"),
    case("set-nu-initial-outside", letter_set("materials.letter.nu={estimate=true, initial=0.3, bounds=[0.35, 0.4]}"),
         "outside bounds"),
    case("set-nu-no-initial", letter_set("materials.letter.nu={estimate=true}"), "materials.letter.nu.initial"),
    case("set-nu-typo-key", letter_set("materials.letter.nu={estimate=true, inital=0.3}"), "inital", "initial"),
    case("set-material-typo", letter_set("materials.leter.E=3"), "leter", "letter"),
    case("set-material-unknown-group", letter_set("materials.bone={E=1.0, nu=0.3}"), "materials.bone", "cell group"),
    case("set-material-missing-nu", letter_set("materials.letter={E=1.0}"), "materials.letter.nu", "missing"),
    case("set-materials-empty", letter_set("materials={}"), "materials"),
    case("set-degree-3", letter_set("degree=3"), "degree"),
    case("set-degree-string", letter_set("degree='2'"), "degree"),
    case("set-plane-typo", letter_set("plane='strian'"), "plane", "strain"),
    case("set-unknown-top-key", letter_set("dgree=2"), "dgree", "degree"),
    case("set-unknown-table", letter_set("optimiser.scan=3"), "optimiser", "optimizer"),
    case("set-malformed", letter_set("materials.letter.E"), "KEY=VALUE"),
    case("set-empty-key", letter_set("=3"), "KEY=VALUE"),
    case("set-into-a-number", letter_set("degree.x=1"), "degree"),
    case("set-fixed-unknown-group", letter_set("boundary.fixed=['nope']"), "boundary.fixed", "nope"),
    case("set-fixed-typo", letter_set("boundary.fixed=['fet']"), "fet", "feet"),
    case("set-fixed-and-loaded", letter_set("boundary.loaded=['feet']"), "feet", "fixed"),
    case("set-fixed-loaded-share-facets", letter_set("boundary.loaded=['outline']"), "share"),
    case("set-fixed-twice", letter_set("boundary.fixed=['feet', 'feet']"), "feet", "twice"),
    case("set-fixed-number", letter_set("boundary.fixed=3"), "boundary.fixed"),
    case("set-matched-unknown", letter_set("boundary.matched=['outline', 'hole']"), "hole"),
    case("set-match-nodes-typo", letter_set("boundary.match_nodes='vertex'"), "match_nodes", "vertices"),
    case("set-displacement-3d-in-2d", letter_set("boundary.displacement.top.value=[0.0, 1.0, 2.0]"),
         "boundary.displacement.top.value", "2D"),
    case("set-displacement-unknown-group", letter_set("boundary.displacement={lid={value=[0.0, 1.0]}}"),
         "boundary.displacement", "lid"),
    case("set-displacement-nan", letter_set("boundary.displacement.top.value=[nan, 1.0]"), "boundary.displacement.top.value"),
    case("set-displacement-gradient-size", letter_set("boundary.displacement.top.gradient=[[1.0, 0.0, 0.0]]"),
         "gradient"),
    case("set-ripple-negative", letter_set("boundary.displacement.top.ripple={amplitude=-1.0, length=1.0}"),
         "ripple.amplitude"),
    case("set-ripple-no-length", letter_set("boundary.displacement.top.ripple={amplitude=0.1}"), "ripple.length"),
    case("set-load-wrong-size", letter_set("boundary.displacement={}", "boundary.load={top=[0.0, 1.0, 0.0]}"),
         "boundary.load.top"),
    case("set-load-unknown-group", letter_set("boundary.load={roof=[0.0, 1.0]}"), "roof"),
    case("set-pressure-string", letter_set("boundary.pressure={top='high'}"), "boundary.pressure.top"),
    case("set-nothing-to-simulate", letter_set("boundary.displacement={}"), "nothing to simulate"),
    case("set-nothing-clamped", letter_set("boundary.fixed=[]", "boundary.displacement={}",
                                           "boundary.load={top=[0.0, -1.0]}"), "boundary.fixed"),
    case("set-solver-typo", letter_set("solver.method='drect'"), "solver.method", "direct"),
    case("set-solver-rtol", letter_set("solver.rtol=2.0"), "solver.rtol"),
    case("set-optimizer-inner", lambda e: e.estimate("optimizer.inner='newton'"), "optimizer.inner"),
    case("set-optimizer-scan-zero", lambda e: e.estimate("optimizer.scan=0"), "optimizer.scan"),
    case("set-optimizer-xtol", lambda e: e.estimate("optimizer.outer_xtol=-1e-3"), "optimizer.outer_xtol"),
    case("set-optimizer-maxiter-float", lambda e: e.estimate("optimizer.inner_maxiter=1.5"), "optimizer.inner_maxiter"),
    case("set-target-surface-replaces-surfaces", lambda e: e.estimate("target.surfaces={outline='x.vtp'}",
                                                                      "target.surface='y.vtp'"), "y.vtp"),
    case("set-target-weight", lambda e: e.estimate("target.landmark_weight=0"), "target.landmark_weight"),
    case("set-target-noise", lambda e: e.estimate("target.noise=-1.0"), "target.noise"),
    case("set-reduction-rank-zero", lambda e: e.estimate(f"reduction={{bases='{e.bases}', rank=0}}"), "reduction.rank"),
    case("set-reduction-no-bases", lambda e: e.estimate("reduction={rank=2}"), "reduction.bases"),
    case("set-reduction-inner", lambda e: e.estimate(f"reduction={{bases='{e.bases}'}}", "optimizer.inner='lbfgs'"),
         "gauss-newton"),
    case("problem-missing", lambda e: e.simulate(e.bad / "absent.toml"), "absent.toml"),
    case("problem-not-toml", lambda e: e.simulate(files.text(e.bad / "broken.toml", 'mesh = "x.msh\n')), "broken.toml", "TOML"),
    case("problem-binary", lambda e: e.simulate(files.garbage(e.bad / "binary.toml")), "binary.toml"),
    case("problem-is-a-folder", lambda e: e.simulate(e.bad), "bad", "directory"),
    case("problem-no-mesh-key", lambda e: e.simulate(e.problem("nomesh", lambda t: t.replace('mesh = "letter_a.msh"', ""))),
         "mesh", "missing"),
    case("problem-mesh-missing", lambda e: e.simulate(e.problem("gone", lambda t: t.replace("letter_a.msh", "gone.msh"))),
         "gone.msh"),
    case("problem-region-without-material", lambda e: e.simulate(e.problem(
        "nomat", lambda t: t.replace("[materials.letter]", "[materials.other]"))), "letter"),
    case("problem-every-E-estimated", lambda e: e.estimate(
        "materials.letter.E={estimate=true, initial=10.0}"), "reference"),
    case("problem-nothing-estimated", lambda e: e.estimate("materials.letter.nu=0.3"), "nothing to estimate"),
    case("problem-estimate-without-target", lambda e: ["estimate", e.problem(
        "notarget", lambda t: t[: t.index("[target]")]), "--out", e.out()], "target", "missing"),
    case("problem-estimate-nothing-loaded", lambda e: e.estimate("boundary.loaded=[]"), "boundary.loaded"),
    case("problem-estimate-nothing-matched", lambda e: e.estimate("boundary.matched=[]"), "boundary.matched"),
]


@pytest.mark.parametrize("row", SCHEMA)
def test_problem_files_and_overrides(env, capfd, row):
    run(row, row.argv(env), capfd)


# =========================================================================== meshes

CUBES = ["no_cells", "mixed", "hexahedra", "twice", "flat", "overlap", "crowded", "orphan", "off_mesh", "facet_quads",
         "folded"]
CUBE_WORDS = {"no_cells": ("'body'", "no cells"), "mixed": ("mixed",), "hexahedra": ("Hexahedron", "tetrahedra"),
              "twice": ("more than once",), "flat": ("flat",), "overlap": ("overlap",), "crowded": ("more than two",),
              "orphan": ("no cell",), "off_mesh": ("'sides'", "not facets"), "facet_quads": ("'top'", "Quadrilateral"),
              "folded": ("curved cell(s) fold over",)}


def msh_problem(e, name: str, mesh_path: Path) -> Path:
    """A letter-A problem whose mesh is ``mesh_path``."""
    return e.problem(name, lambda t: t.replace('"letter_a.msh"', f'"{mesh_path}"'))


def edited_letter(e, name: str, edit) -> Path:
    """The letter A's .msh text, edited, and a problem file on it."""
    source = e.letter.parent / "letter_a.msh"
    path = e.bad / f"{name}.msh"
    path.write_text(edit(source.read_text()))
    return msh_problem(e, name, path)


def _nan_node(text: str) -> str:
    lines = text.splitlines()
    start = lines.index("$Nodes")
    row = next(i for i in range(start + 2, len(lines)) if len(lines[i].split()) == 3 and "." in lines[i])
    lines[row] = "nan 0 0"
    return "\n".join(lines) + "\n"


def _lifted(text: str) -> str:
    """Every node's z set to 1 (a 2D mesh off the z = 0 plane)."""
    lines = text.splitlines()
    start, end = lines.index("$Nodes"), lines.index("$EndNodes")
    for i in range(start + 2, end):
        parts = lines[i].split()
        if len(parts) == 3 and "." in lines[i] + ".":
            try:
                x, y, _ = map(float, parts)
            except ValueError:
                continue
            if not lines[i].strip().isdigit():
                lines[i] = f"{x!r} {y!r} 1.0" if any(c in lines[i] for c in ".e") else lines[i]
    return "\n".join(lines) + "\n"


MESHES = [
    pytest.param(Case(f"msh-{name}", lambda e, n=name: e.simulate(e.cubes[n]), (f"{name}.msh",) + CUBE_WORDS[name]),
                 id=f"msh-{name}") for name in CUBES
] + [
    case("msh-truncated-half", lambda e: e.simulate(msh_problem(e, "half", files.truncated(
        e.letter.parent / "letter_a.msh", e.bad / "letter_half.msh"))), "letter_half.msh"),
    case("msh-truncated-90", lambda e: e.simulate(msh_problem(e, "ninety", files.truncated(
        e.letter.parent / "letter_a.msh", e.bad / "letter_90.msh", 0.9))), "letter_90.msh"),
    case("msh-truncated-header", lambda e: e.simulate(msh_problem(e, "header", files.truncated(
        e.letter.parent / "letter_a.msh", e.bad / "letter_header.msh", 0.01))), "letter_header.msh"),
    case("msh-empty", lambda e: e.simulate(msh_problem(e, "emptymsh", files.text(e.bad / "void.msh", ""))), "void.msh"),
    case("msh-binary", lambda e: e.simulate(msh_problem(e, "binmsh", files.garbage(e.bad / "noise.msh"))), "noise.msh"),
    case("msh-text", lambda e: e.simulate(msh_problem(e, "txtmsh", files.text(e.bad / "words.msh", "hello\n"))),
         "words.msh"),
    case("msh-nodes-garbage", lambda e: e.simulate(msh_problem(e, "nodesgarbage", files.text(
        e.bad / "nodes.msh", "$MeshFormat\n4.1 0 8\n$EndMeshFormat\n$Nodes\ngarbage\n"))), "nodes.msh"),
    case("msh-nan-node", lambda e: e.simulate(edited_letter(e, "nan_node", _nan_node)), "nan_node.msh", "NaN"),
    case("msh-2d-off-plane", lambda e: e.simulate(edited_letter(e, "lifted", _lifted)), "lifted.msh", "z = 0"),
    case("msh-no-groups", lambda e: e.simulate(edited_letter(
        e, "nogroups", lambda t: t[: t.index("$PhysicalNames")] + t[t.index("$EndPhysicalNames") + 18:])),
        "nogroups.msh", "no name"),
    case("msh-is-a-stl", lambda e: e.simulate(msh_problem(e, "stlmesh", files.triangles_3d(e.bad)))),
]


@pytest.mark.parametrize("row", MESHES)
def test_meshes_dolfinx_must_not_get(env, capfd, row):
    run(row, row.argv(env), capfd)


@pytest.mark.parametrize("name", ["good", "quadratic"])
def test_the_cube_itself_is_fine(env, capfd, name):
    """The controls of the cube rows: unchanged, it simulates (with 10-node tets too, the
    control of "folded")."""
    assert main(["simulate", str(env.cubes[name]), "--out", str(env.out())]) == 0


@pytest.mark.slow
def test_a_facet_group_off_the_mesh_under_mpi_is_one_line(env):
    """Was MPI_Abort ("Invalid rank") inside DOLFINx's reader, exit 6, no error line."""
    proc = run_cli("simulate", env.cubes["off_mesh"], "--out", env.out(), mpi=2)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().count("\n") == 0 and "off_mesh.msh" in proc.stderr and "'sides'" in proc.stderr


# =========================================================================== targets, landmarks, bases


def landmarks(e, name: str, content: str) -> list:
    path = files.text(e.bad / f"{name}.csv", content)
    return e.estimate(f"target.landmarks='{path}'")


def letter_landmarks(e, rows: int = 3) -> str:
    return "\n".join("1.0, 1.0, 1.1, 1.0" for _ in range(rows)) + "\n"


TARGETS = [
    case("target-missing", lambda e: e.target(e.bad / "nowhere.vtp"), "nowhere.vtp"),
    case("target-empty", lambda e: e.target(files.text(e.bad / "empty.vtp", "")), "empty.vtp"),
    case("target-text", lambda e: e.target(files.text(e.bad / "words.vtp", "not xml\n")), "words.vtp"),
    case("target-truncated", lambda e: e.target(files.truncated(e.truth / "surface.vtp", e.bad / "cut.vtp")), "cut.vtp"),
    case("target-binary-stl", lambda e: e.target(files.garbage(e.bad / "noise.stl")), "noise.stl"),
    case("target-stl-no-facets", lambda e: e.target(files.text(e.bad / "solid.stl", "solid x\nendsolid x\n")), "solid.stl"),
    case("target-unknown-suffix", lambda e: e.target(files.text(e.bad / "shape.xyz", "1 2 3\n")), "shape.xyz"),
    case("target-a-folder", lambda e: e.target(e.bad), "bad", "directory"),
    case("target-3d-for-2d", lambda e: e.target(files.triangles_3d(e.bad)), "sphere.vtp", "2D"),
    case("target-points-only", lambda e: e.target(files.points_only(e.bad)), "points.vtp"),
    case("target-nan", lambda e: e.target(files.moved(e.truth / "surface.vtp", e.bad / "nan.vtp", nan=True)),
         "nan.vtp", "NaN"),
    case("target-far-away", lambda e: e.target(files.moved(e.truth / "surface.vtp", e.bad / "far.vtp", (1000, 0, 0))),
         "overlap"),
    case("target-2d-for-3d", lambda e: ["estimate", e.phantom, "--out", e.out(), "--set",
                                        f"target.surface='{files.surface_lines(e.bad)}'"], "lines.vtp", "3D"),
    case("target-10x", lambda e: e.target(files.moved(e.truth / "surface.vtp", e.bad / "big.vtp", scale=10.0)),
         "big.vtp", "units"),
    case("target-surfaces-unknown-group", lambda e: e.estimate(
        f"target.surfaces={{outline='{e.truth / 'surface.vtp'}', rim='{e.truth / 'surface.vtp'}'}}"), "rim"),
    case("target-surfaces-missing-group", lambda e: e.estimate(
        "boundary.matched=['outline', 'top']", f"target.surfaces={{outline='{e.truth / 'surface.vtp'}'}}"), "top"),
    case("landmarks-missing", lambda e: e.estimate(f"target.landmarks='{e.bad / 'none.csv'}'"), "none.csv"),
    case("landmarks-empty", lambda e: landmarks(e, "lm_empty", ""), "lm_empty.csv", "empty"),
    case("landmarks-header-only", lambda e: landmarks(e, "lm_header", "x0,x1,X0,X1\n"), "lm_header.csv", "header"),
    case("landmarks-a-folder", lambda e: e.estimate(f"target.landmarks='{e.bad}'"), "bad", "directory"),
    case("landmarks-columns", lambda e: landmarks(e, "lm_cols", "1, 2, 3\n4, 5, 6\n"), "lm_cols.csv", "columns"),
    case("landmarks-nan", lambda e: landmarks(e, "lm_nan", "1.0, 1.0, nan, 1.0\n"), "lm_nan.csv", "NaN"),
    case("landmarks-words", lambda e: landmarks(e, "lm_words", "x, y, X, Y\na, b, c, d\n"), "lm_words.csv"),
    case("landmarks-binary", lambda e: e.estimate(f"target.landmarks='{files.garbage(e.bad / 'lm_bin.csv')}'"),
         "lm_bin.csv"),
    case("landmarks-outside", lambda e: landmarks(e, "lm_out", "100.0, 100.0, 101.0, 100.0\n"), "lm_out.csv", "outside"),
    case("bases-missing", lambda e: e.estimate(f"reduction={{bases='{e.bad / 'no.npz'}'}}"), "no.npz"),
    case("bases-garbage", lambda e: e.estimate(f"reduction={{bases='{files.garbage(e.bad / 'noise.npz')}'}}"),
         "noise.npz"),
    case("bases-no-W", lambda e: e.estimate(f"reduction={{bases='{_npz(e, 'noW', variance=np.ones(1))}'}}"),
         "noW.npz"),
    case("bases-nan", lambda e: e.estimate(f"reduction={{bases='{_bases(e, 'nanW', nan=True)}'}}"), "nanW.npz", "NaN"),
    case("bases-not-orthonormal", lambda e: e.estimate(f"reduction={{bases='{_bases(e, 'skewW', scale=2.0)}'}}"),
         "skewW.npz", "orthonormal"),
    case("bases-wrong-shape", lambda e: e.estimate(f"reduction={{bases='{_bases(e, 'shortW', rows=-3)}'}}"),
         "shortW.npz"),
    case("bases-other-mesh", lambda e: e.estimate(f"reduction={{bases='{_bases(e, 'otherW', shift=0.5)}'}}"),
         "otherW.npz", "other loaded nodes"),
    case("bases-rank-above", lambda e: e.estimate(f"reduction={{bases='{e.bases}', rank=5}}"), "bases.npz", "rank 5"),
]


def _npz(e, name, **arrays) -> Path:
    path = e.bad / f"{name}.npz"
    np.savez(path, **arrays)
    return path


def _bases(e, name, nan=False, scale=1.0, rows=0, shift=0.0) -> Path:
    data = np.load(e.bases)
    W, coords = data["W"].copy() * scale, data["loaded_coords"] + shift
    if nan:
        W[0, 0] = np.nan
    if rows:
        W = W[:rows]
    return files.bases(e.bad / f"{name}.npz", W, coords)


@pytest.mark.parametrize("row", TARGETS)
def test_targets_landmarks_and_bases(env, capfd, row):
    run(row, row.argv(env), capfd)


WARNINGS = [
    case("estimate-target-2x", lambda e: e.target(files.moved(e.truth / "surface.vtp", e.bad / "big.vtp", scale=2.0)),
         "big.vtp", "spans", warning=True),
    case("estimate-misfit-above-noise", lambda e: e.estimate("target.noise=1e-9"), "target.noise", warning=True),
]


@pytest.mark.parametrize("row", WARNINGS)
def test_warnings(env, capfd, row):
    err = run(row, row.argv(env), capfd)
    if row.id.startswith("estimate-target"):
        result = json.loads((env.root / "out" / f"o{env.n}" / "result.json").read_text())
        assert any(all(w in text for w in row.words) for text in result["warnings"]), result["warnings"]
    assert "error" not in err


# =========================================================================== train

TRAIN = [
    case("train-rank-zero", lambda e: e.train(e.truth, rank=0), "--rank"),
    case("train-rank-negative", lambda e: e.train(e.truth, rank=-2), "--rank"),
    case("train-example-missing", lambda e: e.train(e.bad / "ghost.vtp"), "ghost.vtp"),
    case("train-example-far", lambda e: e.train(files.moved(e.truth / "surface.vtp", e.bad / "far_ex.vtp", (1000, 0, 0))),
         "far_ex.vtp", "overlap"),
    case("train-example-far-folder", lambda e: e.train(_far_folder(e)), "far_folder", "overlap"),
    case("train-example-corrupt", lambda e: e.train(files.truncated(e.truth / "surface.vtp", e.bad / "ex_cut.vtp")),
         "ex_cut.vtp"),
    case("train-example-folder-lacks", lambda e: e.train(e.bad), "surface_outline.vtp"),
    case("train-example-3d", lambda e: e.train(files.triangles_3d(e.bad)), "sphere.vtp"),
    case("train-synthetic-zero", lambda e: ["train", e.letter, "--synthetic", 0, "--rank", 2, "--out", e.out() / "b.npz"],
         "--synthetic"),
    case("train-synthetic-atlas", lambda e: ["train", "--atlas", e.phantom.parent / "phantom.msh", "--patient", e.phantom,
                                             e.truth, "--synthetic", 2, "--rank", 2, "--out", e.out() / "b.npz"],
         "--synthetic"),
    case("train-no-scene", lambda e: ["train", "--rank", 2, "--out", e.out() / "b.npz"], "--patient"),
    case("train-no-examples", lambda e: ["train", e.letter, "--rank", 2, "--out", e.out() / "b.npz"], "no examples"),
    case("train-patients-without-atlas", lambda e: ["train", e.letter, "--examples", e.truth, "--patient", e.letter,
                                                    e.truth, "--rank", 2, "--out", e.out() / "b.npz"], "--atlas"),
    case("train-atlas-garbage", lambda e: ["train", "--atlas", files.text(e.bad / "atlas.msh", "x"), "--patient",
                                           e.phantom, e.truth, "--rank", 2, "--out", e.out() / "b.npz"], "atlas.msh"),
    case("train-out-a-folder", lambda e: e.train(e.truth, out=e.bad), "directory"),
    case("train-out-suffix", lambda e: e.train(e.truth, out=e.root / "bases.txt"), ".npz"),
    case("train-out-proc", lambda e: e.train(e.truth, out=Path("/proc/bases.npz")), "/proc"),
    case("train-out-dev-full", lambda e: e.train(e.truth, out=Path("/dev/full")), "/dev"),
    case("train-out-under-a-file", lambda e: e.train(e.truth, out=e.letter / "b.npz"), "not a directory"),
    case("train-example-other-scene", lambda e: e.train(e.truth, problem=e.cantilever), "surface_top.vtp"),
]


def _far_folder(e) -> Path:
    folder = e.bad / "far_folder"
    folder.mkdir(exist_ok=True)
    files.moved(e.truth / "surface_outline.vtp", folder / "surface_outline.vtp", (0, 500, 0))
    return folder


@pytest.mark.parametrize("row", TRAIN)
def test_train(env, capfd, row):
    run(row, row.argv(env), capfd)


# =========================================================================== render


def render_folder(e, name: str, **contents) -> Path:
    """A copy of the simulated letter's folder with files replaced (None: removed)."""
    import shutil

    folder = e.bad / name
    shutil.copytree(e.truth, folder, dirs_exist_ok=True)
    for file, content in contents.items():
        target = folder / file.replace("__", ".")
        if content is None:
            target.unlink()
        elif isinstance(content, bytes):
            target.write_bytes(content)
        else:
            target.write_text(content)
    return folder


RENDER = [
    case("render-missing", lambda e: ["render", e.bad / "nothing"], "nothing"),
    case("render-a-file", lambda e: ["render", e.letter], "problem.toml", "not a folder"),
    case("render-no-surfaces", lambda e: ["render", e.bad / "cubes"], "surface_"),
    case("render-surface-truncated", lambda e: ["render", render_folder(
        e, "r_cut", surface_outline__vtp=(e.truth / "surface_outline.vtp").read_bytes()[:300])], "surface_outline.vtp"),
    case("render-surface-empty", lambda e: ["render", render_folder(e, "r_empty", surface_outline__vtp="")],
         "surface_outline.vtp"),
    case("render-surface-binary", lambda e: ["render", render_folder(
        e, "r_bin", surface_outline__vtp=bytes(range(256)) * 8)], "surface_outline.vtp"),
    case("render-target-corrupt", lambda e: ["render", render_folder(e, "r_target", target__vtp="garbage")],
         "target.vtp"),
    case("render-out-suffix", lambda e: ["render", e.truth, "--out", e.root / "picture.txt"], ".png"),
    case("render-out-folder", lambda e: ["render", e.truth, "--out", e.bad], "directory"),
    case("render-out-proc", lambda e: ["render", e.truth, "--out", "/proc/picture.png"], "/proc"),
    case("render-out-dev-full", lambda e: ["render", e.truth, "--out", "/dev/full"], "/dev"),
]


@pytest.mark.parametrize("row", RENDER)
def test_render(env, capfd, row):
    run(row, row.argv(env), capfd)


# =========================================================================== scene


SPEC = """\
units = "mm"
size = 5.0
[body]
box = {{ margin = 5.0 }}
[regions.ball]
surface = "{surface}"
"""


def spec(e, name: str, text: str | None = None, surface: str = "ball.stl", files_: dict | None = None) -> list:
    """A scene spec (default: a ball region in a box) beside its surface files."""
    import pyvista as pv

    folder = e.bad / "scene" / name
    folder.mkdir(parents=True, exist_ok=True)
    pv.Icosphere(radius=5.0, nsub=3).save(folder / "ball.stl")
    for file, content in (files_ or {}).items():
        if isinstance(content, bytes):
            (folder / file).write_bytes(content)
        elif isinstance(content, str):
            (folder / file).write_text(content)
        else:
            content.save(folder / file)
    path = folder / "spec.toml"
    path.write_text(text if text is not None else SPEC.format(surface=surface))
    return ["scene", path, "--out", e.out()]


def _open_ball():
    import pyvista as pv

    ball = pv.Icosphere(radius=5.0, nsub=3)
    centres = np.asarray(ball.cell_centers().points)
    return ball.extract_cells(np.flatnonzero(centres[:, 2] < 2.0)).extract_surface(algorithm=None)


def _pair(offset: float):
    import pyvista as pv

    return pv.Icosphere(radius=5.0, nsub=3, center=(offset, 0.0, 0.0))


SCENE = [
    case("scene-spec-missing", lambda e: ["scene", e.bad / "nospec.toml", "--out", e.out()], "nospec.toml"),
    case("scene-spec-not-toml", lambda e: spec(e, "nottoml", "size = [\n"), "spec.toml", "TOML"),
    case("scene-unknown-key", lambda e: spec(e, "typo", SPEC.format(surface="ball.stl").replace("size", "sise")),
         "sise", "size"),
    case("scene-no-body", lambda e: spec(e, "nobody", "size = 5.0\n"), "body"),
    case("scene-box-around-nothing", lambda e: spec(e, "empty_box", "[body]\nbox = { margin = 5.0 }\n"), "box"),
    case("scene-units-typo", lambda e: spec(e, "units", SPEC.format(surface="ball.stl").replace('"mm"', '"mn"')),
         "units", "mm"),
    case("scene-size-negative", lambda e: spec(e, "negsize", SPEC.format(surface="ball.stl").replace("5.0\n[body]",
                                                                                               "-5.0\n[body]")), "size"),
    case("scene-cli-size-nan", lambda e: spec(e, "nansize") + ["--size", "nan"], "--size"),
    case("scene-size-memory", lambda e: spec(e, "tiny") + ["--size", 0.01], "spec.toml", "size 0.01", "GB"),
    case("scene-organ-size-above-size", lambda e: spec(e, "organ_big", "organ_size = 9.0\n" + SPEC.format(surface="ball.stl")),
         "organ_size"),
    case("scene-surface-missing", lambda e: spec(e, "nosurface", surface="gone.stl"), "gone.stl"),
    case("scene-surface-empty", lambda e: spec(e, "empty_stl", surface="e.stl", files_={"e.stl": ""}), "e.stl", "empty"),
    case("scene-surface-stl-garbage", lambda e: spec(e, "garbage_stl", surface="g.stl", files_={"g.stl": "solid x\n"}),
         "g.stl"),
    case("scene-surface-vtp-truncated", lambda e: spec(e, "cut_vtp", surface="c.vtp", files_={
        "c.vtp": (e.truth / "surface.vtp").read_bytes()[:300]}), "c.vtp"),
    case("scene-surface-binary", lambda e: spec(e, "bin_stl", surface="b.ply", files_={"b.ply": bytes(range(256)) * 4}),
         "b.ply", "vtkPLYReader failed"),
    case("scene-surface-lines", lambda e: spec(e, "lines", surface="lines.vtp", files_={
        "lines.vtp": (files.surface_lines(e.bad)).read_bytes()}), "lines.vtp", "triangles"),
    case("scene-surface-open", lambda e: spec(e, "open", surface="open.vtp", files_={"open.vtp": _open_ball()}),
         "open.vtp"),
    case("scene-organs-intersect", lambda e: spec(e, "cross", SPEC.format(surface="ball.stl")
                                                  + '[regions.other]\nsurface = "b2.stl"\n', files_={"b2.stl": _pair(4.0)}),
         "intersect"),
    case("scene-group-clash", lambda e: spec(e, "clash", SPEC.format(surface="ball.stl")
                                             + '[cavities.ball_surface]\nsurface = "ball.stl"\n'), "ball_surface"),
    case("scene-patch-zero-normal", lambda e: spec(e, "zero_normal", SPEC.format(surface="ball.stl")
                                                   + "[patches.bones]\nside = { point = [0, 0, 0], normal = [0, 0, 0] }\n"),
         "normal"),
    case("scene-patch-misses", lambda e: spec(e, "patch_miss", SPEC.format(surface="ball.stl")
                                              + "[patches.bones]\nside = { point = [0, 0, 100], normal = [0, 0, 1] }\n"),
         "patches.bones"),
    case("scene-organ-leaks", lambda e: spec(e, "leak", "[body]\nsurface = \"ball.stl\"\n[regions.big]\nsurface = \"b2.stl\"\n",
                                             files_={"b2.stl": _pair(3.0)}), "b2.stl"),
]


@pytest.mark.parametrize("row", SCENE)
def test_scene(env, capfd, row):
    run(row, row.argv(env), capfd)


# =========================================================================== output places


def busy(e) -> list:
    """An output folder locked by a live process (a sleeping child)."""
    from fenics_elasto.files.outputs import LOCK

    folder = e.out()
    folder.mkdir(parents=True)
    e.sleeper = subprocess.Popen(["sleep", "60"])
    now = time.time()
    (folder / LOCK).write_text(json.dumps({"pid": e.sleeper.pid, "host": socket.gethostname(), "started": now,
                                           "start_time": time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(now))}))
    return folder


OUTPUTS = [
    case(f"{command}-out-{kind}", lambda e, c=command, k=kind: _place(e, c, k), *words)
    for command in ("simulate", "estimate", "mesh", "scene")
    for kind, words in (("existing-file", ("not a directory",)), ("proc", ("/proc",)), ("dev-full", ("/dev/full",)),
                        ("under-a-file", ("not a directory",)), ("busy", ("in use by another run",)))
]


def _place(e, command: str, kind: str) -> list:
    out = {"existing-file": e.letter, "proc": Path("/proc/fenics-out"), "dev-full": Path("/dev/full"),
           "under-a-file": e.letter / "sub"}.get(kind)
    out = busy(e) if kind == "busy" else out
    if command == "mesh":
        return ["mesh", "letter-a", "--out", out]
    if command == "scene":
        return spec(e, f"place_{kind}")[:2] + ["--out", out]
    argv = e.simulate(e.letter) if command == "simulate" else e.estimate()
    argv[argv.index("--out") + 1] = out
    return argv


@pytest.mark.parametrize("row", OUTPUTS)
def test_output_places(env, capfd, row):
    try:
        run(row, row.argv(env), capfd)
    finally:
        if getattr(env, "sleeper", None):
            env.sleeper.kill()
            env.sleeper = None


@pytest.fixture
def read_only(tmp_path):
    where = tmp_path / "ro"
    where.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k,ro", "tmpfs", str(where)], capture_output=True)
    if done.returncode != 0:
        pytest.skip("cannot mount a tmpfs here (needs CAP_SYS_ADMIN)")
    yield where
    subprocess.run(["umount", "-l", str(where)], check=False)


@pytest.mark.parametrize("command", ["simulate", "estimate", "mesh", "train", "render"])
def test_a_read_only_place(env, capfd, read_only, command):
    out = read_only / "result"
    argv = {"simulate": lambda: env.simulate(env.letter), "estimate": env.estimate,
            "mesh": lambda: ["mesh", "letter-a", "--out", out], "train": lambda: env.train(env.truth, out=out / "b.npz"),
            "render": lambda: ["render", env.truth, "--out", out / "p.png"]}[command]()
    if "--out" in argv:
        argv[argv.index("--out") + 1] = out if command in ("simulate", "estimate") else argv[argv.index("--out") + 1]
    row = Case(f"{command}-read-only", None, ("Read-only",))
    run(row, argv, capfd)


# =========================================================================== signals through the real CLI


def _cli(*args) -> subprocess.Popen:
    return subprocess.Popen([str(BIN / "fenics-elasto"), *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def assert_complete(folder: Path) -> dict:
    result = json.loads((folder / "result.json").read_text())
    on_disk = sorted(p for p in os.listdir(folder) if p != "result.json")
    assert on_disk == sorted(result["files"]), (on_disk, result["files"])  # no temporaries, no lock
    return result


@pytest.mark.slow
def test_sigterm_during_an_estimate_keeps_the_best_so_far(env):
    """SIGTERM (a batch scheduler, ``timeout``) as Ctrl-C: the folder is written whole,
    ``interrupted`` true, exit 130. (gmsh, reading the mesh, set SIGTERM back to its
    default: the run died at once, exit -15, nothing written.)"""
    out = env.out()
    proc = _cli("estimate", env.letter, "--out", out, "--set", f"target.surface='{env.truth / 'surface.vtp'}'",
                "--set", "optimizer.inner='lbfgs-forces'", "--set", "optimizer.scan=30")
    for line in proc.stdout:
        if line.startswith("  scan"):  # the first material value is solved: there is a best so far
            proc.send_signal(signal.SIGTERM)
            break
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130, stderr
    result = assert_complete(out)
    assert result["interrupted"] is True
    assert {"surface.vtp", "forces.csv", "screenshot.png", "displacement.bp"} <= set(result["files"])


@pytest.mark.slow
def test_sigint_while_writing_finishes_the_writing(env):
    """A SIGINT that lands while the result folder is being written waits for it: the
    folder is complete, then the command stops with 130."""
    out = env.out()
    proc = _cli("simulate", env.letter, "--out", out)
    deadline = time.monotonic() + 60
    while not any(name.startswith(".displacement.part-") for name in (os.listdir(out) if out.is_dir() else [])):
        assert time.monotonic() < deadline and proc.poll() is None, "the writing was never seen"
        time.sleep(0.01)
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130, stderr
    assert "after finishing the files being written" in stderr
    result = assert_complete(out)
    assert {"surface.vtp", "surface_outline.vtp", "screenshot.png", "displacement.bp"} <= set(result["files"])


@pytest.mark.slow
def test_a_second_run_into_a_busy_folder_is_refused(env):
    """A real run holds the folder; a second one into it is refused at once, the first
    finishes undisturbed."""
    out = env.out()
    first = _cli("estimate", env.letter, "--out", out, "--set", f"target.surface='{env.truth / 'surface.vtp'}'",
                 "--set", "optimizer.inner='lbfgs-forces'", "--set", "optimizer.scan=8")
    for line in first.stdout:
        if line.startswith("  scan"):
            break
    second = run_cli("simulate", env.letter, "--out", out)
    assert second.returncode == 2 and "in use by another run" in second.stderr, second.stderr
    assert second.stderr.strip().count("\n") == 0
    first.communicate(timeout=300)
    assert first.returncode == 0
    assert assert_complete(out)["interrupted"] is False
