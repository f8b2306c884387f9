"""Run under mpiexec: simulate a scene, save every node's position and displacement."""

import sys

import numpy as np

import fenics_elasto  # noqa: F401
from fenics_elasto.model.scene import load_scene
from fenics_elasto.model.simulate import simulate

problem, out = sys.argv[1], sys.argv[2]
scene = load_scene(problem)
sim = simulate(scene)
owned = sim.model.dofs.n_owned_blocks
coords = scene.comm.gather(sim.model.dofs.dof_coords[:owned], root=0)
disp = scene.comm.gather(sim.u.x.array.reshape(-1, sim.model.dofs.bs)[:owned], root=0)
if scene.comm.rank == 0:
    np.savez(out, coords=np.concatenate(coords), disp=np.concatenate(disp), ranks=scene.comm.size)
