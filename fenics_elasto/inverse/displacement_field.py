"""A dense displacement field as observations of u inside the body (docs/method.md §10).

A registration's field is smooth at its own correlation length: neighbouring samples
carry the same error, not independent ones. Counting each of 10^5 voxels as an
independent observation would make the interval as narrow as the voxels are many, and
the answer would depend on how finely the field was resampled. The rule here:

    the body is cut into cubes (squares in 2D) of side ``correlation`` -- the field's
    correlation length, ``[target] displacement_correlation``; by default the mesh's
    mean cell size, below which the FE model cannot follow the field anyway -- and each
    cube with samples is one observation: its samples' mean displacement against the
    model's mean displacement at the same samples, with the field's noise
    ``displacement_noise``.

The model is averaged where the samples are, not taken at their mean point: u curves
within a cube, and on the pelvis phantom (cells of 1 cm, a stiff prostate) the model at
the mean point put E 7 % low from an exact field, 11 % apart from the same field
observed in cubes of 0.3. Past MEMBERS samples the model's mean is taken at the means
of the finest sub-cubes that keep within it (``members``).

So the estimate does not change when the field is sampled more densely than the
correlation length, and 10^6 samples cost what MEMBERS points cost: one sparse
interpolation operator over them, built once (observation.PointProbe).

Samples outside the body: an image's voxels cover the air around it, so those are
dropped (and said); a point file's samples are where the user put them, so one outside
is bad input. No sample inside at all is a field in another frame or unit.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import ufl
from dolfinx import fem
from mpi4py import MPI

from fenics_elasto.files.displacements import read_displacement
from fenics_elasto.files.images import is_image
from fenics_elasto.model.observation import Samples, farther_than
from fenics_elasto.util.errors import require
from fenics_elasto.util.logs import log


@dataclass
class DisplacementField:
    """Samples of the deformation: at ``points`` the body moved by ``vectors``; ``source``
    names the file in error lines; ``dense``: an image's grid (samples outside the
    body are dropped, not refused)."""

    points: np.ndarray
    vectors: np.ndarray
    source: str = "displacement"
    dense: bool = False
    cell: float = 0.0  # observed_samples: the side of the cubes each observation stands for
    samples: Samples | None = None  # ... and where the model's mean over each cube is taken
    coverage: float | None = None  # ... and for an image, the share of the body its kept voxels fill

    @classmethod
    def read(cls, path: Path, gdim: int, frame: str = "world") -> DisplacementField:
        """The field in a file (files/displacements.py; ``frame``: its vectors' frame),
        named by its path; an image is dense."""
        return cls(*read_displacement(path, gdim, frame), source=str(path), dense=is_image(path))


def mean_cell_size(mesh) -> float:
    """The edge of a regular simplex with the mesh's mean cell volume."""
    tdim = mesh.topology.dim
    volume = mesh.comm.allreduce(fem.assemble_scalar(fem.form(1.0 * ufl.dx(domain=mesh))))
    cells = mesh.topology.index_map(tdim).size_global
    mean = volume / cells
    return float((6.0 * np.sqrt(2.0) * mean) ** (1 / 3) if tdim == 3 else np.sqrt(4.0 * mean / np.sqrt(3.0)))


def cubes(points: np.ndarray, side: float) -> tuple[np.ndarray, np.ndarray]:
    """(the cube each point lies in, the points per cube): cubes of ``side`` from the points' corner."""
    keys = np.floor((points - points.min(axis=0)) / side).astype(np.int64)
    _, cube, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    return cube.ravel(), counts


def _sums(cube: np.ndarray, count: int, a: np.ndarray) -> np.ndarray:
    return np.stack([np.bincount(cube, a[:, c], count) for c in range(a.shape[1])], axis=1)


def _means(cube: np.ndarray, counts: np.ndarray, a: np.ndarray) -> np.ndarray:
    return _sums(cube, len(counts), a) / counts[:, None]


MEMBERS = 50_000  # the most points a field's model means are taken at (PointProbe's set-up: ~0.05 ms a point)


def members(points: np.ndarray, cube: np.ndarray, counts: np.ndarray, length: float) -> Samples:
    """Each cube's row (``cubes(points, length)``) as the mean over its samples: at the
    samples themselves, or, past MEMBERS of them, at the means of the finest sub-cubes
    (side length / k, k = 8 down to 2) that keep within MEMBERS, each weighed by its samples."""
    means = _means(cube, counts, points)
    if len(points) <= MEMBERS:
        return Samples(means, points, cube, 1.0 / counts[cube])
    for k in (8, 6, 4, 3, 2):
        keys = np.column_stack([cube, np.floor((points - points.min(axis=0)) * (k / length)).astype(np.int64)])
        _, sub, weight = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
        if len(weight) <= MEMBERS or k == 2:
            break
    sub = sub.ravel()
    row = np.zeros(len(weight), np.int64)
    row[sub] = cube
    at = _means(sub, weight, points)
    return Samples(means, at, row, weight / counts[row])


# A point file's samples on the body's own surface lie up to the source's geometric error
# outside its facets (straight, or curved on load): 45 of 8,000 samples of an exact field
# on a rounded box's faces were refused at 1e-6 of its size. Within this share of a cell
# they are the body's, observed by their closest cell's polynomial.
ON_SURFACE = 0.25


def _tolerance(field: DisplacementField, mesh, cell: float) -> float:
    """How far outside the mesh a sample still counts as inside: an image's voxels (in the
    air around the body, dropped) by a rounding's width; a point file's by ON_SURFACE cells."""
    if not field.dense:
        return ON_SURFACE * cell
    size = mesh.comm.allreduce(float(np.ptp(mesh.geometry.x, axis=0).max()), op=MPI.MAX)
    return 1e-6 * size


def observed_samples(field: DisplacementField, mesh, correlation: float | None) -> DisplacementField:
    """The field as the estimate observes it: inside the body, one row per correlation
    cube (module docstring)."""
    cell = mean_cell_size(mesh)
    outside = farther_than(mesh, _tolerance(field, mesh, cell), field.points)
    require(not outside.all(), f"{field.source}: no sample lies inside the body (the field's points span "
            f"{np.round(field.points.min(axis=0), 3).tolist()} to {np.round(field.points.max(axis=0), 3).tolist()}): "
            "is it in another frame or unit?")
    if field.dense:
        masked = ~np.isfinite(field.vectors).all(axis=1) & ~outside
        require(not masked.any(), f"{field.source}: {int(masked.sum())} voxels inside the body hold NaN or infinite "
                f"values, the first at {np.round(field.points[np.argmax(masked)], 6).tolist()}")
        points, vectors = field.points[~outside], field.vectors[~outside]
    else:
        first = np.round(field.points[np.argmax(outside)], 6).tolist()
        require(not outside.any(), f"{field.source}: {int(outside.sum())} of {len(outside)} points lie outside "
                f"the body, the first at {first}")
        points, vectors = field.points, field.vectors
    length = correlation or cell
    cube, counts = cubes(points, length)
    means = _means(cube, counts, vectors)
    samples = members(points, cube, counts, length)
    log.info(f"displacement field {field.source}: {len(field.points)} samples, {int((~outside).sum())} inside the "
             f"body, observed as {len(means)} cubes of {length:.3g} (its correlation length"
             f"{'' if correlation else ': the mesh cell size, [target] displacement_correlation sets it'}), "
             f"the model's means over {len(samples.at)} points")
    coverage = _coverage(field.points, int((~outside).sum()), mesh) if field.dense else None
    return DisplacementField(samples.points, means, field.source, cell=length, samples=samples, coverage=coverage)


def _coverage(points: np.ndarray, kept: int, mesh) -> float:
    """The share of the body's volume an image's kept voxels fill (each voxel the image's
    box over its voxel count): about 1 for a field over the whole body, a sliver's share
    where its affine is wrong (a user's RAS/LPS slip kept 180 of 55,016 voxels)."""
    voxel = float(np.prod(np.ptp(points, axis=0))) / max(len(points), 1)
    volume = mesh.comm.allreduce(fem.assemble_scalar(fem.form(fem.Constant(mesh, 1.0) * ufl.dx(domain=mesh))),
                                 op=MPI.SUM)
    return kept * voxel / volume if volume > 0 else 1.0


INFLATION = 2.0  # correlated_over: a cube whose residual sums vary this much more than independent rows' is one error
SCALES = (2, 4, 8, 16)  # ... tried at these multiples of the observation cell
MIN_CUBES = 10  # ... where at least this many cubes hold two rows or more


def correlated_over(points: np.ndarray, residual: np.ndarray, cell: float) -> float | None:
    """The largest cube side (SCALES x ``cell``) over which the field's residual at the
    answer does not average out as independent rows would: the mean over cubes of
    |sum of its rows|^2 / n against the rows' mean |r|^2 -- 1 for independent rows, up to
    n for one error the cube shares (1 + (n - 1) rho) -- at least INFLATION; None if not
    even at twice the cell. Each observation stands for a cube of ``cell`` and is counted
    as independent, so a residual shared beyond them is an error the interval counts too
    often: the pelvis phantom's field with a smooth 1 % error (waves of 3-10 cm, cells of
    0.75 cm) beside noisy surfaces put E -12.6 % off with an interval that missed, and
    held it with displacement_correlation = 6.04, the cube this found. (The part of such
    an error that looks like a change of E leaves no residual at all: this sees the rest.)"""
    r = residual - residual.mean(axis=0)
    found = None
    for scale in SCALES:
        cube, counts = cubes(points, scale * cell)
        shared = counts >= 2
        if shared.sum() < MIN_CUBES:
            break
        kept = (_sums(cube, len(counts), r)[shared] ** 2).sum(axis=1) / counts[shared]
        inflation = float(kept.mean()) / max(float((r[shared[cube]] ** 2).sum(axis=1).mean()), 1e-300)
        if inflation < INFLATION:
            break
        found = scale * cell
    return found
