"""A displacement field's cube is observed as the model's mean over the cube's own
samples (displacement_field.members, observation.Samples): exact for a field the space
holds, where the model at the samples' mean point is off wherever u curves."""

from __future__ import annotations

import numpy as np
import pytest
from mpi4py import MPI

import dolfinx
from fenics_elasto.inverse import displacement_field
from fenics_elasto.inverse.displacement_field import cubes, members
from fenics_elasto.model.observation import PointProbe, Samples

CUBE = 0.25


def quadratic(p: np.ndarray) -> np.ndarray:
    """A displacement a P2 space on straight cells holds exactly, curving on the cubes' scale."""
    x, y, z = p.T
    return np.stack([x**2 - y * z, 2 * y**2 + x * z, z**2 - 3 * x * y], axis=1)


@pytest.fixture(scope="module")
def space_and_u():
    mesh = dolfinx.mesh.create_unit_cube(MPI.COMM_SELF, 4, 4, 4)
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 2, (3,)))
    u = dolfinx.fem.Function(V)
    u.interpolate(lambda x: quadratic(x.T).T)
    return V, u


def observed(points: np.ndarray) -> tuple[Samples, np.ndarray]:
    """The field's rows and their cube means of the exact field."""
    cube, counts = cubes(points, CUBE)
    samples = members(points, cube, counts, CUBE)
    exact = np.stack([np.bincount(cube, quadratic(points)[:, c]) for c in range(3)], axis=1) / counts[:, None]
    return samples, exact


def test_a_cube_is_the_models_mean_over_its_samples(space_and_u):
    V, u = space_and_u
    points = np.random.default_rng(0).uniform(0.0, 1.0, (3000, 3))
    samples, exact = observed(points)
    assert len(samples.at) == len(points)  # few enough: every sample is evaluated
    means = samples.mean(PointProbe(V, samples.at).values(u.x.array))
    assert np.abs(means - exact).max() < 1e-12
    at_mean_point = PointProbe(V, samples.points).values(u.x.array)
    assert np.abs(at_mean_point - exact).max() > 1e-3  # what observing at the mean point missed


def test_past_the_budget_sub_cube_means_stand_for_the_samples(space_and_u, monkeypatch):
    V, u = space_and_u
    monkeypatch.setattr(displacement_field, "MEMBERS", 2000)
    points = np.random.default_rng(1).uniform(0.0, 1.0, (20000, 3))
    samples, exact = observed(points)
    assert len(samples.at) <= 2000 and len(samples.points) == len(exact)
    assert np.allclose(np.bincount(samples.row, samples.weight), 1.0)  # each row's shares sum to 1
    assert np.allclose(samples.mean(samples.at), samples.points)  # weighed by their samples
    means = samples.mean(PointProbe(V, samples.at).values(u.x.array))
    at_mean_point = PointProbe(V, samples.points).values(u.x.array)
    # sub-cubes of a third of the side: the curvature's error ~9x smaller
    assert np.abs(means - exact).max() < np.abs(at_mean_point - exact).max() / 5


def test_spread_is_the_transpose_of_mean():
    rng = np.random.default_rng(2)
    field = rng.uniform(size=(40, 3))
    samples = Samples.joined([Samples.single(rng.uniform(size=(3, 3))), members(field, *cubes(field, 0.5), 0.5)])
    v, r = rng.standard_normal((len(samples.at), 3)), rng.standard_normal((len(samples.points), 3))
    assert np.isclose(np.sum(samples.mean(v) * r), np.sum(v * samples.spread(r)))
    assert samples.row[:3].tolist() == [0, 1, 2] and samples.row[3:].min() == 3  # the parts one after another


def test_samples_on_the_bodys_surface_count_as_inside(space_and_u):
    """A point file's samples a little outside the mesh's facets -- on the body's true
    surface, which the source's facets approximate -- are observed, within a quarter of
    a cell (a new user's exact field on a rounded box had 45 of 8,000 refused); farther
    out they are refused; an image's voxels outside are dropped, not kept."""
    from fenics_elasto.inverse.displacement_field import DisplacementField, observed_samples
    from fenics_elasto.util.errors import UserError

    V, _ = space_and_u
    mesh = V.mesh  # cells of 0.25 along an edge: a mean cell size of ~0.18
    inside = np.random.default_rng(1).uniform(0.1, 0.9, (200, 3))
    skin = np.array([[1.0 + 0.01, 0.5, 0.5], [0.3, -0.02, 0.6]])  # a hair outside two faces
    points = np.vstack([inside, skin])
    field = observed_samples(DisplacementField(points, quadratic(points), "field.vtp"), mesh, None)
    assert len(field.samples.at) == len(points)  # few enough: each sample is where the model is taken
    dense = observed_samples(DisplacementField(points, quadratic(points), "field.nii.gz", dense=True), mesh, None)
    assert len(dense.samples.at) == len(inside)
    beyond = np.vstack([inside, [[1.2, 0.5, 0.5]]])
    with pytest.raises(UserError, match="1 of 201 points lie outside the body"):
        observed_samples(DisplacementField(beyond, quadratic(beyond), "field.vtp"), mesh, None)


def test_an_image_over_the_body_covers_it_and_a_slipped_one_does_not():
    """The share of the body an image's kept voxels fill: about 1 for a grid over the
    whole body (a 2 x 1 x 1 box, voxels of 0.05 across it and 0.2 of air around), a
    sliver's for the same grid with x and y negated about a corner (an LPS/RAS slip)."""
    mesh = dolfinx.mesh.create_box(MPI.COMM_WORLD, [[0.0, 0.0, 0.0], [2.0, 1.0, 1.0]], [4, 2, 2])
    axes = [np.arange(-0.2, high + 0.2 + 1e-9, 0.05) for high in (2.0, 1.0, 1.0)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    inside = np.all((grid >= 0) & (grid <= [2.0, 1.0, 1.0]), axis=1)
    assert displacement_field._coverage(grid, int(inside.sum()), mesh) == pytest.approx(1.0, rel=0.15)
    slipped = grid * [-1.0, -1.0, 1.0]
    kept = np.all((slipped >= 0) & (slipped <= [2.0, 1.0, 1.0]), axis=1)
    assert displacement_field._coverage(slipped, int(kept.sum()), mesh) < 0.05


def test_nan_voxels_outside_the_body_are_dropped_and_inside_refused():
    """A registration masks its background with NaN: those voxels, outside the body, go
    with the rest of the air (they were refused); one inside is refused, where it lies."""
    from fenics_elasto.inverse.displacement_field import DisplacementField, observed_samples
    from fenics_elasto.util.errors import UserError

    mesh = dolfinx.mesh.create_box(MPI.COMM_WORLD, [[0.0, 0.0, 0.0], [2.0, 1.0, 1.0]], [4, 2, 2])
    axes = [np.arange(-0.2, high + 0.2 + 1e-9, 0.1) for high in (2.0, 1.0, 1.0)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    vectors = 0.01 * grid
    outside = ~np.all((grid > -1e-9) & (grid < [2.0 + 1e-9, 1.0 + 1e-9, 1.0 + 1e-9]), axis=1)
    masked = np.where(outside[:, None], np.nan, vectors)
    kept = observed_samples(DisplacementField(grid, masked, "masked.nii.gz", dense=True), mesh, None)
    plain = observed_samples(DisplacementField(grid, vectors, "plain.nii.gz", dense=True), mesh, None)
    assert np.isfinite(kept.vectors).all() and np.allclose(kept.vectors, plain.vectors)
    inside = masked.copy()
    inside[np.flatnonzero(~outside)[7]] = np.nan
    with pytest.raises(UserError, match=r"holed.nii.gz: 1 voxels inside the body hold NaN"):
        observed_samples(DisplacementField(grid, inside, "holed.nii.gz", dense=True), mesh, None)
