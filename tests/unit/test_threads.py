"""BLAS threads under MPI (util/threads.py): each rank gets its share of the cores, and
a user's own thread count wins. Each case runs in a fresh interpreter, as a rank would
(the limit is set when the package is imported)."""

import json
import os
import subprocess
import sys

import pytest

PROBE = ("import fenics_elasto, numpy, json; from threadpoolctl import threadpool_info; "
         "print(json.dumps(max(i['num_threads'] for i in threadpool_info() if i['user_api'] == 'blas')))")


def blas_threads(**env) -> int:
    """The most threads any loaded BLAS will use, in a fresh interpreter with ``env``."""
    clean = {k: v for k, v in os.environ.items()
             if k not in ("MPI_LOCALNRANKS", "OMPI_COMM_WORLD_LOCAL_SIZE", "OMP_NUM_THREADS",
                          "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
    out = subprocess.run([sys.executable, "-c", PROBE], env=clean | env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


pytestmark = pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="one core: nothing to share")


def test_ranks_share_the_cores():
    cores = len(os.sched_getaffinity(0))
    assert blas_threads(MPI_LOCALNRANKS=str(cores)) == 1  # MPICH's Hydra
    assert blas_threads(OMPI_COMM_WORLD_LOCAL_SIZE=str(cores)) == 1  # Open MPI
    assert blas_threads() > 1  # one rank: BLAS keeps its own default


def test_a_users_thread_count_wins():
    """Two ranks would get one thread each; the user asked for two (OpenBLAS caps a
    request at the cores there are)."""
    assert blas_threads(MPI_LOCALNRANKS="2", OPENBLAS_NUM_THREADS="2") == 2
