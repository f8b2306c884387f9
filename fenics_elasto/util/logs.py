"""Progress and warnings: one logger, printed by MPI rank 0 only.

Library code logs to ``log`` (progress at INFO, problems the user should see at
WARNING) and prints nothing itself. ``show`` -- called by the command line, or by a
script that wants to watch -- sends INFO to stdout and WARNING to stderr as
``warning: ...``, on rank 0; the other ranks stay quiet (they compute the same).
"""

from __future__ import annotations

import logging
import sys

from mpi4py import MPI

log = logging.getLogger("fenics_elasto")
log.addHandler(logging.NullHandler())


class _Below(logging.Filter):
    def __init__(self, level: int):
        super().__init__()
        self.level = level

    def filter(self, record: logging.LogRecord) -> bool:
        return record.levelno < self.level


def show(level: int = logging.INFO, comm=MPI.COMM_WORLD) -> None:
    """Print progress (stdout) and warnings (stderr) of the library on rank 0."""
    for handler in [h for h in log.handlers if not isinstance(h, logging.NullHandler)]:
        log.removeHandler(handler)
    log.setLevel(level)
    log.propagate = False
    if comm.rank != 0:
        return
    progress = logging.StreamHandler(sys.stdout)
    progress.addFilter(_Below(logging.WARNING))
    progress.setFormatter(logging.Formatter("%(message)s"))
    problems = logging.StreamHandler(sys.stderr)
    problems.setLevel(logging.WARNING)
    problems.setFormatter(logging.Formatter("warning: %(message)s"))
    log.addHandler(progress)
    log.addHandler(problems)


def quiet() -> None:
    """No output from the library (tests, benchmarks)."""
    show(logging.CRITICAL + 1)
