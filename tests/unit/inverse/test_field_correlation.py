"""A displacement field's residual that is one error over many of its observation cells
is found (displacement_field.correlated_over), and independent errors are not."""

from __future__ import annotations

import numpy as np
import pytest

from fenics_elasto.inverse.displacement_field import correlated_over, cubes

CELL = 0.5


def samples(count: int = 20000, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0.0, 10.0, (count, 3))


def cube_means(points: np.ndarray, vectors: np.ndarray, side: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(mean points, mean vectors, sample counts), one row per occupied cube of ``side``."""
    cube, counts = cubes(points, side)
    mean = lambda a: np.stack([np.bincount(cube, a[:, c]) for c in range(a.shape[1])], axis=1) / counts[:, None]  # noqa: E731
    return mean(points), mean(vectors), counts


def cell_means(points: np.ndarray, error: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The observations as the estimate makes them: one per cube of CELL."""
    p, e, _ = cube_means(points, error, CELL)
    return p, e


def wave(points: np.ndarray, wavelength: float) -> np.ndarray:
    k = 2 * np.pi / wavelength
    return np.stack([np.sin(k * points[:, 0] + 1.0), np.cos(k * points[:, 1]), np.sin(k * points[:, 2] + 2.0)], axis=1)


def test_independent_errors_per_cell_are_not_shared():
    points = samples()
    p, e = cell_means(points, np.random.default_rng(1).standard_normal((len(points), 3)))
    assert correlated_over(p, e, CELL) is None


@pytest.mark.parametrize("wavelength, at_least", [(6.0, 2 * CELL), (20.0, 4 * CELL)])
def test_a_smooth_error_is_shared_over_cubes_of_its_own_size(wavelength, at_least):
    """A registration's kind of error, smooth over several cells (plus a little white
    noise): shared over cubes that grow with its wavelength."""
    points = samples()
    error = wave(points, wavelength) + 0.1 * np.random.default_rng(2).standard_normal((len(points), 3))
    p, e = cell_means(points, error)
    length = correlated_over(p, e, CELL)
    assert length is not None and length >= at_least, length
    assert length <= wavelength, length  # not beyond its own waves


def test_cubes_group_the_samples_by_the_cube_they_lie_in():
    points = np.array([[0.1, 0.1, 0.1], [0.2, 0.3, 0.1], [0.7, 0.1, 0.1]])
    vectors = np.array([[1.0, 0.0, 0.0], [3.0, 0.0, 0.0], [5.0, 1.0, 0.0]])
    cube, _ = cubes(points, 0.5)
    assert cube[0] == cube[1] != cube[2]
    p, v, counts = cube_means(points, vectors, 0.5)
    order = np.argsort(p[:, 0])
    assert counts[order].tolist() == [2, 1]
    assert np.allclose(v[order], [[2.0, 0.0, 0.0], [5.0, 1.0, 0.0]])
    assert np.allclose(p[order][0], [0.15, 0.2, 0.1])
