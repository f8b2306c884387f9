"""Each matched group's fit to its own target (Misfit.group_distances, checks.stray_group):
the distance per group in result.json, and the group whose target fits far worse named."""

import numpy as np

import fenics_elasto  # noqa: F401  (dolfinx_solver first)
from fenics_elasto.geometry.surface import Surface
from fenics_elasto.geometry.targets import SurfaceTerm
from fenics_elasto.inverse.checks import STRAY_GROUP, stray_group
from fenics_elasto.inverse.misfit import Misfit

SQUARE = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]])


def two_groups(lift_a: float, lift_b: float) -> tuple[Misfit, np.ndarray]:
    """Rows of groups a (4 rows) and b (2 rows) above their targets, flat squares at z = 0
    and z = 5, by ``lift_a`` and ``lift_b``: the residual at those rows."""
    square = np.array([[0, 1, 2], [0, 2, 3]])
    targets = [Surface(SQUARE, square), Surface(SQUARE + [0.0, 0.0, 5.0], square)]
    term = SurfaceTerm(targets, np.array([0, 0, 0, 0, 1, 1]))
    y = np.array([[0.2, 0.3, lift_a], [0.7, 0.2, lift_a], [0.5, 0.5, lift_a], [0.3, 0.8, lift_a],
                  [0.5, 0.5, 5.0 + lift_b], [0.2, 0.9, 5.0 - lift_b]])
    misfit = Misfit([(6, term, 1.0)])
    return misfit, misfit.residual(y)


def test_each_group_has_its_own_distance():
    misfit, residual = two_groups(0.01, 0.3)
    fits = misfit.group_distances(residual, ["a", "b"])
    assert abs(fits["a"] - 0.01) < 1e-12
    assert abs(fits["b"] - 0.3) < 1e-12
    surface = misfit.distances(residual, ["a", "b"])["surface"]
    assert surface["groups"] == fits and abs(surface["rms"] - np.sqrt((4 * 0.01**2 + 2 * 0.09) / 6)) < 1e-12


def test_a_group_far_off_its_target_is_named():
    """b fits 30x worse than a: named, with the advice to check its target; 3x worse is not
    a stray, but a refusal may still list every group's fit, the worst first."""
    misfit, residual = two_groups(0.01, 0.3)
    line = stray_group(misfit, residual, ["a", "b"])
    assert line is not None and line.startswith("b fits its target 30x worse") and "check its target" in line
    misfit, residual = two_groups(0.1, 0.3)
    assert 3 < STRAY_GROUP and stray_group(misfit, residual, ["a", "b"]) is None
    assert stray_group(misfit, residual, ["a", "b"], always=True) == "rms distance per group, the worst first: b 0.3, a 0.1"
