"""Run under mpiexec: a two-state estimate (problem file and overrides from argv; a measured
force scales every E, as in the API); save the answer and each state's forces."""

import json
import sys
from pathlib import Path

import numpy as np

import fenics_elasto  # noqa: F401  (before mpi4py, dolfinx and petsc4py)
from fenics_elasto.inverse.estimator import estimate
from fenics_elasto.inverse.measured_force import with_force_reference
from fenics_elasto.inverse.objective import InverseProblem
from fenics_elasto.inverse.reduction.bases import load_bases
from fenics_elasto.model.scene import load_scene

problem_path, overrides, bases, out = sys.argv[1], json.loads(sys.argv[2]), Path(sys.argv[3]), sys.argv[4]
scene = with_force_reference(load_scene(problem_path, overrides))  # as the API does: a measured force may scale every E
problem = InverseProblem(scene)
W, held_out = load_bases(bases, problem, None)
result = estimate(problem, basis=W, held_out=held_out)
if scene.comm.rank == 0:
    np.savez(out, theta=result.theta, **{f"forces_{name}": f for name, f in result.state_forces.items()})
