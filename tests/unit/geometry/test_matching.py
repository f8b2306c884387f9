"""The matched motion that joins the bases (geometry.matching.joined_motion): its affine part
kept, the rest smoothed -- against the continuous Gaussian's analytic gain on a flat, evenly
sampled patch."""

import numpy as np
import pytest

from fenics_elasto.geometry.matching import SMOOTHING_EDGES, SMOOTHING_PER_NOISE, joined_motion

SPACING = 0.5


def patch(n: int = 61) -> np.ndarray:
    """A flat square of n x n points SPACING apart in the plane z = 0."""
    x, y = np.meshgrid(np.arange(n) * SPACING, np.arange(n) * SPACING)
    return np.c_[x.ravel(), y.ravel(), np.zeros(n * n)]


def inner(points: np.ndarray, margin: float) -> np.ndarray:
    """The points at least ``margin`` from the patch's edges (the average is one-sided nearer)."""
    low, high = points[:, :2].min(axis=0) + margin, points[:, :2].max(axis=0) - margin
    return np.all((points[:, :2] >= low) & (points[:, :2] <= high), axis=1)


def test_an_affine_motion_is_kept_exactly_in_each_group():
    points = patch(21)
    groups = (points[:, 0] > 5.0).astype(int)  # two groups with different affine motions
    rng = np.random.default_rng(0)
    u = np.zeros_like(points)
    for g in (0, 1):
        A, b = rng.normal(size=(3, 3)), rng.normal(size=3)
        u[groups == g] = points[groups == g] @ A + b
    assert np.allclose(joined_motion(points, groups, u, noise=0.02), u, atol=1e-12)


def test_a_clean_target_without_an_edge_leaves_the_motion_as_matched():
    points = patch(11)
    u = np.random.default_rng(2).normal(size=points.shape)
    assert np.allclose(joined_motion(points, np.zeros(len(points), int), u, noise=0.0), u, atol=1e-12)


@pytest.mark.parametrize("noise, edge", [(0.05, 0.0), (0.1, 0.0), (0.0, 0.6)])
def test_a_ripple_keeps_the_gaussians_gain_and_the_noise_is_averaged_out(noise, edge):
    """A ripple of wavelength L is scaled by exp(-2 pi^2 l^2 / L^2) by a Gaussian of
    length l; white noise of std s on each point by about spacing / (2 sqrt(pi) l)."""
    points, wavelength = patch(), 10.0
    length = max(SMOOTHING_PER_NOISE * noise, SMOOTHING_EDGES * edge)
    ripple = np.zeros_like(points)
    ripple[:, 2] = np.sin(2 * np.pi * points[:, 0] / wavelength) * np.cos(2 * np.pi * points[:, 1] / wavelength)
    rng = np.random.default_rng(1)
    u = ripple + noise * rng.normal(size=points.shape)
    out = joined_motion(points, np.zeros(len(points), int), u, noise, edge)
    middle = inner(points, 4 * length)
    gain = np.exp(-2 * np.pi**2 * length**2 / wavelength**2 * 2)  # the ripple varies along x and y
    # the affine fit taken out first is smoothed exactly, so the ripple's part beyond it scales by the gain
    homogeneous = np.c_[points, np.ones(len(points))]
    affine = homogeneous @ np.linalg.lstsq(homogeneous, u, rcond=None)[0]
    expected = affine + gain * (ripple - homogeneous @ np.linalg.lstsq(homogeneous, ripple, rcond=None)[0])
    noise_left = noise * SPACING / (2 * np.sqrt(np.pi) * length)
    error = np.abs(out[middle] - expected[middle]).max()
    assert error < 2e-3 + 6 * noise_left  # 2e-3: the weight cut beyond 4 lengths
    if noise:
        assert np.std(out[middle] - expected[middle]) == pytest.approx(noise_left, rel=0.3)
