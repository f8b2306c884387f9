"""Costs of the inverse machinery (serial).

    python benchmarks/gradient.py

1. Phi with its adjoint gradient against Phi alone, and against a finite-difference
   gradient, on the phantom (P2) with unknown boundary forces.
2. Closest-point queries per second: libigl's AABB against VTK's static cell locator.
3. The inner solvers on the letter A at the true nu: iterations, time, Phi*.
"""

import tempfile
import time
from pathlib import Path

import numpy as np

import fenics_elasto  # noqa: F401
from fenics_elasto.inverse.estimator import Estimator
from fenics_elasto.inverse.options import Options
from fenics_elasto.files.writers import write_matched_surfaces
from fenics_elasto.mesh.builtin import build_scene
from fenics_elasto.inverse.objective import InverseProblem
from fenics_elasto.model.scene import load_scene
from fenics_elasto.model.simulate import simulate
from forward import best_of as timed  # benchmarks/ is the script's folder


def target_scene(tmp: Path, name: str, size: float, fine: float, settings=()):
    source = build_scene(name, tmp / "source", size=size)
    fine_scene = load_scene(build_scene(name, tmp / "fine", size=fine), list(settings))
    write_matched_surfaces(tmp / "target", fine_scene, simulate(fine_scene).u)
    return source


def gradient_costs(tmp: Path):
    source = target_scene(tmp, "prostate-phantom", 1.6, 1.2, ["materials.prostate.E=50"])
    table = ", ".join(f"{g}='{tmp / 'target' / f'surface_{g}.vtp'}'" for g in ("bladder", "prostate_surface", "rectum"))
    problem = InverseProblem(load_scene(source, [f"target={{surfaces={{{table}}}}}"]))
    theta = np.array([40.0])
    forces = np.zeros(problem.force_dofs)
    problem.evaluate_forces(theta, forces)  # factorize once: the inner loop re-uses it
    c = problem.forward.coefficients(theta)[0]
    f = problem.model.dofs.function("f")
    solve = timed(lambda: problem.model.solve(c, problem.forward.clamped, f.x.petsc_vec))
    forward = timed(lambda: problem.evaluate_forces(theta, forces))
    both = timed(lambda: problem.evaluate_forces(theta, forces, gradient=True))
    n = problem.force_dofs + len(theta)
    print(f"phantom P2: {problem.model.dofs.num_dofs} dofs, {problem.force_dofs} force dofs, "
          f"{problem.observation.node_count} matched nodes")
    print("| quantity | seconds | ratio |")
    print("|---|---|---|")
    print(f"| one back-solve (factorization re-used) | {solve:.4f} | 1 |")
    print(f"| Phi (forward solve + closest points) | {forward:.4f} | {forward / solve:.1f} x back-solve |")
    print(f"| Phi + adjoint gradient (all {n} components) | {both:.4f} | {both / forward:.2f} x Phi |")
    print(f"| one inner L-BFGS iteration (= Phi + gradient) | {both:.4f} | {both / solve:.1f} x back-solve |")
    print(f"| finite-difference gradient ({n} + 1 evaluations of Phi) | {(n + 1) * forward:.1f} | "
          f"{(n + 1) * forward / both:.0f} x adjoint |")


def closest_point_rates():
    import igl
    import pyvista as pv

    surface = pv.ParametricEllipsoid(3, 2, 1.5, u_res=150, v_res=150, w_res=10).clean().triangulate()
    V = np.asarray(surface.points, float)
    F = surface.faces.reshape(-1, 4)[:, 1:].astype(np.int64)
    print(f"\nclosest points on a {len(F)}-triangle surface (exact point-to-triangle)")
    print("| points | libigl AABB (points/s) | VTK static cell locator (points/s) | max difference |")
    print("|---|---|---|---|")
    rng = np.random.default_rng(0)
    for n in (10_000, 100_000):
        P = V[rng.integers(0, len(V), n)] + rng.normal(scale=0.1, size=(n, 3))
        start = time.perf_counter()
        cp_igl = igl.point_mesh_squared_distance(P, V, F)[2]
        t_igl = time.perf_counter() - start
        start = time.perf_counter()
        cp_vtk = surface.find_closest_cell(P, return_closest_point=True)[1]
        t_vtk = time.perf_counter() - start
        diff = np.abs(np.linalg.norm(cp_igl - P, axis=1) - np.linalg.norm(cp_vtk - P, axis=1)).max()
        print(f"| {n} | {n / t_igl:,.0f} | {n / t_vtk:,.0f} | {diff:.1e} |")


def inner_solvers(tmp: Path):
    source = target_scene(tmp / "letter", "letter-a", 0.4, 0.2, ["materials.letter.nu=0.25"])
    problem = InverseProblem(load_scene(source, [f"target.surface='{tmp / 'letter' / 'target' / 'surface.vtp'}'"]))
    theta = np.array([0.25])
    print(f"\ninner problem at the true nu, letter A ({problem.force_dofs} force dofs)")
    print("| inner solver | iterations | seconds | Phi* |")
    print("|---|---|---|---|")
    for inner in ("gauss-newton", "lbfgs", "lbfgs-forces"):
        est = Estimator(problem, Options(inner=inner, inner_tol=1e-10))
        solver = est.profile.inner
        start = time.perf_counter()
        if inner == "gauss-newton":
            result = solver.solve(theta, est.profile.response, None)
        else:
            result = solver.solve(theta, est.initial_controls(theta))
        print(f"| {inner} | {result.iterations} | {time.perf_counter() - start:.3f} | {result.value:.3e} |")


if __name__ == "__main__":
    with tempfile.TemporaryDirectory() as tmp:
        gradient_costs(Path(tmp))
        closest_point_rates()
        inner_solvers(Path(tmp))
