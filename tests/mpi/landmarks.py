"""Run under mpiexec: estimate from surfaces plus interior landmarks; save the answer and
which rank evaluates each landmark (PointProbe.rows)."""

import sys

import numpy as np

import fenics_elasto  # noqa: F401  (before mpi4py, dolfinx and petsc4py)
from mpi4py import MPI
from fenics_elasto.inverse.estimator import estimate
from fenics_elasto.inverse.objective import InverseProblem
from fenics_elasto.model.scene import load_scene

problem_path, target, landmarks, out = sys.argv[1:5]
scene = load_scene(problem_path, [f"target={{surface='{target}', landmarks='{landmarks}'}}"])
problem = InverseProblem(scene)
result = estimate(problem)
claimed = np.zeros(len(problem.misfit.landmark_rows()), int)
claimed[problem.observation.probe.rows] = scene.comm.rank + 1
owner = scene.comm.allreduce(claimed, op=MPI.SUM) - 1  # each landmark is claimed by one rank
if scene.comm.rank == 0:
    np.savez(out, theta=result.theta, forces=result.forces, owner=owner, ranks=scene.comm.size)
