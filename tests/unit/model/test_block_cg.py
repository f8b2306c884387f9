"""CG in lock step on one factorization (model/block_cg.py): several material values'
systems solved on the factors of another equal fresh direct solves, within CG's bound
on the steps; one that cannot reach rtol in time is an error, not a wrong answer."""

import numpy as np
import pytest

from fenics_elasto.model.block_cg import LockstepCG, cg_steps_bound
from fenics_elasto.model.elasticity import ElasticModel
from fenics_elasto.model.scene import load_scene
from fenics_elasto.model.simulate import material_values
from fenics_elasto.model.solvers import SolverError, SolverSettings, coefficient_spread


@pytest.fixture(scope="module")
def phantom_p1(scenes):
    """The 3D phantom at P1 (~5k DOFs): three regions, one of them scaled below."""
    return load_scene(scenes["prostate-phantom"], ["degree=1"])


def _systems(scene, model, scales, columns=3):
    """(coefficients, K, loads) of the first region's E scaled by each of ``scales``,
    random loads that are zero on the clamped rows."""
    E, nu = material_values(scene)
    clamped = model.dofs.clamped_dofs(scene.fixed)
    rng = np.random.default_rng(0)
    out = []
    for scale in scales:
        c = model.stiffness.coefficients(E * np.r_[scale, np.ones(len(E) - 1)], nu)
        B = rng.standard_normal((model.dofs.owned, columns))
        B[clamped] = 0.0
        out.append((c, model.solvers.stiffness(c, clamped), B))
    return clamped, out


def test_levels_on_one_factorization_equal_their_own_direct_solves(phantom_p1):
    model = ElasticModel(phantom_p1, SolverSettings(method="direct"))
    clamped, (base, *levels) = _systems(phantom_p1, model, [1.0, 8.0, 0.15])
    factors = model.factorize(base[0], clamped)
    rtol = 1e-8
    solutions, steps = LockstepCG(factors, model.dofs, [(K, B) for _, K, B in levels], rtol).solve(maxiter=100)
    assert model.factorizations == 1
    spread = max(coefficient_spread(c, base[0]) for c, _, _ in levels)
    assert 2 <= steps <= cg_steps_bound(spread, rtol)  # the bound holds, and it is not a direct solve in disguise
    fresh = ElasticModel(phantom_p1, SolverSettings(method="direct"))
    for (c, _, B), X in zip(levels, solutions):
        exact = np.column_stack([_direct(fresh, c, clamped, b) for b in B.T])
        assert np.linalg.norm(X - exact) <= 1e-6 * np.linalg.norm(exact)


def test_too_few_steps_are_an_error(phantom_p1):
    model = ElasticModel(phantom_p1, SolverSettings(method="direct"))
    clamped, (base, level) = _systems(phantom_p1, model, [1.0, 8.0])
    factors = model.factorize(base[0], clamped)
    with pytest.raises(SolverError, match="stopped after 2 steps above rtol"):
        LockstepCG(factors, model.dofs, [level[1:]], 1e-10).solve(maxiter=2)


def _direct(model, c, clamped, b) -> np.ndarray:
    rhs = model.dofs.function("f")
    rhs.x.array[:] = 0.0
    rhs.x.array[: len(b)] = b
    return model.solve(c, clamped, rhs.x.petsc_vec).x.array[: len(b)].copy()
