"""Forward model properties: linear combination, scaling, factorization reuse, MPI."""


import basix
import numpy as np
import pytest
import ufl

import dolfinx.fem.petsc
from dolfinx import fem

from conftest import TESTS, run_mpi_script
import fenics_elasto.model.stiffness as stiffness
from fenics_elasto.model.dofs import DofLayout
from fenics_elasto.model.elasticity import ElasticModel
from fenics_elasto.model.materials import lame, lame_jacobian
from fenics_elasto.model.stiffness import stiffness_quadrature
from fenics_elasto.util.errors import UserError
from fenics_elasto.model.scene import load_scene, reconfigure
from fenics_elasto.model.simulate import material_values, simulate


@pytest.fixture(scope="module")
def phantom(scenes):
    scene = load_scene(scenes["prostate-phantom"], ["degree=1"])
    return scene, ElasticModel(scene)


def test_linear_combination_equals_direct_assembly(phantom):
    scene, model = phantom
    E, nu = np.array([10.0, 37.0]), np.array([0.45, 0.3])
    mu, lam = lame(E, nu)
    Q = fem.functionspace(scene.mesh, ("DG", 0))
    mu_f, lam_f = fem.Function(Q), fem.Function(Q)
    for m, material in enumerate(scene.materials):
        cells = scene.cell_tags.find(material.tag)
        mu_f.x.array[Q.dofmap.list[cells, 0]] = mu[m]
        lam_f.x.array[Q.dofmap.list[cells, 0]] = lam[m]
    u, v = ufl.TrialFunction(model.dofs.V), ufl.TestFunction(model.dofs.V)
    eps = lambda w: ufl.sym(ufl.grad(w))  # noqa: E731
    dx = ufl.dx(metadata=stiffness_quadrature(model.dofs.V))
    direct = dolfinx.fem.petsc.assemble_matrix(
        fem.form(2 * mu_f * ufl.inner(eps(u), eps(v)) * dx + lam_f * ufl.div(u) * ufl.div(v) * dx))
    direct.assemble()
    combined = model.stiffness.matrix(model.stiffness.coefficients(E, nu))
    combined.axpy(-1.0, direct)
    assert combined.norm() / direct.norm() < 1e-12


def test_a_small_region_derivative_runs_over_its_own_entries(phantom):
    """ElasticModel.compact_terms: the prostate's terms (a small region) get copies without
    the pattern's explicit zeros, the tissue's do not; dK/dE_prostate x through them equals
    the product with the summed matrix, and K x (every term) is unchanged."""
    scene, model = phantom
    names = [m.name for m in scene.materials]
    small = [names.index("prostate")]
    compact = model.stiffness.compact_terms
    assert [j for j, C in enumerate(compact) if C is not None] == [2 * m + k for m in small for k in (0, 1)]
    full = sum(M.getInfo()["nz_used"] for M in model.stiffness.terms[2 * small[0]:2 * small[0] + 2])
    kept = sum(compact[j].getInfo()["nz_used"] for j in (2 * small[0], 2 * small[0] + 1))
    assert kept < 0.5 * full
    E, nu = np.array([10.0, 37.0]), np.array([0.45, 0.3])
    x, y, z = model.dofs.function(), model.dofs.function(), model.dofs.function()
    x.x.array[:] = np.random.default_rng(0).standard_normal(len(x.x.array))
    for c in (model.stiffness.coefficient_derivatives(E, nu)[0][small[0]], model.stiffness.coefficients(E, nu)):
        model.stiffness.apply(c, x.x.petsc_vec, y.x.petsc_vec)
        summed = model.stiffness.matrix(c)
        summed.mult(x.x.petsc_vec, z.x.petsc_vec)
        summed.destroy()
        assert np.linalg.norm(y.x.array - z.x.array) <= 1e-13 * np.linalg.norm(z.x.array)


def _patch_residual(scene, model) -> np.ndarray:
    """|K u| per node for an affine u, one material everywhere: zero at every node off
    the boundary when the quadrature integrates a constant stress's equilibrium exactly."""
    A = np.array([[0.03, -0.02, 0.01], [0.015, -0.04, 0.02], [-0.01, 0.025, 0.05]])
    u, r = model.dofs.function(), model.dofs.function()
    u.x.array[:] = (model.dofs.dof_coords @ A.T).ravel()
    one = np.ones(len(scene.materials))
    model.stiffness.apply(model.stiffness.coefficients(10 * one, 0.4 * one), u.x.petsc_vec, r.x.petsc_vec)
    return np.abs(r.x.array.reshape(-1, 3)[: model.dofs.n_owned_blocks]).max(axis=1)


def _folded_cells(scene) -> int:
    """How many cells' det J changes sign over a lattice of points in them."""
    mesh = scene.mesh
    points = basix.create_lattice(basix.CellType.tetrahedron, 4, basix.LatticeType.equispaced, True)
    cells = np.arange(mesh.topology.index_map(3).size_local, dtype=np.int32)
    detJ = fem.Expression(ufl.JacobianDeterminant(mesh), points).eval(mesh, cells).reshape(len(cells), -1)
    return int(((detJ.min(axis=1) <= 0) & (detJ.max(axis=1) >= 0)).sum())


def test_curved_cells_pass_the_patch_test(scenes, monkeypatch):
    """P2 on the phantom's curved tets: the stiffness quadrature (degree 3) puts an affine
    field in equilibrium at every interior node to round-off; degree 2, enough for
    convergence alone, does not. (No cell folds over -- the meshing untangles them, the
    mesh check refuses them -- so det J keeps its sign.)"""
    scene = load_scene(scenes["prostate-phantom"])
    assert _folded_cells(scene) == 0
    model = ElasticModel(scene)
    assert stiffness_quadrature(model.dofs.V) == {"quadrature_degree": 3}
    boundary = model.dofs.boundary_blocks(list(scene.facet_groups))
    interior = np.setdiff1d(np.arange(model.dofs.n_owned_blocks), boundary)
    residual = _patch_residual(scene, model)
    scale = residual[boundary].max()
    assert residual[interior].max() < 1e-12 * scale
    monkeypatch.setattr(stiffness, "stiffness_quadrature", lambda V: {"quadrature_degree": 2})
    loose = _patch_residual(scene, ElasticModel(scene))[interior]
    assert (loose > 1e-6 * scale).sum() > 100


def test_lame_jacobian_matches_finite_differences():
    E, nu, h = 7.0, 0.37, 1e-6
    for plane in ("strain", "stress"):
        numeric = [(np.array(lame(E + h, nu, plane)) - lame(E - h, nu, plane)) / (2 * h),
                   (np.array(lame(E, nu + h, plane)) - lame(E, nu - h, plane)) / (2 * h)]
        dmu_dE, dmu_dnu, dlam_dE, dlam_dnu = lame_jacobian(E, nu, plane)
        assert np.allclose([dmu_dE, dlam_dE], numeric[0], rtol=1e-8)
        assert np.allclose([dmu_dnu, dlam_dnu], numeric[1], rtol=1e-8)


def test_scaling_stiffness_and_forces_leaves_u_unchanged(scenes):
    scene = load_scene(scenes["cantilever"])
    base = simulate(scene).u.x.array.copy()
    scaled = load_scene(scenes["cantilever"], ["materials.beam.E=7000.0", "boundary.load.tip=[0.0, -7.0]"])
    u = simulate(scaled).u.x.array
    assert np.abs(u - base).max() < 1e-10 * np.abs(base).max()
    assert np.abs(base).max() > 0.01  # the load really deforms the beam


def test_reconfigure_equals_loading_with_the_overrides(scenes):
    """Overrides on a loaded scene (no mesh re-read, one shared model) give the same
    displacement as loading the file with them; changing the mesh is refused."""
    settings = ["materials.beam.E=3000.0", "boundary.load.tip=[0.5, -2.0]"]
    scene = load_scene(scenes["cantilever"])
    model = ElasticModel(scene)
    again = reconfigure(scene, settings)
    assert again.mesh is scene.mesh
    u = simulate(again, model).u.x.array
    expected = simulate(load_scene(scenes["cantilever"], settings)).u.x.array  # its own K: one matrix, not a sum
    assert np.abs(u - expected).max() < 1e-10 * np.abs(expected).max()
    assert np.abs(u - simulate(scene, model).u.x.array).max() > 0.1 * np.abs(expected).max()
    with pytest.raises(UserError, match="keeps the mesh"):
        reconfigure(scene, ["mesh='other.msh'"])


def test_curved_surfaces_lie_on_the_organs(scenes, phantom):
    """The phantom's P2 geometry with a P2 field writes 4x4 flat pieces per curved
    facet, all on the true prostate ellipsoid up to the quadratic interpolation
    error; with a P1 field (corners only) the flat facets cut inside by their sag."""
    from fenics_elasto.files.writers import surface
    from fenics_elasto.mesh.builtin import phantom_organs

    prostate = phantom_organs(0)["prostate"]

    def depth(points):  # 1 - elliptic radius: > 0 inside the organ
        return 1 - np.sqrt(np.sum(((points - prostate["center"]) / prostate["radii"]) ** 2, axis=1))

    def centroid_depth(mesh):
        return depth(np.asarray(mesh.points)[mesh.faces.reshape(-1, 4)[:, 1:]].mean(axis=1))

    curved_scene = load_scene(scenes["prostate-phantom"])
    facets = curved_scene.facet_groups["prostate_surface"]
    curved = surface(DofLayout(curved_scene).function("zero"), facets, deformed=False)
    flat_scene, flat_model = phantom  # degree 1: no midpoint values, corners only
    flat = surface(flat_model.dofs.function("zero"), flat_scene.facet_groups["prostate_surface"], deformed=False)
    assert curved.n_cells == 16 * len(facets) and flat.n_cells == len(facets)
    assert np.abs(depth(np.asarray(curved.points))).max() < 2e-3
    assert centroid_depth(curved).max() < 0.2 * centroid_depth(flat).max()


def test_factorization_is_cached_and_counted(phantom):
    scene, model = phantom
    E, nu = material_values(scene)
    clamped = model.dofs.clamped_dofs(scene.fixed)
    before = model.factorizations
    rhs = model.dofs.function("f")
    rhs.x.array[:] = 1.0
    u1 = model.solve(model.stiffness.coefficients(E, nu), clamped, rhs.x.petsc_vec).x.array.copy()
    u2 = model.solve(model.stiffness.coefficients(E, nu), clamped, rhs.x.petsc_vec).x.array.copy()
    assert model.factorizations == before + 1
    assert np.array_equal(u1, u2)
    model.solve(model.stiffness.coefficients(E * 2, nu), clamped, rhs.x.petsc_vec)
    assert model.factorizations == before + 2


def _sorted_by_position(data):
    order = np.lexsort(np.round(data["coords"], 9).T[::-1])
    return data["coords"][order], data["disp"][order]


@pytest.mark.slow
@pytest.mark.parametrize("name", ["letter-a", "prostate-phantom"])
def test_two_ranks_give_the_serial_displacement(scenes, tmp_path, name):
    script = TESTS / "mpi" / "forward.py"
    results = {}
    for ranks in (1, 2):
        run_mpi_script(script, ranks, scenes[name], tmp_path / f"u{ranks}.npz")
        results[ranks] = _sorted_by_position(np.load(tmp_path / f"u{ranks}.npz"))
    (x1, u1), (x2, u2) = results[1], results[2]
    assert np.allclose(x1, x2, atol=1e-12)
    assert np.abs(u1 - u2).max() < 1e-8 * max(1.0, np.abs(u1).max())
    assert np.abs(u1).max() > 1e-3
