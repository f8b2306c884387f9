"""Written surfaces fit for reuse as targets: closed groups closed, consistently
oriented, outward, their points shared (not merged by position), under MPI as in serial.

Independent truths: Euler's formula (a closed genus-0 triangulation has T/2 + 2
points), the volume of the phantom's ellipsoids and cylinder, and an affine
displacement, which scales every enclosed volume by its determinant exactly.
"""

import numpy as np
import pytest

import dolfinx
from conftest import run_cli
from fenics_elasto.files.writers import surface
from fenics_elasto.mesh.builtin import phantom_organs
from fenics_elasto.model.scene import load_scene
from fenics_elasto.geometry.tessellate import MAX_TRIANGLES, PIECES, default_pieces, orient_outward

SCALE = 0.1  # the affine field u = SCALE (x - c): volumes grow by (1 + SCALE)^3


@pytest.fixture(scope="module")
def phantom(scenes):
    scene = load_scene(scenes["prostate-phantom"])
    V = dolfinx.fem.functionspace(scene.mesh, ("Lagrange", 2, (3,)))
    u = dolfinx.fem.Function(V)
    centre = np.array(phantom_organs(0)["bladder"]["center"])
    u.interpolate(lambda x: SCALE * (x - centre[:, None]))
    return scene, u


def triangles(mesh) -> np.ndarray:
    return mesh.faces.reshape(-1, 4)[:, 1:]


def signed_volume(points: np.ndarray, tris: np.ndarray) -> float:
    p = points - points.mean(axis=0)
    return float(np.einsum("ij,ij->i", p[tris[:, 0]], np.cross(p[tris[:, 1]], p[tris[:, 2]])).sum() / 6)


def assert_closed_and_consistent(mesh, group):
    tris = triangles(mesh)
    directed = tris[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    assert mesh.n_open_edges == 0, group
    # consistent: every edge is crossed once each way, so no directed edge repeats
    assert len(np.unique(directed, axis=0)) == len(directed), group
    assert mesh.n_points == len(tris) // 2 + 2, group  # Euler, genus 0: shared points, none twice


@pytest.mark.parametrize("group, volume", [
    ("prostate_surface", lambda o: 4 / 3 * np.pi * np.prod(o["prostate"]["radii"])),
    ("bladder", lambda o: 4 / 3 * np.pi * np.prod(o["bladder"]["radii"])),
    ("rectum", lambda o: np.pi * o["rectum"]["radius"] ** 2 * o["rectum"]["length"]),
])
def test_closed_groups_are_closed_and_outward(phantom, group, volume):
    scene, u = phantom
    organs = phantom_organs(0)
    reference = surface(u, scene.facet_groups[group], deformed=False)
    deformed = surface(u, scene.facet_groups[group])
    assert reference.n_cells == PIECES**2 * len(scene.facet_groups[group])
    for mesh in (reference, deformed):
        assert_closed_and_consistent(mesh, group)
    v0 = signed_volume(np.asarray(reference.points), triangles(reference))
    v1 = signed_volume(np.asarray(deformed.points), triangles(deformed))
    assert v0 == pytest.approx(volume(organs), rel=0.01)  # outward (> 0), and the organ's volume
    assert v1 / v0 == pytest.approx((1 + SCALE) ** 3, rel=1e-12)  # the affine map, exactly


def test_outer_boundary_is_outward(phantom):
    scene, u = phantom
    skin = surface(u, scene.facet_groups["skin"], deformed=False)
    assert_closed_and_consistent(skin, "skin")
    assert signed_volume(np.asarray(skin.points), triangles(skin)) == pytest.approx(12.0 * 10.0 * 10.0, rel=1e-9)


def test_open_exterior_group_points_out_of_the_body(phantom):
    """An open group on the boundary (the box's top face) faces away from the body."""
    scene, u = phantom
    top = scene.facet_groups["skin"]
    mesh = scene.mesh
    x = dolfinx.mesh.compute_midpoints(mesh, 2, top)
    patch = surface(u, top[x[:, 2] > 4.99], deformed=False)
    assert patch.n_open_edges > 0
    normals = patch.compute_normals(cell_normals=True, point_normals=False, auto_orient_normals=False)
    assert np.allclose(normals.cell_data["Normals"], [0.0, 0.0, 1.0], atol=1e-9)


def test_letter_outline_is_closed_loops(scenes):
    scene = load_scene(scenes["letter-a"])
    V = dolfinx.fem.functionspace(scene.mesh, ("Lagrange", 2, (2,)))
    outline = surface(dolfinx.fem.Function(V), scene.facet_groups["outline"])
    segments = outline.lines.reshape(-1, 3)[:, 1:]
    assert len(segments) == len(scene.facet_groups["outline"])
    assert np.all(np.bincount(segments.ravel()) == 2)  # every point joins two segments: closed loops
    assert outline.n_points == len(segments)


def test_orientation_repairs_a_shuffled_closed_surface():
    """orient_outward on an octahedron with random triangles flipped: outward again."""
    points = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
    tris = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    flipped = tris.copy()
    flipped[[1, 4, 6]] = flipped[[1, 4, 6]][:, ::-1]
    fixed = orient_outward(points, flipped[:, ::-1].copy())
    assert signed_volume(points, fixed) == pytest.approx(4 / 3)  # the octahedron's volume, positive
    assert {tuple(np.roll(t, -np.argmin(t))) for t in fixed} == {tuple(np.roll(t, -np.argmin(t))) for t in tris}


def test_fewer_pieces_on_large_surfaces():
    assert default_pieces(1000) == PIECES
    assert default_pieces(MAX_TRIANGLES // 4) == 2
    assert default_pieces(10 * MAX_TRIANGLES) == 1
    assert all(default_pieces(n) ** 2 * n <= MAX_TRIANGLES for n in (10**5, 3 * 10**5, 10**6))


@pytest.mark.slow
def test_two_ranks_write_the_serial_surfaces(scenes, tmp_path):
    """Under MPI each rank sends its own facets; rank 0 numbers the shared points."""
    import pyvista as pv

    for ranks in (1, 2):
        proc = run_cli("simulate", scenes["prostate-phantom"], "--out", tmp_path / f"r{ranks}", mpi=ranks)
        assert proc.returncode == 0, proc.stderr
    for name in ("surface_prostate_surface.vtp", "surface.vtp"):
        one, two = (pv.read(tmp_path / f"r{ranks}" / name) for ranks in (1, 2))
        assert (one.n_points, one.n_cells, one.n_open_edges) == (two.n_points, two.n_cells, 0)
        a, b = (np.asarray(m.points)[np.lexsort(np.round(m.points, 9).T)] for m in (one, two))
        assert np.abs(a - b).max() < 1e-12
        assert signed_volume(np.asarray(one.points), triangles(one)) == pytest.approx(
            signed_volume(np.asarray(two.points), triangles(two)), rel=1e-12)
