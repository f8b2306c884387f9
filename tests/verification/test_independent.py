"""The independent reference (tests/independent.py) checked before anything relies on it:
its FE solution against exact answers and its own refinement, its sampling against the
exact geometry, its files against the toolkit's readers."""

import numpy as np
import pytest

import independent as ind
from fenics_elasto.mesh.builtin import phantom_organs
from fenics_elasto.files.readers import read_landmarks, read_surface

# Cheap sizes: the checks below hold at any size; the defaults are for estimates.
LETTER = {"size": 0.32}
INCLUSION = {"size": 0.4, "spacing": 0.02, "top": (0.3, 0.05, -0.5, -0.02)}
PHANTOM = {"walls": 0.7, "prostate": 0.45, "far": 2.5, "spacing": 0.08}  # (0.8, 0.5, 2.0): HXT fails


@pytest.fixture(scope="session")
def truth_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("independent")


def _affine(x):
    """An affine displacement, (dim, n) -> (dim, n)."""
    dim = x.shape[0]
    A = np.array([[0.03, -0.02, 0.01], [0.015, -0.04, 0.02], [-0.01, 0.025, 0.05]])[:dim, :dim]
    return A @ x + np.array([0.1, -0.2, 0.05])[:dim, None]


def test_stiffness_equals_scikit_fem_vector_form():
    """The assembly shortcut (scalar gradient matrices combined) is scikit-fem's own
    vector elasticity form, on curved 2D and 3D P2 meshes."""
    from skfem import MeshTet2, MeshTri2, asm
    from skfem.models.elasticity import linear_elasticity

    for mesh in (MeshTri2.init_circle(2), MeshTet2.init_ball(1)):
        model = ind.Elasticity(ind.FEMesh(mesh, {"all": np.arange(mesh.nelements)}, {}))
        lam, mu = ind.lame(7.0, 0.35)
        reference = asm(linear_elasticity(lam, mu), model.basis)
        assert abs(model.stiffness({"all": (7.0, 0.35)}) - reference).max() < 1e-12 * abs(reference).max()


def test_patch_affine_motion_reproduced_on_gmsh_mesh():
    """Patch test on the curved inclusion mesh (one material in both regions): the
    outline moved affinely gives that affine field everywhere, also at points a hair
    outside the curved mesh (evaluated on their nearest cell's polynomial)."""
    model = ind.inclusion_model((0.3, -0.2), 1.2, 0.5)
    u = model.solve({"matrix": (10.0, 0.3), "inclusion": (10.0, 0.3)}, {"outline": _affine})
    rng = np.random.default_rng(1)
    inside = rng.uniform([-4.9, -2.9], [4.9, 2.9], (200, 2))
    circle = ind.sample_circle((0.3, -0.2), 1.2, 0.05)
    hair = np.array([[5.0005, 0.3], [-2.0, -3.0005], [5.0003, 3.0003]])
    points = np.concatenate([inside, circle, hair])
    assert np.abs(ind.evaluate(model.basis, u, points) - _affine(points.T).T).max() < 1e-10
    assert ind.locate(model.basis, hair)[2].min() > 0  # they really are outside


def test_gmsh_quadratic_nodes_are_edge_midpoints_on_the_geometry():
    """The gmsh -> scikit-fem node order is right (every edge node near its own edge's
    midpoint), and the edge nodes of the interface lie on the exact circle (curved
    geometry, not chords)."""
    model = ind.inclusion_model((0.0, 0.0), 1.2, 0.5)
    mesh = model.fe.mesh
    edge_nodes = mesh.doflocs[:, mesh.nvertices:]
    chord_mid = mesh.p[:, mesh.facets].mean(axis=1)  # in 2D the facets are the edges
    length = np.linalg.norm(np.diff(mesh.p[:, mesh.facets], axis=1)[:, 0], axis=0)
    assert (np.linalg.norm(edge_nodes - chord_mid, axis=0) < 0.2 * length).all()
    interface = model.fe.facets["interface"]
    on_circle = mesh.doflocs[:, mesh.nvertices + interface]
    assert np.abs(np.linalg.norm(on_circle, axis=0) - 1.2).max() < 1e-9
    sag = np.linalg.norm(chord_mid[:, interface], axis=0)
    assert (1.2 - sag).max() > 1e-3  # a straight-sided mesh would have put them here


def test_exact_geometry_sampling():
    """Samples lie on the exact curves and surfaces, and are as fine as asked."""
    circle = ind.sample_circle((0.5, -1.0), 1.2, 0.01)
    assert np.abs(np.linalg.norm(circle - (0.5, -1.0), axis=1) - 1.2).max() < 1e-14
    assert np.linalg.norm(np.diff(circle, axis=0), axis=1).max() <= 0.01
    segment = ind.sample_segment((0, 0), (1.6, 0.0), 0.01)
    assert np.allclose(segment[[0, -1]], [(0, 0), (1.6, 0)]) and np.abs(segment[:, 1]).max() == 0

    points, triangles = ind.ellipsoid_surface((0.0, 0.0, -0.8), (1.6, 1.3, 1.1), 0.03)
    level = np.sum(((points - (0.0, 0.0, -0.8)) / (1.6, 1.3, 1.1)) ** 2, axis=1)
    assert np.abs(level - 1).max() < 1e-14
    edges = np.linalg.norm(points[triangles] - points[np.roll(triangles, 1, axis=1)], axis=2)
    assert edges.max() < 0.05

    base, radius, length = np.array([0.0, 2.9, -4.0]), 0.9, 5.0
    points, triangles = ind.cylinder_surface(base, radius, length, 0.05)
    d = points - base
    r = np.hypot(d[:, 0], d[:, 1])
    on_side = np.isclose(r, radius, atol=1e-14) & (d[:, 2] >= -1e-14) & (d[:, 2] <= length + 1e-14)
    on_cap = (np.isclose(d[:, 2], 0, atol=1e-14) | np.isclose(d[:, 2], length, atol=1e-14)) & (r <= radius + 1e-14)
    assert (on_side | on_cap).all() and on_cap.sum() > 100 and on_side.sum() > 1000
    import pyvista as pv

    closed = pv.PolyData(points, faces=np.c_[np.full(len(triangles), 3), triangles].ravel())
    assert closed.n_open_edges == 0
    assert closed.volume == pytest.approx(np.pi * radius**2 * length, rel=2e-3)


def test_letter_a_files_load_and_cache(truth_dir):
    files = ind.letter_a(truth_dir, 0.3, **LETTER)
    surface = read_surface(files["target"], 2)
    assert len(surface.cells) > 3000  # 0.01 apart along ~52 cm of outline
    feet = surface.points[surface.points[:, 1] < 1e-12]  # clamped: still on y = 0
    assert len(feet) > 300
    top = surface.points[np.abs(surface.points[:, 1] - 9.2) < 1e-12]  # the top edge moved by (0.4, -0.8)
    assert len(top) >= 201 and np.allclose([top[:, 0].min(), top[:, 0].max()], [3.4, 5.4], atol=1e-12)
    stamp = files["target"].stat().st_mtime_ns
    assert ind.letter_a(truth_dir, 0.3, **LETTER) == files
    assert files["target"].stat().st_mtime_ns == stamp


@pytest.mark.slow
def test_letter_a_outline_converges():
    """The letter-A outline displacement under refinement (corner-graded P2): the
    default size (0.16) is within 1e-4 rms of a mesh twice as fine, a sixth of what a
    2 % change of nu moves it, and halving the size shrinks the error."""
    def outline(size, nu=0.25):
        ind.letter_a_model.cache_clear()
        model, edges = ind.letter_a_model(size)
        points = np.concatenate([ind.sample_segment(a, b, 0.02) for a, b in edges])
        motions = {"feet": ind.constant_motion((0, 0)), "top": ind.constant_motion((0.4, -0.8))}
        u = model.solve({"letter": (10.0, nu)}, motions)
        return ind.evaluate(model.basis, u, points)

    def rms(d):
        return np.sqrt(np.mean(np.sum(d**2, axis=1)))

    fine, default, coarse = outline(0.08), outline(0.16), outline(0.32)
    nu_signal = rms(outline(0.16, 0.255) - default)
    assert rms(default - fine) < 1e-4 < nu_signal / 6
    assert rms(default - fine) < 0.5 * rms(coarse - fine)


@pytest.mark.slow
def test_letter_a_agrees_with_the_toolkit(truth_dir, tmp_path):
    """Two independent codes on two different meshes: the toolkit's simulation of the
    letter's outline lies on the scikit-fem target to the toolkit's discretisation
    error (uniform h = 0.15, stress-singular corners: ~4e-4 rms, as scikit-fem's own on
    a uniform h = 0.16 mesh), while nu 0.3 instead of 0.25 moves it 10x farther."""
    from targets import fine_simulation

    target = read_surface(ind.letter_a(truth_dir, 0.25)["target"], 2)
    fine_simulation("letter-a", tmp_path, 0.15, ["materials.letter.nu=0.25"])
    toolkit = read_surface(tmp_path / "target" / "surface.vtp", 2)
    gap = np.linalg.norm(toolkit.points - target.closest(toolkit.points), axis=1)
    assert np.sqrt(np.mean(gap**2)) < 6e-4 and gap.max() < 3e-3
    other = read_surface(ind.letter_a(truth_dir, 0.3)["target"], 2)
    moved = np.linalg.norm(toolkit.points - other.closest(toolkit.points), axis=1)
    assert np.sqrt(np.mean(moved**2)) > 10 * np.sqrt(np.mean(gap**2))


def test_inclusion_scene_and_targets_load(truth_dir):
    """The user-style source scene loads in the toolkit with its groups, straight-sided,
    and its targets are the displaced exact rectangle and circle."""
    from fenics_elasto.model.scene import load_scene

    files = ind.inclusion(truth_dir, 5.0, **INCLUSION)
    scene = load_scene(files["problem"])
    assert {m.name for m in scene.materials} == {"matrix", "inclusion"}
    assert {"bottom", "top", "outline", "interface"} <= set(scene.facet_groups)
    outline, interface = read_surface(files["outline"], 2), read_surface(files["interface"], 2)
    bottom = outline.points[np.abs(outline.points[:, 1] + 3) < 1e-12]
    assert len(bottom) > 400  # clamped: the bottom did not move
    a, b, _, _ = INCLUSION["top"]  # the top moved by (a + b x, c + d x^2), which P2 interpolates exactly
    x = (outline.points[:, 0] - a) / (1 + b)
    on_top = np.abs(outline.points[:, 1] - 3 - ind.inclusion_top_motion(INCLUSION["top"])(np.array([x, 0 * x]))[1]) < 1e-10
    assert on_top.sum() >= 10 / INCLUSION["spacing"]
    radius = np.linalg.norm(interface.points, axis=1)
    assert 0.01 < np.abs(radius - 1.2).max() < 0.5  # the circle deformed


@pytest.mark.slow
def test_phantom_files_motion_and_fiducials(truth_dir):
    """Coarse phantom: the targets load as triangle surfaces and landmarks; the walls
    follow the prescribed motion (to the P2 interpolation error), which is not affine;
    the 10-node tets are read in the right node order; the fiducials sit inside the
    prostate and moved."""
    files = ind.phantom(truth_dir, 50.0, **PHANTOM)
    organs = phantom_organs(0)
    surfaces = ind.phantom_surfaces(organs, PHANTOM["spacing"])
    motions = ind.phantom_motions(organs)
    for group in ("bladder", "prostate_surface", "rectum"):
        target = read_surface(files[group], 3)
        source = surfaces[group][0]
        assert target.points.shape == source.shape
        moved = target.points - source
        if group in motions:  # the walls: moved as prescribed, and no affine map explains it
            assert np.abs(moved - motions[group](source.T).T).max() < 0.01  # 0.15 cm ripple at h = 0.7
            affine, *_ = np.linalg.lstsq(np.c_[source, np.ones(len(source))], target.points, rcond=None)
            misfit = target.points - np.c_[source, np.ones(len(source))] @ affine
            assert np.sqrt(np.mean(np.sum(misfit**2, axis=1))) > 0.03
    mesh = ind.phantom_model(0, PHANTOM["walls"], PHANTOM["prostate"], PHANTOM["far"]).fe.mesh  # cached
    chord = mesh.p[:, mesh.edges]  # the 10-node tet's edge nodes in scikit-fem's order: near their edges
    gap = np.linalg.norm(mesh.doflocs[:, mesh.nvertices:] - chord.mean(axis=1), axis=0)
    bend = gap / np.linalg.norm(chord[:, 0] - chord[:, 1], axis=0)  # (a swapped order: ~0.5 for most)
    assert np.median(bend) < 0.05 and np.percentile(bend, 99) < 0.25  # a few: coarse cells on thin bones
    source, moved = read_landmarks(files["fiducials"], 3)
    prostate = organs["prostate"]
    level = np.sum(((source - prostate["center"]) / prostate["radii"]) ** 2, axis=1)
    assert len(source) == 4 and level.max() < 0.6
    assert (np.linalg.norm(moved - source, axis=1) > 0.01).all()


# --------------------------------------------------------------------------- estimates
# The toolkit's own command line with default settings on targets it did not make
# (scikit-fem P2 on finer, differently built curved meshes, sampled on the exact
# geometry). Before the sag-free matching and the estimator fixes these were off by
# 17-54 % (inclusion) and up to 152 % (stretched top); see docs/validation.md.


def _estimate(problem, out, *settings) -> dict:
    import json

    from fenics_elasto.app.cli import main

    args = ["estimate", str(problem), "--out", str(out)]
    for s in settings:
        args += ["--set", s]
    assert main(args) == 0
    return json.loads((out / "result.json").read_text())


@pytest.mark.slow
@pytest.mark.parametrize("nu", [0.1, 0.4])
def test_letter_a_nu_from_an_independent_target(truth_dir, tmp_path, nu):
    """Measured -0.65 % (nu = 0.1) and -0.24 % (0.4); the bound leaves room for the
    platform, not for a regression to the old -2 %."""
    from fenics_elasto.mesh.builtin import build_scene

    problem = build_scene("letter-a", tmp_path / "source")
    target = ind.letter_a(truth_dir, nu)["target"]
    result = _estimate(problem, tmp_path / "out", f"target.surface='{target}'")
    found = result["materials"]["letter"]["nu"]
    assert abs(found - nu) / nu < 0.012, found
    assert not result["warnings"], result["warnings"]


@pytest.mark.slow
@pytest.mark.parametrize("ratio, top, bound", [(5.0, ind.INCLUSION_TOP, 0.01), (10.0, (0.25, 0.1, -0.3, -0.02), 0.02)])
def test_inclusion_ratio_from_independent_targets(truth_dir, tmp_path, ratio, top, bound):
    """A user's straight-sided scene (h = 0.35) against the exact displaced circle:
    measured +0.19 % (ratio 5) and -0.93 % (ratio 10, top stretched), where the old
    default was +29.6 % and +25.9 %. The 95 % interval is reported and, with the
    residual as noise, must not be so narrow that it excludes a truth this close."""
    files = ind.inclusion(truth_dir, ratio, top=top)
    result = _estimate(files["problem"], tmp_path / "out")
    E = result["materials"]["inclusion"]["E"]
    assert abs(E / 10.0 - ratio) / ratio < bound, E
    low, high = result["uncertainty"]["inclusion.E"]["ci95"]
    assert low < E < high and high - low < 0.2 * E
