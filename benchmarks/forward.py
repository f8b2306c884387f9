"""Forward-model costs on the prostate phantom at three sizes (P2, serial).

    python benchmarks/forward.py [--sizes 1.6 1.3 1.0] [--repeat 3]

Prints DOFs, the one-off assembly of the per-material matrices, a direct assembly of
K, K formed as a linear combination, MUMPS LU and Cholesky factorizations (analysis
included), one back-solve (with its residual check), and a 100-column block solve through
one factorization. benchmarks/solvers.py goes further: analysis reuse, BLR, CG + AMG.
"""

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

import fenics_elasto  # noqa: F401  (imports dolfinx_solver before petsc4py)
import ufl

import dolfinx.fem.petsc
from dolfinx import fem
from fenics_elasto.model.elasticity import ElasticModel
from fenics_elasto.model.materials import epsilon
from fenics_elasto.model.stiffness import stiffness_quadrature
from fenics_elasto.mesh.builtin import build_scene
from fenics_elasto.model.scene import load_scene
from fenics_elasto.model.simulate import material_values
from fenics_elasto.model.solvers import DirectSolver, SolverSettings, SolverStats


def best_of(work, repeat=3):
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        work()
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def direct_assembly(model, E, nu):
    """K assembled from scratch with per-cell Lame coefficients (what caching avoids)."""
    scene = model.scene
    mu, lam = model.stiffness.coefficients(E, nu).reshape(-1, 2).T
    Q = fem.functionspace(scene.mesh, ("DG", 0))
    mu_f, lam_f = fem.Function(Q), fem.Function(Q)
    for m, material in enumerate(scene.materials):
        cells = Q.dofmap.list[scene.cell_tags.find(material.tag), 0]
        mu_f.x.array[cells], lam_f.x.array[cells] = mu[m], lam[m]
    u, v = ufl.TrialFunction(model.dofs.V), ufl.TestFunction(model.dofs.V)
    dx = ufl.dx(metadata=stiffness_quadrature(model.dofs.V))  # the model's rule: like is compared with like
    form = fem.form(2 * mu_f * ufl.inner(epsilon(u), epsilon(v)) * dx + lam_f * ufl.div(u) * ufl.div(v) * dx)

    def assemble():
        K = dolfinx.fem.petsc.assemble_matrix(form)
        K.assemble()
        K.destroy()

    return assemble


def measure(h, repeat):
    with tempfile.TemporaryDirectory() as tmp:
        scene = load_scene(build_scene("prostate-phantom", Path(tmp), size=h))
        start = time.perf_counter()
        model = ElasticModel(scene)
        model.stiffness.terms  # assembled on first use
        setup = time.perf_counter() - start
    E, nu = material_values(scene)
    c = model.stiffness.coefficients(E, nu)
    clamped = model.dofs.clamped_dofs(scene.fixed)
    row = {"h": h, "dofs": model.dofs.num_dofs, "material matrices (once)": setup}
    row["assemble K"] = best_of(direct_assembly(model, E, nu), repeat)
    row["K by lin. comb."] = best_of(lambda: model.stiffness.matrix(c).destroy(), repeat)

    def factorize(kind):
        settings = SolverSettings(method="direct", factor=kind)
        return DirectSolver(model.stiffness.constrained(c, clamped), clamped, settings, SolverStats("direct"))

    for kind in ("lu", "cholesky"):
        row[f"{kind.upper()} factor"] = best_of(lambda: factorize(kind).destroy(), repeat)
    factor = factorize("lu")
    b, x = factor.K.createVecRight(), factor.K.createVecRight()
    b.setRandom()
    b.array[clamped] = 0.0
    row["back-solve"] = best_of(lambda: factor.solve(b, x), repeat)
    columns = np.random.default_rng(0).standard_normal((model.dofs.n_owned_blocks * model.dofs.bs, 100))
    B, X = model.dofs.dense(100), model.dofs.dense(100)
    B.getDenseArray()[:] = columns
    B.getDenseArray()[clamped] = 0.0
    row["100 RHS block"] = best_of(lambda: factor.solve_many(B, X), repeat)
    row["ratio assemble/lin.comb."] = row["assemble K"] / row["K by lin. comb."]
    return row


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=float, nargs="+", default=[1.6, 1.3, 1.0])
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    rows = [measure(h, args.repeat) for h in args.sizes]
    keys = list(rows[0])
    print("| " + " | ".join(keys) + " |")
    print("|" + "---|" * len(keys))
    for row in rows:
        print("| " + " | ".join(f"{row[k]:.4g}" if isinstance(row[k], float) else str(row[k]) for k in keys) + " |")
    print("(times in seconds, median of", args.repeat, "runs; the last column is a ratio)")


if __name__ == "__main__":
    main()
