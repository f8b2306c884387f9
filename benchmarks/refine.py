"""Refining a scene once and moving reduced bases onto it (the prostate phantom, serial).

    python benchmarks/refine.py [--sizes 1.6 1.0] [--rank 40]

Prints, per size: refine_scene (read, split, write the .msh and problem.toml), loading
both scenes, transfer_bases of a random rank-r basis, and the sizes before and after.
"""

import argparse
import tempfile
import time

import numpy as np

from fenics_elasto.model.dofs import DofLayout
from fenics_elasto.mesh.builtin import build_scene
from fenics_elasto.model.refine import refine_scene, transfer_bases
from fenics_elasto.model.scene import load_scene


def timed(work):
    start = time.perf_counter()
    value = work()
    return value, time.perf_counter() - start


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=float, nargs="+", default=[1.6, 1.0])
    parser.add_argument("--rank", type=int, default=40)
    args = parser.parse_args()
    print(f"{'size':>5} {'cells':>15} {'P2 dofs':>17} {'loaded rows':>13} {'refine':>7} {'load':>6} {'transfer':>9}")
    for size in args.sizes:
        out = tempfile.mkdtemp(prefix="refine-bench-")
        problem = build_scene("prostate-phantom", f"{out}/coarse", size=size)
        refined, t_refine = timed(lambda: refine_scene(problem, f"{out}/fine"))
        (coarse, fine), t_load = timed(lambda: (load_scene(problem), load_scene(refined)))
        nodes = DofLayout(coarse).node_set(coarse.loaded, coarse.fixed)
        W = np.linalg.qr(np.random.default_rng(0).normal(size=(nodes.total * coarse.gdim, args.rank)))[0]
        W_fine, t_transfer = timed(lambda: transfer_bases(W, coarse, fine))
        cells = [s.mesh.topology.index_map(3).size_global for s in (coarse, fine)]
        dofs = [DofLayout(s).num_dofs for s in (coarse, fine)]
        print(f"{size:5.2f} {cells[0]:>6} -> {cells[1]:>6} {dofs[0]:>7} -> {dofs[1]:>7} {W.shape[0]:>5} -> {W_fine.shape[0]:>5} "
              f"{t_refine:6.2f}s {t_load:5.2f}s {t_transfer:8.2f}s")


if __name__ == "__main__":
    main()
