"""Run under mpiexec: refine a scene, move affine bases onto it, save them (rank 0)."""

import sys

import numpy as np

from fenics_elasto.elasticity import ElasticModel
from fenics_elasto.refine import refine_scene, transfer_bases
from fenics_elasto.scene import load_scene

problem, out, bases = sys.argv[1:4]
coarse = load_scene(problem)
fine = load_scene(refine_scene(problem, out))
nodes = ElasticModel(coarse).node_set(coarse.loaded, coarse.fixed)
x = nodes.gather(nodes.coords)
W, _ = np.linalg.qr(np.c_[np.ones(x.size), np.repeat(x, coarse.gdim, axis=0)])
W_fine = transfer_bases(W, coarse, fine)
if coarse.comm.rank == 0:
    np.save(bases, W_fine)
