"""Costs and pay-off of the reduced force bases on the prostate phantom (P2, serial).

    python benchmarks/reduced.py [--size 1.6] [--skip-tables]

1. The response J of r modes: one factorization plus an r-column block solve
   (MatMatSolve), against r single back-solves in a loop.
2. One inner iteration: reduced Gauss-Newton (dense algebra + closest points, no FE
   solve) against full-space L-BFGS (forward + adjoint back-solves) and the
   full-space response that Gauss-Newton would need.
3. Table-1-like: whole estimates, full force space against reduced (rank 12) on the
   same targets, for true prostate E 25/50/75 (landmark targets, where both spaces
   determine E), plus the paper's own full-space method (L-BFGS on raw nodal forces)
   and the full space on surface targets, both capped.
4. Fig-8-like: rank against E error, inner iterations and time (surface targets).
The same study at the demo's scale is `make demo` (demos/prostate_elastography.py).
"""

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

import fenics_elasto  # noqa: F401
from fenics_elasto.inverse.estimator import Estimator, surface_matched_start
from fenics_elasto.inverse.options import Options
from fenics_elasto.files.writers import write_matched_surfaces
from fenics_elasto.mesh.builtin import build_scene
from fenics_elasto.inverse.objective import InverseProblem
from fenics_elasto.model.scene import load_scene
from fenics_elasto.model.simulate import simulate
from fenics_elasto.inverse.surrogate import MaterialSurrogate
from forward import best_of  # benchmarks/ is the script's folder

from fenics_elasto.app.study import FINE, TRUE_E, rank_sweep, rank_table, recovered, run_case, speedup_table

from fenics_elasto.app.study import simulate_examples, simulate_targets  # noqa: E402
from fenics_elasto.inverse.reduction.bases import train_bases  # noqa: E402
from fenics_elasto.model.responses import response_block


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", type=float, default=1.6)
    parser.add_argument("--skip-tables", action="store_true", help="costs only (1, 2), not the whole estimates")
    args = parser.parse_args()
    costs(args.size)
    if not args.skip_tables:
        with tempfile.TemporaryDirectory() as tmp:
            estimates(Path(tmp), args.size)


def costs(size: float) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        source = build_scene("prostate-phantom", tmp / "source", size=size)
        fine = load_scene(build_scene("prostate-phantom", tmp / "fine", size=size * 0.8), ["materials.prostate.E=50"])
        write_matched_surfaces(tmp / "target", fine, simulate(fine).u)
        table = ", ".join(f"{g}='{tmp / 'target' / f'surface_{g}.vtp'}'" for g in ("bladder", "prostate_surface", "rectum"))
        problem = InverseProblem(load_scene(source, [f"target={{surfaces={{{table}}}}}"]))
    theta = np.array([40.0])
    model = problem.model
    model.stiffness.terms  # assembled once per mesh: not part of the factorization
    start = time.perf_counter()
    factor = model.factorize(problem.forward.coefficients(theta)[0], problem.forward.clamped_boundary)
    factor_time = time.perf_counter() - start
    b, x = model.dofs.function("b"), model.dofs.function("x")
    b.x.array[:] = 1.0
    solve = best_of(lambda: factor.solve(b.x.petsc_vec, x.x.petsc_vec))
    print(f"phantom P2: {model.dofs.num_dofs} dofs, {problem.force_dofs} force dofs, "
          f"{problem.observation.node_count} matched nodes; "
          f"factorization {factor_time:.2f} s, back-solve {solve:.4f} s")
    print("| rank r | response J (block solve) s | r back-solves in a loop s | loop / block |")
    print("|---|---|---|---|")
    rng = np.random.default_rng(0)
    for r in (4, 12, 48, 100):
        W = np.linalg.qr(rng.standard_normal((problem.force_dofs, r)))[0]
        block = best_of(lambda: problem.response(theta, W))
        print(f"| {r} | {block:.3f} | {r * solve:.3f} | {r * solve / block:.1f} |")

    d0 = surface_matched_start(problem)
    print("\n| inner iteration | seconds | FE solves |")
    print("|---|---|---|")
    for r in (12, 48):
        W = np.linalg.qr(np.c_[d0, rng.standard_normal((problem.force_dofs, r - 1))])[0]
        est = Estimator(problem, Options(inner="gauss-newton", inner_maxiter=1, inner_tol=0.0, surrogate=False), basis=W)
        J = problem.response(theta, W)
        seconds = best_of(lambda: est.profile.inner.fit(J))
        print(f"| reduced Gauss-Newton, rank {r} | {seconds:.4f} | 0 |")
        surrogate = MaterialSurrogate(problem, W)
        for E_snap in (4.6, 24.5, 130.0):  # the phantom's scan
            surrogate.add([E_snap], response_block(problem.forward, [E_snap], W))
        seconds = best_of(lambda: surrogate.response(theta))
        print(f"| J(theta) and dJ/dtheta from the surrogate ({surrogate.size} directions), rank {r} | {seconds:.4f} | 0 |")
    both = best_of(lambda: problem.evaluate_displacement(theta, d0, gradient=True))
    print(f"| full-space L-BFGS ({problem.force_dofs} unknowns) | {both:.4f} | 2 back-solves + 2 matvecs |")
    full = problem.force_dofs * solve
    print(f"| full-space Gauss-Newton would first need J: {problem.force_dofs} back-solves | ~{full:.1f} | "
          f"{problem.force_dofs} |")



def estimates(tmp: Path, size: float) -> None:
    source = build_scene("prostate-phantom", tmp / "source", size=size)
    examples = simulate_examples(source, tmp / "examples", 12)
    trainer = InverseProblem(load_scene(source), target=False)
    W = train_bases(trainer, examples, rank=12).W
    targets = simulate_targets(tmp / "targets", TRUE_E, FINE, source=source)
    rows = []
    for E in TRUE_E:
        settings = targets[E].settings(landmarks=True)
        rows.append((E, run_case(source, settings), run_case(source, settings, W)))
        print(f"  E = {E:g}: full {recovered(rows[-1][1]):.2f} ({rows[-1][1]['seconds']:.1f} s), "
              f"reduced {recovered(rows[-1][2]):.2f} ({rows[-1][2]['seconds']:.1f} s)", flush=True)
    print("\n" + "\n".join(speedup_table(rows, trainer.force_dofs, 12)))

    E = 50.0
    reduced = {"landmarks": rows[TRUE_E.index(E)][2], "surfaces": run_case(source, targets[E].settings(landmarks=False), W)}
    capped = Options(inner_maxiter=100, outer_maxiter=6, allow_undetermined=True)  # it is refused otherwise
    others = [("paper's full space: L-BFGS on raw forces, landmarks", "landmarks",
               run_case(source, targets[E].settings(landmarks=True), options=Options(inner="lbfgs-forces", inner_maxiter=100,
                                                                         outer_maxiter=6))),
              ("full space, surfaces (E not determined)", "surfaces",
               run_case(source, targets[E].settings(landmarks=False), options=capped))]
    print(f"\nOther full-space estimates (true E = {E:g}; capped at 100 inner / 6 outer iterations), "
          "against the reduced estimate on the same target")
    print("| method | target | E | error % | seconds | outer/inner | reduced E | reduced s | speed-up |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, kind, r in others:
        red = reduced[kind]
        print(f"| {name} | {kind} | {recovered(r):.2f} | {100 * abs(recovered(r) - E) / E:.1f} | {r['seconds']:.1f} | "
              f"{r['iterations']['outer']}/{r['iterations']['inner']} | {recovered(red):.2f} | {red['seconds']:.1f} | "
              f"{r['seconds'] / red['seconds']:.1f}x |")

    print(f"\nFig-8-like: rank of the bases (surface target, true E = {E:g})")
    print("\n".join(rank_table(rank_sweep(source, targets[E].settings(landmarks=False), W, (1, 2, 4, 8, 12), E))))


if __name__ == "__main__":
    main()
