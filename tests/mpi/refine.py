"""Run under mpiexec: refine a scene, move affine bases onto it, save them (rank 0)."""

import sys

import numpy as np

from fenics_elasto.model.dofs import DofLayout
from fenics_elasto.model.refine import refine_scene, transfer_bases
from fenics_elasto.model.scene import load_scene

problem, out, bases = sys.argv[1:4]
coarse = load_scene(problem)
fine = load_scene(refine_scene(problem, out))
nodes = DofLayout(coarse).node_set(coarse.loaded, coarse.fixed)
x = nodes.gather(nodes.coords)
# The affine columns' orthonormal span. The inclusion's loaded top is flat (y = 5): its y
# column is the constant one again, and QR's third column was then round-off -- 2.7e-15
# apart in x between 1 and 2 ranks made it 0.5 apart. The SVD keeps only what A spans.
U, sv, _ = np.linalg.svd(np.c_[np.ones(x.size), np.repeat(x, coarse.gdim, axis=0)], full_matrices=False)
W = U[:, sv > 1e-8 * sv[0]]
W *= np.sign(np.arange(1, len(W) + 1) @ W)  # a sign per column that round-off cannot flip
W_fine = transfer_bases(W, coarse, fine)
if coarse.comm.rank == 0:
    np.save(bases, W_fine)
