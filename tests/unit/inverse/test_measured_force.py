"""A measured force's scale: the rows of a group's force in the wall motion, and the
weighing of its parts by how well the fitted motion determines them."""

import numpy as np
import pytest

from fenics_elasto.inverse.measured_force import MeasuredForce, force_rows, force_scale, group_forces
from fenics_elasto.inverse.objective import InverseProblem
from fenics_elasto.model.scene import load_scene
from targets import letter_case


@pytest.fixture(scope="module")
def letter(tmp_path_factory):
    source, target = letter_case(tmp_path_factory.mktemp("force"), 0.3, 0.3)
    return InverseProblem(load_scene(source, [f"target.surface='{target}'"]))


def test_force_rows_give_the_group_force_of_any_wall_motion(letter):
    """force_rows reads the group's force through the symmetry of the loaded nodes'
    stiffness (gdim solves, not one per wall DOF): for a random wall motion it must be
    the group's summed reaction forces of that motion's solve."""
    problem = letter
    theta = problem.params.initial
    group = problem.scene.loaded[0]
    d = np.random.default_rng(4).normal(size=problem.forward.force_dofs)
    direct = group_forces(problem, problem.forward.reaction_forces(theta, problem.forward.from_boundary(theta, d)))
    via_rows = force_rows(problem, theta, group) @ d
    print(direct[group], via_rows)
    assert np.allclose(via_rows, direct[group], rtol=1e-8, atol=1e-10 * np.abs(direct[group]).max())


def test_the_scale_leans_on_the_parts_of_the_force_the_motion_determines():
    """The pelvis phantom's rectum force (fit units, then measured): its y part, the push
    the surfaces see, is 2.000x; x and z, along and around the tube, are off. Unweighted
    the scale is pulled high and chi2 is large; with the prediction's x and z uncertain
    (its covariance) the scale is the y part's and chi2 small."""
    predicted = {"rectum": np.array([-1.1613, -8.5160, 3.0029])}
    measured = [MeasuredForce("rectum", np.array([-3.4543, -17.0320, 7.8910]), noise=0.3817)]
    plain = force_scale(predicted, measured)
    uncertain = np.diag([4.0, 0.0, 4.0])  # 2 (fit units) in x and z: their parts a few times the noise
    weighed = force_scale(predicted, measured, {"rectum": uncertain})
    print(plain, weighed)
    assert plain.value > 2.05 and plain.chi2 > 20
    assert abs(weighed.value - 2.0) < 0.01 and weighed.chi2 < 3 and weighed.std > plain.std


def test_simulate_reports_the_force_an_estimate_measures(tmp_path):
    """simulate's result holds each driven group's total force (K u over its nodes, the
    clamped ones left out), on the estimate's own definition: the letter's top force fed
    back as a measured force scales E = 10 (fixed) by 1 to 1e-4."""
    import fenics_elasto as fe

    scene = fe.load_scene(fe.build_scene("letter-a", tmp_path / "src"))
    sim = fe.simulate(scene)
    force = sim.record["group_forces"]["top"]
    assert list(sim.record["group_forces"]) == ["top"] and np.linalg.norm(force) > 0
    target = fe.Target(surfaces={"outline": sim.surface("outline")},
                       measured_force={"top": {"value": force, "noise": 0.01 * float(np.linalg.norm(force))}})
    result = fe.estimate(scene, target)
    assert result.record["measured_force"]["scale"] == pytest.approx(1.0, abs=1e-4), result.record["measured_force"]


@pytest.mark.parametrize("measured, words", [
    ([-0.0368, 0.332], ["points against", "not its reaction on the probe"]),  # the reaction: the sign
    ([0.332, 0.0368], ["is zero or across", "frame, axis order and group"]),  # turned 90 degrees: read "against"
    ([0.0, 0.0], ["is zero or across", "frame, axis order and group"]),
])
def test_a_force_the_motion_cannot_scale_to_is_refused_for_its_reason(measured, words):
    """A user's forces against the fitted motion's need [0.0184, -0.168]: the reaction is
    told apart from a force across it or none."""
    from types import SimpleNamespace

    from fenics_elasto.inverse.measured_force import _check_direction
    from fenics_elasto.util.errors import UserError

    problem = SimpleNamespace(scene=SimpleNamespace(path="p.toml"))
    force = MeasuredForce("top", np.array(measured), 0.01)
    with pytest.raises(UserError) as refusal:
        _check_direction(problem, {"top": np.array([0.0184, -0.168])}, [force], -1.0)
    assert all(w in str(refusal.value) for w in words), refusal.value
