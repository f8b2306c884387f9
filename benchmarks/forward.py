"""Forward-model costs on the prostate phantom at three sizes (P2, serial).

    python benchmarks/forward.py [--sizes 1.6 1.3 1.0] [--repeat 3]

Prints DOFs, the one-off assembly of the per-material matrices, a direct assembly of
K, K formed as a linear combination, MUMPS LU and Cholesky factorizations, one
back-solve, and a 100-column block solve through one factorization.
"""

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

import fenics_elasto  # noqa: F401  (imports dolfinx_solver before petsc4py)
import ufl
from petsc4py import PETSc

import dolfinx.fem.petsc
from dolfinx import fem
from fenics_elasto.elasticity import ElasticModel, Factorization, epsilon
from fenics_elasto.meshing import build_scene
from fenics_elasto.scene import load_scene
from fenics_elasto.simulate import material_values


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
    mu, lam = model.lame_parameters(E, nu)
    Q = fem.functionspace(scene.mesh, ("DG", 0))
    mu_f, lam_f = fem.Function(Q), fem.Function(Q)
    for m, material in enumerate(scene.materials):
        cells = Q.dofmap.list[scene.cell_tags.find(material.tag), 0]
        mu_f.x.array[cells], lam_f.x.array[cells] = mu[m], lam[m]
    u, v = ufl.TrialFunction(model.V), ufl.TestFunction(model.V)
    form = fem.form(2 * mu_f * ufl.inner(epsilon(u), epsilon(v)) * ufl.dx + lam_f * ufl.div(u) * ufl.div(v) * ufl.dx)

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
        model.material_matrices  # assembled on first use
        setup = time.perf_counter() - start
    E, nu = material_values(scene)
    clamped = model.clamped_dofs(scene.fixed)
    row = {"h": h, "dofs": model.num_dofs, "material matrices (once)": setup}
    row["assemble K"] = best_of(direct_assembly(model, E, nu), repeat)
    row["K by lin. comb."] = best_of(lambda: model.stiffness(E, nu).destroy(), repeat)
    K = model.stiffness(E, nu)
    K.zeroRowsColumns(clamped.astype(PETSc.IntType), diag=1.0)
    for kind in ("lu", "cholesky"):
        row[f"{kind.upper()} factor"] = best_of(lambda: Factorization(K.copy(), clamped, kind).destroy(), repeat)
    factor = Factorization(K, clamped, "lu")
    b, x = K.createVecRight(), K.createVecRight()
    b.setRandom()
    row["back-solve"] = best_of(lambda: factor.solve(b, x), repeat)
    n = model.num_dofs
    columns = np.random.default_rng(0).standard_normal((n, 100))  # PETSc borrows this memory
    B = PETSc.Mat().createDense((n, 100), array=columns)
    X = PETSc.Mat().createDense((n, 100))
    X.setUp()
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
