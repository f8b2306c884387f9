"""What the linear solves cost on the prostate phantom (P2, serial); prints markdown tables.

    python benchmarks/solvers.py [--sizes 1.6 1.0] [--repeat 3] [--tables reuse blr iterative gamg rtol]

reuse      MUMPS LU and Cholesky: the first factorization (ordering + symbolic analysis +
           numeric) against a refactorization at a new material value that keeps the
           analysis (K refilled in place), from PETSc's event log; one back-solve.
blr        block low-rank factors (MUMPS CNTL(7) = blr; one run each): factorization time, factor size,
           the residual of the compressed factor alone, the refinement steps that bring a
           solve to rtol = 1e-8, and the refined answer's distance from full rank.
iterative  CG + GAMG: hierarchy setup, its refresh at a new material value, one solve from
           zero and one warm-started after a 1 % change of the prostate's E.
gamg       iterations and times of a few GAMG variants (why the defaults of solvers.py).
rtol       the field's relative error against the direct solve, per CG tolerance.

Times are medians of --repeat runs; the machine may be shared: read ratios first.
"""

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

import fenics_elasto  # noqa: F401  (imports dolfinx_solver before petsc4py)
from petsc4py import PETSc

from fenics_elasto.model.elasticity import ElasticModel
from fenics_elasto.model.loads import boundary_load
from fenics_elasto.util.logs import quiet
from fenics_elasto.mesh.builtin import build_scene
from fenics_elasto.model.scene import load_scene
from fenics_elasto.model.simulate import material_values
from fenics_elasto.model.solvers import (DirectSolver, IterativeSolver, SolverError, SolverSettings, SolverStats,
    WarmStart, rigid_body_modes)

EVENTS = {"lu": ("MatLUFactorSym", "MatLUFactorNum"), "cholesky": ("MatCholFctrSym", "MatCholFctrNum")}


class Case:
    """One phantom size: the model, a material value and a nearby one, a pressure load."""

    def __init__(self, problem):
        self.scene = load_scene(problem, command="simulate")
        self.model = ElasticModel(self.scene, SolverSettings(method="direct"))
        self.model.stiffness.terms
        E, nu = material_values(self.scene)
        prostate = np.array([m.name == "prostate" for m in self.scene.materials])
        self.c = self.model.stiffness.coefficients(E, nu)
        self.c_near = self.model.stiffness.coefficients(E * np.where(prostate, 1.01, 1.0), nu)
        self.clamped = self.model.dofs.clamped_dofs(self.scene.fixed)
        self.b = boundary_load(self.model.dofs, {}, {"bladder": 1.0})
        self.b.array[self.clamped] = 0.0
        self.modes = rigid_body_modes(self.model.dofs.dof_coords[: self.model.dofs.n_owned_blocks], self.model.dofs.comm)

    def K(self, c=None):
        return self.model.stiffness.constrained(self.c if c is None else c, self.clamped)

    def direct(self, **settings):
        return DirectSolver(self.K(), self.clamped, SolverSettings(method="direct", **settings), SolverStats("direct"))

    def iterative(self, **settings):
        return IterativeSolver(self.K(), self.clamped, SolverSettings(method="iterative", **settings),
                               SolverStats("iterative"), self.modes, WarmStart(self.model.dofs.comm))

    def solve(self, solver):
        x = self.b.duplicate()
        clock = time.perf_counter()
        solver.solve(self.b, x)
        return x, time.perf_counter() - clock

    def reference(self):
        if not hasattr(self, "_reference"):
            solver = self.direct(rtol=1e-12)
            self._reference = self.solve(solver)[0]
            solver.destroy()
        return self._reference


def median(work, repeat):
    times = []
    for _ in range(repeat):
        clock = time.perf_counter()
        work()
        times.append(time.perf_counter() - clock)
    return statistics.median(times)


def event_time(name):
    info = PETSc.Log.Event(name).getPerfInfo()
    return info["time"], info["count"]


def reuse_rows(case, repeat):
    rows = []
    for factor in ("lu", "cholesky"):
        symbolic, numeric = EVENTS[factor]
        s0, n0 = event_time(symbolic), event_time(numeric)
        first, refactor, solves = [], [], []
        for _ in range(repeat):
            clock = time.perf_counter()
            solver = case.direct(factor=factor)
            first.append(time.perf_counter() - clock)
            case.model.stiffness.constrained(case.c_near, case.clamped, out=solver.K)
            clock = time.perf_counter()
            solver.refresh()
            refactor.append(time.perf_counter() - clock)
            solves.append(case.solve(solver)[1])
            F = solver.factor
            memory = F.getMumpsInfog(22)
            solver.destroy()
        s1, n1 = event_time(symbolic), event_time(numeric)
        rows.append({"DOFs": case.model.dofs.num_dofs, "factor": factor,
                     "first (analysis + numeric) s": statistics.median(first),
                     "refactor (numeric only) s": statistics.median(refactor),
                     "analysis s (event log)": (s1[0] - s0[0]) / max(s1[1] - s0[1], 1),
                     "numeric s (event log)": (n1[0] - n0[0]) / max(n1[1] - n0[1], 1),
                     "analyses / numeric": f"{s1[1] - s0[1]} / {n1[1] - n0[1]}",
                     "solve + residual check s": statistics.median(solves), "MUMPS memory MB": memory})
    return rows


def blr_rows(case, repeat):
    rows, reference = [], case.reference()
    for blr in (0.0, 1e-10, 1e-8, 1e-6, 1e-4):
        clock = time.perf_counter()
        solver = case.direct(blr=blr, rtol=1e-8)
        factor_time = time.perf_counter() - clock
        F = solver.factor
        raw = case.b.duplicate()
        solver.ksp.solve(case.b, raw)  # the compressed factor alone
        residual = case.b.duplicate()
        solver.K.mult(raw, residual)
        residual.aypx(-1.0, case.b)
        x, solve_time = case.solve(solver)
        rows.append({"DOFs": case.model.dofs.num_dofs, "blr": blr, "factorization s": factor_time,
                     "factor entries (M)": F.getMumpsInfog(35 if blr else 29) / 1e6,
                     "MUMPS memory MB": F.getMumpsInfog(22),
                     "residual of the factor alone": residual.norm() / case.b.norm(),
                     "refinement steps": solver.stats.iterations, "refined solve s": solve_time,
                     "error vs full rank": (x - reference).norm() / reference.norm()})
        solver.destroy()
    return rows


def iterative_rows(case, repeat):
    reference = case.reference()
    setups, refreshes, solves, warm_solves, cold_its, warm_its = [], [], [], [], [], []
    for _ in range(repeat):
        clock = time.perf_counter()
        solver = case.iterative()
        setups.append(time.perf_counter() - clock)
        x, t = case.solve(solver)
        solves.append(t)
        cold_its.append(solver.stats.iterations)
        case.model.stiffness.constrained(case.c_near, case.clamped, out=solver.K)
        clock = time.perf_counter()
        solver.refresh()
        refreshes.append(time.perf_counter() - clock)
        warm_solves.append(case.solve(solver)[1])
        warm_its.append(solver.stats.iterations - cold_its[-1])
        solver.destroy()
    return [{"DOFs": case.model.dofs.num_dofs, "GAMG setup s": statistics.median(setups),
             "refresh (new material) s": statistics.median(refreshes), "CG its": cold_its[0],
             "solve s": statistics.median(solves), "warm CG its (1 % change)": warm_its[0],
             "warm solve s": statistics.median(warm_solves),
             "error vs direct": (x - reference).norm() / reference.norm()}]


GAMG_VARIANTS = {
    "jacobi smoothing (PETSc defaults)": {"mg_levels_pc_type": "jacobi"},
    "sor smoothing (solvers.py)": {},
    "sor, threshold 0.02": {"pc_gamg_threshold": "0.02"},
    "sor, threshold 0.05": {"pc_gamg_threshold": "0.05"},
    "sor, no aggressive coarsening": {"pc_gamg_aggressive_coarsening": "0"},
}


def gamg_rows(case, repeat):
    rows = []
    db = PETSc.Options()
    for name, options in GAMG_VARIANTS.items():
        for key, value in options.items():
            db["elasto_" + key] = value
        setups, solves, its = [], [], "-"
        try:
            for _ in range(repeat):
                clock = time.perf_counter()
                solver = case.iterative()
                setups.append(time.perf_counter() - clock)
                solves.append(case.solve(solver)[1])
                its = solver.stats.iterations
                solver.destroy()
        except SolverError as err:  # a variant that fails says so in the table
            its = f"failed: {err}"
        for key in options:
            db.delValue("elasto_" + key)
        rows.append({"DOFs": case.model.dofs.num_dofs, "GAMG variant": name, "CG its": its,
                     "setup s": statistics.median(setups) if setups else "-",
                     "solve s": statistics.median(solves) if solves else "-"})
    return rows


def rtol_rows(case, repeat):
    reference, rows = case.reference(), []
    for rtol in (1e-6, 1e-8, 1e-10):
        solver = case.iterative(rtol=rtol)
        x, t = case.solve(solver)
        rows.append({"DOFs": case.model.dofs.num_dofs, "rtol": rtol, "CG its": solver.stats.iterations, "solve s": t,
                     "field error vs direct": (x - reference).norm() / reference.norm()})
        solver.destroy()
    return rows


TABLES = {"reuse": reuse_rows, "blr": blr_rows, "iterative": iterative_rows, "gamg": gamg_rows, "rtol": rtol_rows}


def print_table(rows):
    keys = list(rows[0])
    print("| " + " | ".join(keys) + " |")
    print("|" + "---|" * len(keys))
    for row in rows:
        print("| " + " | ".join(f"{row[k]:.3g}" if isinstance(row[k], float) else str(row[k]) for k in keys) + " |")
    print()


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=float, nargs="+", default=[1.6, 1.0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--tables", nargs="+", default=list(TABLES), choices=list(TABLES))
    args = parser.parse_args()
    quiet()
    PETSc.Log.begin()
    results = {name: [] for name in args.tables}
    with tempfile.TemporaryDirectory() as tmp:
        for h in args.sizes:
            case = Case(build_scene("prostate-phantom", Path(tmp) / f"h{h}", size=h))
            for name in args.tables:
                results[name] += TABLES[name](case, args.repeat)
    for name, rows in results.items():
        print(f"**{name}**\n")
        print_table(rows)


if __name__ == "__main__":
    main()
