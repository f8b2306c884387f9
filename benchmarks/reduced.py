"""Costs of the reduced force bases on the prostate phantom (P2, serial).

    python benchmarks/reduced.py [--size 1.6]

1. The response J of r modes: one factorization plus an r-column block solve
   (MatMatSolve), against r single back-solves in a loop.
2. One inner iteration: reduced Gauss-Newton (dense algebra + closest points, no FE
   solve) against full-space L-BFGS (forward + adjoint back-solves) and the
   full-space response that Gauss-Newton would need.
The accuracy side (Table 1, the rank sweep of Fig. 8) is printed by `make demo`.
"""

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

import fenics_elasto  # noqa: F401
from fenics_elasto.estimate import NestedEstimator, Options
from fenics_elasto.io import write_matched_surfaces
from fenics_elasto.meshing import build_scene
from fenics_elasto.objective import InverseProblem
from fenics_elasto.scene import load_scene
from fenics_elasto.simulate import simulate
from forward import best_of  # benchmarks/ is the script's folder


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", type=float, default=1.6)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        source = build_scene("prostate-phantom", tmp / "source", size=args.size)
        fine = load_scene(build_scene("prostate-phantom", tmp / "fine", size=args.size * 0.8), ["materials.prostate.E=50"])
        write_matched_surfaces(tmp / "target", fine, simulate(fine).u)
        table = ", ".join(f"{g}='{tmp / 'target' / f'surface_{g}.vtp'}'" for g in ("bladder", "prostate_surface", "rectum"))
        problem = InverseProblem(load_scene(source, [f"target={{surfaces={{{table}}}}}"]))
    theta = np.array([40.0])
    model = problem.model
    E, nu = problem.materials(theta)
    start = time.perf_counter()
    factor = model.factorize(E, nu, problem.clamped_boundary)
    factor_time = time.perf_counter() - start
    b, x = model.function("b"), model.function("x")
    b.x.array[:] = 1.0
    solve = best_of(lambda: factor.solve(b.x.petsc_vec, x.x.petsc_vec))
    print(f"phantom P2: {model.num_dofs} dofs, {problem.force_dofs} force dofs, {problem.matched.total} matched nodes; "
          f"factorization {factor_time:.2f} s, back-solve {solve:.4f} s")
    print("| rank r | response J (block solve) s | r back-solves in a loop s | loop / block |")
    print("|---|---|---|---|")
    rng = np.random.default_rng(0)
    for r in (4, 12, 48, 100):
        W = np.linalg.qr(rng.standard_normal((problem.force_dofs, r)))[0]
        block = best_of(lambda: problem.response(theta, W))
        print(f"| {r} | {block:.3f} | {r * solve:.3f} | {r * solve / block:.1f} |")

    est = NestedEstimator(problem, Options(inner="gauss-newton"), say=lambda *_: None)
    d0 = est.matched_boundary_displacement()
    print("\n| inner iteration | seconds | FE solves |")
    print("|---|---|---|")
    for r in (12, 48):
        W = np.linalg.qr(np.c_[d0, rng.standard_normal((problem.force_dofs, r - 1))])[0]
        est = NestedEstimator(problem, Options(inner="gauss-newton", inner_maxiter=1, inner_tol=0.0), say=lambda *_: None,
                              basis=W)
        J = problem.response(theta, W)
        est.anchor = W.T @ d0
        problem.response = lambda *_, J=J: J  # time the iteration alone
        seconds = best_of(lambda: est._gauss_newton(theta, W.T @ d0))
        del problem.response
        print(f"| reduced Gauss-Newton, rank {r} | {seconds:.4f} | 0 |")
    both = best_of(lambda: problem.evaluate_displacement(theta, d0, "both"))
    print(f"| full-space L-BFGS ({problem.force_dofs} unknowns) | {both:.4f} | 2 back-solves + 2 matvecs |")
    full = problem.force_dofs * solve
    print(f"| full-space Gauss-Newton would first need J: {problem.force_dofs} back-solves | ~{full:.1f} | "
          f"{problem.force_dofs} |")


if __name__ == "__main__":
    main()
