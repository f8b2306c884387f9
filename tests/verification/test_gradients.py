"""Hand-derived adjoint gradients: Taylor remainders shrink at rate 2, and they agree
with central finite differences, for forces, boundary displacements, E and nu, in 2D
(plane strain and stress) and 3D."""

import numpy as np
import pytest

from fenics_elasto.mesh.builtin import build_scene
from fenics_elasto.inverse.objective import InverseProblem
from fenics_elasto.model.scene import load_scene
from targets import fine_simulation, landmarks_for, letter_case, taylor_rates


def check(problem, theta, controls, coordinates, rng, eps_controls, eps_theta):
    evaluate = problem.evaluate_forces if coordinates == "forces" else problem.evaluate_displacement
    ev = evaluate(theta, controls, "both")
    d_controls = rng.standard_normal(controls.shape)
    rates, rem = taylor_rates(lambda c: evaluate(theta, c).phi, controls, d_controls, ev.grad_controls, eps_controls)
    assert rates[-2:].min() > 1.8, (coordinates, rates, rem)
    d_theta = rng.uniform(0.5, 1.0, theta.shape) * theta
    rates, rem = taylor_rates(lambda t: evaluate(t, controls).phi, theta, d_theta, ev.grad_theta, eps_theta)
    assert rates[-2:].min() > 1.8, ("theta", rates, rem)
    for k in range(len(theta)):  # each material derivative against central differences
        h = 1e-5 * theta[k]  # the phantom's nu: 1e-6 left roundoff of 1.2e-5 (1e-5: 2.4e-7; its E 4.5e-10)
        step = np.zeros_like(theta)
        step[k] = h
        fd = (evaluate(theta + step, controls).phi - evaluate(theta - step, controls).phi) / (2 * h)
        assert abs(fd - ev.grad_theta[k]) <= 1e-5 * abs(fd) + 1e-12, (k, fd, ev.grad_theta[k])


@pytest.fixture(scope="module")
def letter(tmp_path_factory):
    return letter_case(tmp_path_factory.mktemp("letter"), 0.3, 0.25)


@pytest.mark.parametrize("coordinates", ["forces", "displacement"])
def test_letter_a_plane_strain_surface_target(letter, coordinates):
    source, target = letter
    scene = load_scene(source, [f"target.surface='{target}'"])
    problem = InverseProblem(scene)
    rng = np.random.default_rng(1)
    scale = 1e-2 if coordinates == "forces" else 1e-1
    controls = scale * rng.standard_normal(problem.force_dofs)
    check(problem, np.array([0.3]), controls, coordinates, rng, eps_controls=scale, eps_theta=0.1)


def test_inclusion_plane_stress_two_parameters(tmp_path):
    """E of the inclusion and nu of the matrix at once, plane stress, landmark target."""
    problem_path = build_scene("inclusion", tmp_path / "source", size=1.0)
    _, sim = fine_simulation("inclusion", tmp_path / "fine", 0.6, ["plane='stress'"])
    landmarks = landmarks_for(problem_path, sim, tmp_path / "landmarks.csv")
    scene = load_scene(problem_path, ["plane='stress'", f"target={{landmarks='{landmarks}'}}",
                                      "materials.matrix.nu={estimate=true, initial=0.3, bounds=[0.0, 0.45]}"])
    problem = InverseProblem(scene)
    assert problem.params.names == [("matrix", "nu"), ("inclusion", "E")]  # regions in tag order
    rng = np.random.default_rng(2)
    controls = 0.1 * rng.standard_normal(problem.force_dofs)
    check(problem, np.array([0.25, 40.0]), controls, "displacement", rng, eps_controls=0.1, eps_theta=0.1)


def test_phantom_3d(tmp_path):
    """3D, two materials (prostate E, tissue nu), P1, per-organ target surfaces."""
    source = build_scene("prostate-phantom", tmp_path / "source", size=1.6)
    fine_simulation("prostate-phantom", tmp_path / "fine", 1.3, ["degree=1", "materials.prostate.E=60"])
    surfaces = {g: str(tmp_path / "fine" / "target" / f"surface_{g}.vtp") for g in ("bladder", "prostate_surface", "rectum")}
    table = ", ".join(f"{g}='{f}'" for g, f in surfaces.items())
    scene = load_scene(source, ["degree=1", f"target={{surfaces={{{table}}}}}",
                                "materials.tissue.nu={estimate=true, initial=0.4, bounds=[0.1, 0.49]}"])
    problem = InverseProblem(scene)
    rng = np.random.default_rng(3)
    controls = 0.05 * rng.standard_normal(problem.force_dofs)
    check(problem, np.array([40.0, 0.42]), controls, "displacement", rng, eps_controls=0.05, eps_theta=0.01)


def test_response_matrix_is_the_linearised_forward_map(letter):
    """J q equals the matched displacement of the FE solve with boundary displacement W q."""
    source, target = letter
    problem = InverseProblem(load_scene(source, [f"target.surface='{target}'"]))
    rng = np.random.default_rng(4)
    theta = np.array([0.33])
    W = np.linalg.qr(rng.standard_normal((problem.force_dofs, 5)))[0]
    q = rng.standard_normal(5)
    J = problem.response(theta, W)
    u = problem.evaluate_displacement(theta, W @ q).u
    moved = problem.observation.values(u)
    assert np.abs(np.einsum("ldr,r->ld", J, q) - moved).max() < 1e-12 * max(1.0, np.abs(moved).max())
    assert np.abs(moved).max() > 1e-3
