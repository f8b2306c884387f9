"""Several states' noise (inverse/states.py): each state's rows weigh by the noise its
target states, relative to the smallest, or by the level its residual shows where none
is stated; one stated for some states only is refused."""

import numpy as np
import pytest

from fenics_elasto.inverse.misfit import Misfit, PointTerm, stacked
from fenics_elasto.inverse.states import LEVEL_FLOOR, States
from fenics_elasto.util.errors import UserError


def states(*noises) -> States:
    specs = [{} if n is None else {"noise": n} for n in noises]
    misfits = [Misfit([(2, PointTerm(np.zeros((2, 2))), 1.0)]) for _ in noises]
    return States([f"s{i}" for i in range(len(noises))], misfits, specs)


def test_states_weigh_by_their_stated_noise():
    s = states(0.02, 0.01, 0.04)
    assert s.noise == 0.01
    assert np.allclose(s.weights, [0.25, 1.0, 1 / 16])
    assert np.allclose(stacked(s.misfits, s.weights).weights, [0.25, 0.25, 1.0, 1.0, 1 / 16, 1 / 16])
    one = states(0.3)
    assert one.noise == 0.3 and one.weights.tolist() == [1.0]


def test_without_stated_noise_the_states_weigh_alike():
    s = states(None, None)
    assert s.noise is None and s.weights.tolist() == [1.0, 1.0]


def test_noise_stated_for_some_states_only_is_refused():
    with pytest.raises(UserError, match=r"not for \['s1'\]"):
        _ = states(0.01, None).weights


def test_without_stated_noise_each_state_has_its_residual_level():
    """The level is the rms of a state's own rows (its misfit's weights: here a landmark
    weight of 4 doubles it), floored at LEVEL_FLOOR x the largest; the weights follow."""
    s = states(None, None, None)
    s.misfits[1].weights[:] = 4.0
    residual = np.zeros((6, 2))
    residual[0:2, 0] = 0.01  # state 0: 0.01 in x at both rows
    residual[2:4] = [[0.03, 0.04], [0.0, 0.05]]  # state 1: 0.05 at both rows, weighed 4x
    levels = s.residual_levels(residual)  # state 2 fits exactly
    assert np.allclose(levels, [0.01, 0.1, LEVEL_FLOOR * 0.1])
    s.estimated = levels
    assert np.allclose(s.weights, (LEVEL_FLOOR * 0.1 / levels) ** 2)
    assert s.weights[2] == 1.0


def test_reweighing_states_is_undone_if_interrupted():
    """weigh_by_residuals: the stacked misfit's rows take each state's weight, and an
    interrupt while Phi* is solved again leaves the weights the best value was solved with."""
    from types import SimpleNamespace

    from fenics_elasto.inverse.states import weigh_by_residuals

    s = states(None, None)
    misfit = stacked(s.misfits, s.weights)
    residual = np.zeros((4, 2))
    residual[0:2, 0], residual[2:4, 0] = 0.01, 0.1
    best = SimpleNamespace(evaluation=SimpleNamespace(residual=residual))

    def interrupted(theta, stage):
        assert np.allclose(misfit.weights, [1.0, 1.0, 0.01, 0.01])  # weighed while it solves
        raise KeyboardInterrupt

    profile = SimpleNamespace(best=lambda: best, best_theta=lambda: np.ones(1), start_over=interrupted)
    problem = SimpleNamespace(states=s, misfit=misfit)
    with pytest.raises(KeyboardInterrupt):
        weigh_by_residuals(problem, profile)
    assert s.estimated is None and misfit.weights.tolist() == [1.0] * 4
    profile.start_over = lambda theta, stage: None
    assert weigh_by_residuals(problem, profile) and np.allclose(s.weights, [1.0, 0.01])
    assert not weigh_by_residuals(problem, profile)  # settled: the same residual, the same weights
    fresh = states(None, None)  # levels 10x apart: before the outer loop (EARLY_SPREAD) they are left alike
    assert not weigh_by_residuals(SimpleNamespace(states=fresh, misfit=stacked(fresh.misfits)), profile, spread=20.0)
    assert fresh.estimated is None
