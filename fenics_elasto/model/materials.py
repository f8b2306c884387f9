"""Material constants: Lame coefficients from (E, nu), and their derivatives."""

from __future__ import annotations

import numpy as np
import ufl


def lame(E, nu, plane: str = "strain"):
    """(mu, lambda) from Young's modulus and Poisson's ratio; plane stress uses lambda*."""
    E, nu = np.asarray(E, float), np.asarray(nu, float)
    mu = E / (2 * (1 + nu))
    lam = E * nu / (1 - nu**2) if plane == "stress" else E * nu / ((1 + nu) * (1 - 2 * nu))
    return mu, lam


def lame_jacobian(E, nu, plane: str = "strain"):
    """Partial derivatives (dmu/dE, dmu/dnu, dlam/dE, dlam/dnu)."""
    E, nu = np.asarray(E, float), np.asarray(nu, float)
    dmu_dE = 1 / (2 * (1 + nu))
    dmu_dnu = -E / (2 * (1 + nu) ** 2)
    if plane == "stress":
        dlam_dE = nu / (1 - nu**2)
        dlam_dnu = E * (1 + nu**2) / (1 - nu**2) ** 2
    else:
        dlam_dE = nu / ((1 + nu) * (1 - 2 * nu))
        dlam_dnu = E * (1 + 2 * nu**2) / ((1 + nu) * (1 - 2 * nu)) ** 2
    return dmu_dE, dmu_dnu, dlam_dE, dlam_dnu


def epsilon(u):
    return ufl.sym(ufl.grad(u))
