"""The critical path of one reduced estimate: when its factors are ready, and what runs
after them, in order (issue #35).

One estimate runs in this process, unprofiled. Its progress lines and every application
of the factorization (a block of right-hand sides, or one) are printed with the seconds
since the command began (reading the problem comes first), so that the gaps between
them are the work in between: inner fits, the surrogate's algebra, the mesh part's
degree-3 smoothing.

    .venv/bin/python benchmarks/critical_path.py PROBLEM.toml BASES.npz [--out DIR]

The rank table's case: ``benchmarks/ranks.py --out out/ranks`` makes the phantom, the
target and the bases; then ``critical_path.py out/ranks/phantom/problem_ranks.toml
out/ranks/bases_80.npz``.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import fenics_elasto  # noqa: F401 (first: the DOLFINx wheel's MPI and PETSc)
from petsc4py import PETSc

from fenics_elasto.app.cli import main
from fenics_elasto.model import solvers
from fenics_elasto.util.logs import log

START = [time.perf_counter()]


def stamp() -> str:
    return f"{time.perf_counter() - START[0]:7.2f} s"


class Stamped(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        return f"{stamp()}  {record.getMessage()}"


def trace_factor_applications() -> None:
    """Print each application of a factorization: when it began, its columns, its seconds."""
    apply = solvers.DirectSolver.apply_factors

    def traced(self, B, X) -> None:
        self._settle()  # a factorization still running is waited for first, not counted here
        began, when = time.perf_counter(), stamp()
        apply(self, B, X)
        columns = 1 if isinstance(B, PETSc.Vec) else B.getSize()[1]
        print(f"{when}  factors applied to {columns} column(s): {time.perf_counter() - began:.2f} s", flush=True)

    solvers.DirectSolver.apply_factors = traced


def ready_stamp() -> None:
    """Print when the factorization started ahead is ready."""
    settle = solvers.DirectSolver._settle

    def stamped(self) -> None:
        waiting = self._pending is not None
        settle(self)
        if waiting:
            print(f"{stamp()}  factors ready", flush=True)

    solvers.DirectSolver._settle = stamped


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("problem", type=Path)
    parser.add_argument("bases", type=Path)
    parser.add_argument("--out", type=Path, default=Path("out/critical_path"))
    arguments = parser.parse_args()
    trace_factor_applications()
    ready_stamp()
    import fenics_elasto.app.cli as cli

    show = cli.show

    def show_stamped(*args, **kwargs) -> None:  # the command line's own handlers, stamped
        show(*args, **kwargs)
        for handler in log.handlers:
            handler.setFormatter(Stamped())

    cli.show = show_stamped  # type: ignore[attr-defined]
    START[0] = time.perf_counter()
    main(["estimate", str(arguments.problem), "--out", str(arguments.out), "--set",
          f"reduction={{bases='{arguments.bases.resolve()}'}}"])
