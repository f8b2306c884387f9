"""One BLAS thread per core each rank may use, under MPI.

OpenBLAS starts as many threads as the machine has cores in every process. Under
``mpiexec -n 2`` on 2 cores that is 4 threads spinning on 2 cores, and the dense algebra
of a reduced estimate (the inner fits, the surrogate's projections), which every rank
does on its own copy of the small problem, slowed to a crawl: the pelvis phantom's
rank-80 estimate took 103 s on 2 ranks against 42.5 s serial; with one BLAS thread per
rank, 34.6 s (benchmarks/profile_estimate.py's case, docs: performance). The ranks on
a node share its cores; a user's own OMP_NUM_THREADS / OPENBLAS_NUM_THREADS /
MKL_NUM_THREADS setting wins. threadpoolctl (BSD-3) finds every BLAS the process has
already loaded and limits it, which environment variables set that late cannot.
"""

from __future__ import annotations

import os

from mpi4py import MPI
from threadpoolctl import threadpool_limits

USER_SETTINGS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
# What launchers say about the ranks on this node: MPICH's Hydra, Open MPI
NODE_RANKS = ("MPI_LOCALNRANKS", "OMPI_COMM_WORLD_LOCAL_SIZE")


def ranks_on_this_node(comm=MPI.COMM_WORLD) -> int:
    """From the launcher's environment, else all ranks (as if on one node: at worst too
    few threads, never too many)."""
    for name in NODE_RANKS:
        if os.environ.get(name, "").isdigit():
            return max(1, int(os.environ[name]))
    return comm.size


def share_cores_among_ranks(comm=MPI.COMM_WORLD) -> int | None:
    """Limit BLAS to this rank's share of the cores, when running on several ranks and
    the user set no thread count; the limit set, or None. Called before numpy is
    imported (fenics_elasto/__init__.py), the environment variables reach the BLAS
    libraries loaded later; threadpoolctl limits those already loaded (a script that
    imported numpy first)."""
    ranks = ranks_on_this_node(comm)
    if ranks == 1 or any(name in os.environ for name in USER_SETTINGS):
        return None
    threads = _core_share(ranks)
    for name in USER_SETTINGS:
        os.environ[name] = str(threads)
    threadpool_limits(limits=threads, user_api="blas")
    return threads


def threads_per_rank(comm=MPI.COMM_WORLD) -> int:
    """How many threads this rank's own parallel loops may run: the user's thread count
    if set (OMP_NUM_THREADS, ...), else its share of the cores on this node."""
    for name in USER_SETTINGS:
        if os.environ.get(name, "").isdigit():
            return max(1, int(os.environ[name]))
    return _core_share(ranks_on_this_node(comm))


def _core_share(ranks: int) -> int:
    """This rank's share of the cores it may run on, with ``ranks`` on the node."""
    return max(1, len(os.sched_getaffinity(0)) // ranks)
