"""A scene refined once (refine.py): every group kept with its overlaps, the same
geometry (lengths, areas, volumes; the fine nodes are the coarse mesh's own order-4
lattice as DOLFINx computes it), conforming, boundary fields carried over exactly (against
DOLFINx's point evaluation), and a refined problem that runs and converges."""

import itertools
import json
import tomllib

import basix.ufl
import numpy as np
import pytest
import ufl
from scipy.spatial import cKDTree

import dolfinx
import dolfinx.geometry
from dolfinx import fem

from conftest import TESTS, run_mpi_script
from fenics_elasto.app.cli import main
from fenics_elasto.model.dofs import DofLayout
from fenics_elasto.model.elasticity import ElasticModel
from fenics_elasto.util.errors import UserError
from fenics_elasto.mesh.gmsh_models import GmshModel
from fenics_elasto.mesh.builtin import build_scene
from fenics_elasto.model.refine import prolongation, refine_scene, transfer_bases
from fenics_elasto.model.scene import load_scene
from fenics_elasto.model.simulate import simulate
from analytic import C, E, L, P, cantilever_errors

SIZES = {"letter-a": None, "inclusion": None, "cantilever": 0.5, "prostate-phantom": 1.6}
STRAIGHT_WALLS = {"letter-a": True, "inclusion": True, "prostate-phantom": False}  # loaded facets: physical
# quadratics are in the P2 space there (on curved facets only affine fields are)
NAMES = ["letter-a", "inclusion", "prostate-phantom"]


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """name -> (coarse scene, its refinement), built on first use."""
    cache = {}

    def get(name):
        if name not in cache:
            base = tmp_path_factory.mktemp(name)
            coarse = build_scene(name, base / "coarse", size=SIZES[name])
            cache[name] = (load_scene(coarse), load_scene(refine_scene(coarse, base / "fine")))
        return cache[name]

    return get


def _count(scene, dim):
    return scene.mesh.topology.index_map(dim).size_global


# --------------------------------------------------------------------------- groups


@pytest.mark.parametrize("name", NAMES)
def test_every_group_kept_with_its_children(pair, name):
    coarse, fine = pair(name)
    tdim = coarse.mesh.topology.dim
    assert [(m.name, m.tag) for m in fine.materials] == [(m.name, m.tag) for m in coarse.materials]
    assert _count(fine, tdim) == 2**tdim * _count(coarse, tdim)
    for m in coarse.materials:
        assert len(fine.cell_tags.find(m.tag)) == 2**tdim * len(coarse.cell_tags.find(m.tag)), m.name
    assert sorted(fine.facet_groups) == sorted(coarse.facet_groups)
    for a, b in itertools.combinations_with_replacement(sorted(coarse.facet_groups), 2):
        shared = [len(np.intersect1d(s.facet_groups[a], s.facet_groups[b])) for s in (coarse, fine)]
        assert shared[1] == 2 ** (tdim - 1) * shared[0], (a, b, shared)  # overlaps kept, none made
    if name == "letter-a":
        for part in ("feet", "top"):
            assert len(fine.facet_groups[part]) > 0
            assert np.isin(fine.facet_groups[part], fine.facet_groups["outline"]).all()


# --------------------------------------------------------------------------- geometry


def _measures(scene, degree):
    """Every region's volume (and its signed volume, the integral of det J: a polynomial
    of degree <= 3), every facet group's length or area (exterior and interior facets),
    the latter with quadrature of ``degree``."""
    mesh, tdim = scene.mesh, scene.mesh.topology.dim
    metadata = {"quadrature_degree": degree}
    dx = ufl.Measure("dx", domain=mesh, subdomain_data=scene.cell_tags, metadata={"quadrature_degree": 4})
    one, detJ = fem.Constant(mesh, 1.0), ufl.JacobianDeterminant(mesh)
    out = {}
    for m in scene.materials:
        out[m.name] = fem.assemble_scalar(fem.form(one * dx(m.tag)))
        out["signed " + m.name] = fem.assemble_scalar(fem.form(ufl.sign(detJ) * dx(m.tag)))
    for group, facets in scene.facet_groups.items():
        tags = dolfinx.mesh.meshtags(mesh, tdim - 1, np.sort(facets), np.ones(len(facets), np.int32))
        ds = ufl.Measure("ds", domain=mesh, subdomain_data=tags, metadata=metadata)
        dS = ufl.Measure("dS", domain=mesh, subdomain_data=tags, metadata=metadata)
        out[group] = fem.assemble_scalar(fem.form(one * ds(1) + one("+") * dS(1)))
    return out


@pytest.mark.parametrize("name", NAMES)
def test_same_lengths_areas_and_volumes(pair, name):
    """Order 2: the same curved geometry, so equal up to quadrature (a high degree: arc
    lengths and curved areas are not polynomial); order 1: the same polygon."""
    coarse, fine = pair(name)
    degree = 20 if coarse.gdim == 3 else 12
    before, after = _measures(coarse, degree), _measures(fine, degree)
    for key, value in before.items():
        assert abs(after[key] - value) <= 1e-10 * abs(value), (key, value, after[key])
        assert value > 0, key


def _dof_points(mesh, degree):
    element = basix.ufl.element("Lagrange", mesh.topology.cell_name(), degree,
                                lagrange_variant=basix.LagrangeVariant.equispaced)
    return fem.functionspace(mesh, element).tabulate_dof_coordinates()


@pytest.mark.parametrize("name", NAMES)
def test_fine_nodes_are_the_coarse_order4_lattice(pair, name):
    """The fine P2 nodes are exactly the coarse cells' equispaced P4 points mapped by
    the coarse geometry (DOLFINx's own map): nothing moved, nothing duplicated
    (conforming: shared nodes are shared), none missing."""
    coarse, fine = pair(name)
    lattice, nodes = _dof_points(coarse.mesh, 4), _dof_points(fine.mesh, 2)
    assert len(nodes) == len(lattice)
    gap, match = cKDTree(lattice).query(nodes)
    assert gap.max() < 1e-12 * np.ptp(lattice, axis=0).max()
    assert len(np.unique(match)) == len(match)


# --------------------------------------------------------------------------- fields


def _loaded(scene):
    nodes = DofLayout(scene).node_set(scene.loaded, scene.fixed)
    return nodes, nodes.gather(nodes.coords)


def _evaluate(scene, u, points):
    """u at points by DOLFINx: cell search and pull-back (curved cells: Newton)."""
    padded = np.zeros((len(points), 3))
    padded[:, : scene.gdim] = points
    tree = dolfinx.geometry.bb_tree(scene.mesh, scene.mesh.topology.dim, padding=1e-6)
    cells = dolfinx.geometry.compute_colliding_cells(scene.mesh, dolfinx.geometry.compute_collisions_points(tree, padded), padded)
    first = np.array([cells.links(i)[0] for i in range(len(points))], dtype=np.int32)
    return u.eval(padded, first)


def _random_coarse_field(scene, seed=1):
    """A random field of the coarse space, zero on the clamped nodes, and its loaded-node rows."""
    model = ElasticModel(scene)
    u = model.dofs.function()
    u.x.array[:] = np.random.default_rng(seed).normal(size=u.x.array.size)
    u.x.array[model.dofs.clamped_dofs(scene.fixed)] = 0.0
    nodes, _ = _loaded(scene)
    return u, nodes.gather(u.x.array.reshape(-1, model.dofs.bs)[nodes.blocks])


def _affine(x):
    A = np.arange(1.0, 1.0 + x.shape[1] ** 2).reshape(x.shape[1], -1) / 7
    return x @ A.T + np.arange(x.shape[1])


def _quadratic(x):
    columns = [x[:, 0] ** 2 - x[:, 1], x[:, 0] * x[:, 1], x[:, -1] ** 2]
    return np.stack(columns[: x.shape[1]], axis=1)


@pytest.mark.parametrize("name", NAMES)
def test_prolongation_is_exact_in_the_coarse_space(pair, name):
    coarse, fine = pair(name)
    P = prolongation(coarse, fine, coarse.loaded, coarse.fixed)
    (_, x), (_, y) = _loaded(coarse), _loaded(fine)
    assert P.shape == (len(y), len(x)) and len(y) >= 2 * len(x) - 1
    u, rows = _random_coarse_field(coarse)
    expected = _evaluate(coarse, u, y)
    assert np.abs(P @ rows - expected).max() < 1e-10 * np.abs(expected).max()
    assert np.abs(P @ _affine(x) - _affine(y)).max() < 1e-12 * np.abs(_affine(y)).max()
    if STRAIGHT_WALLS[name]:
        assert np.abs(P @ _quadratic(x) - _quadratic(y)).max() < 1e-12 * np.abs(_quadratic(y)).max()


@pytest.mark.parametrize("name", NAMES)
def test_transfer_bases_keeps_affine_and_quadratic_fields(pair, name):
    """Bases spanning an affine and a quadratic boundary field (on curved walls: a random
    field of the coarse space) span exactly those fields on the fine loaded nodes."""
    coarse, fine = pair(name)
    (_, x), (_, y) = _loaded(coarse), _loaded(fine)
    if not STRAIGHT_WALLS[name]:
        u, rows = _random_coarse_field(coarse)
        second, second_fine = rows, _evaluate(coarse, u, y)
    else:
        second, second_fine = _quadratic(x), _quadratic(y)
    fields = np.stack([_affine(x).ravel(), second.ravel()], axis=1)
    W, R = np.linalg.qr(fields)
    W_fine = transfer_bases(W, coarse.path, fine)
    assert W_fine.shape == (y.size, 2)
    assert np.abs(W_fine.T @ W_fine - np.eye(2)).max() < 1e-12
    for column in (_affine(y).ravel(), second_fine.ravel()):
        assert np.linalg.norm(column - W_fine @ (W_fine.T @ column)) < 1e-10 * np.linalg.norm(column)
    first = _affine(y).ravel() / np.linalg.norm(_affine(y))  # the first mode stays first, same sign
    assert abs(W_fine[:, 0] @ first * np.sign(R[0, 0]) - 1) < 1e-12
    with pytest.raises(UserError, match="do not fit"):
        transfer_bases(W[:-1], coarse, fine)


# --------------------------------------------------------------------------- the problem file


def test_problem_paths_still_resolve(tmp_path):
    """mesh points at the refined mesh; relative files are rewritten relative to the new
    folder, absolute ones kept; everything else unchanged."""
    problem = build_scene("letter-a", tmp_path / "scene")
    raw = tomllib.loads(problem.read_text())
    raw.pop("target")
    text = problem.read_text().split("[target]")[0]
    text += ('[target]\nsurfaces = { outline = "../data/outline.vtp" }\nlandmarks = "marks.csv"\n'
             f'[reduction]\nbases = "{tmp_path / "bases.npz"}"\n')
    problem.write_text(text)
    refined = refine_scene(problem, tmp_path / "deeper" / "fine")
    new = tomllib.loads(refined.read_text())
    assert new["mesh"] == "letter_a.msh" and (refined.parent / new["mesh"]).is_file()
    here = refined.parent
    assert (here / new["target"]["surfaces"]["outline"]).resolve() == (tmp_path / "data" / "outline.vtp").resolve()
    assert (here / new["target"]["landmarks"]).resolve() == (problem.parent / "marks.csv").resolve()
    assert new["reduction"]["bases"] == str(tmp_path / "bases.npz")
    for key in ("materials", "boundary", "plane", "degree"):
        assert new[key] == raw[key], key


def test_bad_input_is_one_line(tmp_path):
    problem = build_scene("letter-a", tmp_path / "scene")
    with pytest.raises(UserError, match="overwrite"):
        refine_scene(problem, problem.parent)
    with pytest.raises(UserError, match="no such problem file"):
        refine_scene(tmp_path / "nope.toml", tmp_path / "out")
    (tmp_path / "scene" / "letter_a.msh").write_text("not a mesh")
    with pytest.raises(UserError, match="letter_a.msh"):
        refine_scene(problem, tmp_path / "out")
    with GmshModel("quads") as gmsh:  # quadrilaterals: not split, said so
        gmsh.model.occ.addRectangle(0, 0, 0, 1, 1)
        gmsh.model.occ.synchronize()
        gmsh.model.addPhysicalGroup(2, [1], name="letter")
        gmsh.option.setNumber("Mesh.RecombineAll", 1)
        gmsh.model.mesh.generate(2)  # written as is: save() would refuse quadrilaterals
        gmsh.write(str(tmp_path / "scene" / "letter_a.msh"))
    with pytest.raises(UserError, match="Quadrilateral"):
        refine_scene(problem, tmp_path / "out")


# --------------------------------------------------------------------------- solving on it


def test_refined_cantilever_converges_at_the_p2_rate(tmp_path):
    """P2 against Timoshenko-Goodier: one refinement divides the L2 error by ~2^3."""
    coarse = build_scene("cantilever", tmp_path / "coarse", size=SIZES["cantilever"])
    fine = refine_scene(coarse, tmp_path / "fine")
    (error, tip, h), (fine_error, fine_tip, fine_h) = cantilever_errors(coarse, 2), cantilever_errors(fine, 2)
    assert abs(fine_h - h / 2) < 1e-12 * h
    assert 5.0 < error / fine_error < 12.0, (error, fine_error)
    exact_tip = P * L**3 / (3 * E * 2 * C**3 / 3)
    assert abs(fine_tip - exact_tip) < abs(tip - exact_tip)


@pytest.mark.slow
def test_simulate_runs_on_the_refined_problem(pair, tmp_path):
    """`fenics-elasto simulate` on the refined problem.toml: the same problem, ~4x the DOFs."""
    coarse, fine = pair("inclusion")
    assert main(["simulate", str(fine.path), "--out", str(tmp_path / "fine")]) == 0
    result = json.loads((tmp_path / "fine" / "result.json").read_text())
    assert result["dofs"] == DofLayout(fine).num_dofs > 3.5 * DofLayout(coarse).num_dofs
    assert abs(result["max_displacement"] / simulate(coarse).result["max_displacement"] - 1) < 1e-2


@pytest.mark.slow
def test_two_ranks_refine_and_transfer_as_one(pair, tmp_path):
    coarse, _ = pair("inclusion")
    script = TESTS / "mpi" / "refine.py"
    for ranks in (1, 2):
        run_mpi_script(script, ranks, coarse.path, tmp_path / f"r{ranks}", tmp_path / f"w{ranks}.npy")
    assert (tmp_path / "r1" / "inclusion.msh").read_bytes() == (tmp_path / "r2" / "inclusion.msh").read_bytes()
    assert np.abs(np.load(tmp_path / "w1.npy") - np.load(tmp_path / "w2.npy")).max() < 1e-12


@pytest.mark.slow
def test_estimate_check_mesh_reports_how_far_the_answer_moves(tmp_path):
    """`estimate --check-mesh`: the estimate again on the source split once; on the
    curved inclusion against a 2x finer target E moves by well under 1 %."""
    from conftest import run_cli
    from targets import fine_simulation

    source = build_scene("inclusion", tmp_path / "source")
    fine_simulation("inclusion", tmp_path / "fine", 0.25, ["materials.inclusion.E=50.0"])
    target = ", ".join(f"{g}='{tmp_path / 'fine' / 'target' / f'surface_{g}.vtp'}'" for g in ("outline", "interface"))
    proc = run_cli("estimate", source, "--out", tmp_path / "out", "--check-mesh", "--set", f"target.surfaces={{{target}}}")
    assert proc.returncode == 0, proc.stderr[-2000:]
    check = json.loads((tmp_path / "out" / "result.json").read_text())["mesh_check"]
    assert check["refined_dofs"] > 3 * json.loads((tmp_path / "out" / "result.json").read_text())["dofs"]
    assert abs(check["change_percent"]["inclusion.E"]) < 1.0, check
    assert abs(check["estimated"]["inclusion.E"] - 50.0) < 1.0, check
