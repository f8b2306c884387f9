"""Run under mpiexec: a forward solve and a block response with the given [solver]
method (P1 phantom), and the forward solve again at twice the prostate's E as simulate
makes it (direct: CG on the first factors, solvers.NearbySolver), and with direct
factors the same load at 3x and 1/3 of it in lock step on them (model.block_cg); saves
them at the
prostate surface's nodes (neither clamped nor loaded), in canonical node order: the
same under any number of ranks."""

import sys

import numpy as np

import fenics_elasto  # noqa: F401
from fenics_elasto.model.block_cg import LockstepCG
from fenics_elasto.model.elasticity import ElasticModel
from fenics_elasto.model.forward import BoundaryForward
from fenics_elasto.model.scene import load_scene
from fenics_elasto.model.solvers import SolverSettings
from fenics_elasto.model.responses import response_block

problem, method, out = sys.argv[1], sys.argv[2], sys.argv[3]
scene = load_scene(problem, ["degree=1"])
forward = BoundaryForward(scene, ElasticModel(scene, SolverSettings(method=method)))
rng = np.random.default_rng(1)
theta = np.array([40.0])
forces = rng.standard_normal(forward.force_dofs)
basis = rng.standard_normal((forward.force_dofs, 3))
u = forward.from_forces(theta, forces)
X = response_block(forward, theta, basis)
f = forward.load(forces)  # kept alive: its petsc_vec borrows its memory
near = forward.model.solve(forward.coefficients(2 * theta)[0], forward.clamped, f.x.petsc_vec, nearby=True)
lockstep = np.zeros((len(u.x.array), 2))
if method == "direct":
    model, owned = forward.model, forward.model.dofs.owned
    factors = model.solvers.factors_near(forward.coefficients(theta)[0], forward.clamped)
    b = f.x.array[:owned].copy()
    b[forward.clamped] = 0.0
    systems = [(model.solvers.stiffness(forward.coefficients(t)[0], forward.clamped), b[:, None]) for t in (3 * theta, theta / 3)]
    solutions, _ = LockstepCG(factors, model.dofs, systems, 1e-8).solve(maxiter=50)
    lockstep[:owned] = np.hstack(solutions)
nodes = forward.model.dofs.node_set(["prostate_surface"])
rows = nodes.dofs(forward.model.dofs.bs).ravel()
block = nodes.gather(X[rows].reshape(len(nodes), forward.model.dofs.bs * X.shape[1]))  # a rank may own none
field, near_field = (nodes.gather(v.x.array.reshape(-1, forward.model.dofs.bs)[nodes.blocks]) for v in (u, near))
lockstep = nodes.gather(lockstep[rows].reshape(len(nodes), forward.model.dofs.bs * 2))
if scene.comm.rank == 0:
    np.savez(out, u=field, X=block, near=near_field, lockstep=lockstep, factorizations=forward.model.factorizations,
             ranks=scene.comm.size, method=forward.model.method)
