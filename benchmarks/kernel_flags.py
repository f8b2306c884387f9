"""The stiffness kernels compiled with dolfinx's default arguments and with
model.stiffness.KERNEL_FLAGS (-O3, sums reassociated), side by side, on the default
phantom (curved P2 geometry).

    python benchmarks/kernel_flags.py [--repeat 3]

For the model's degree (2) and sigma's mesh part (3): the matrix's assembly (median of
``--repeat``), the ratio, and how far the two matrices differ (Frobenius norm, relative):
round-off, since only the order of the sums changes.
"""

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

import fenics_elasto  # noqa: F401  (imports dolfinx_solver before petsc4py)
import dolfinx.fem.petsc
from dolfinx import fem
from fenics_elasto.mesh.builtin import build_scene
from fenics_elasto.model.scene import load_scene
from fenics_elasto.model.stiffness import dolfinx_compile_args, kernel_options, stiffness_form


def assembled(form, repeat: int):
    """(median seconds, matrix) of assembling ``form`` into one matrix ``repeat`` times."""
    A = dolfinx.fem.petsc.create_matrix(form)
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        A.zeroEntries()
        dolfinx.fem.petsc.assemble_matrix(A, form)
        A.assemble()
        times.append(time.perf_counter() - start)
    return float(np.median(times)), A


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    default = {"cffi_extra_compile_args": dolfinx_compile_args()}
    with tempfile.TemporaryDirectory() as tmp:
        scene = load_scene(build_scene("prostate-phantom", Path(tmp)))
    E = [10.0 * (i + 1) for i in range(len(scene.materials))]
    nu = [0.4] * len(scene.materials)
    print(f"default phantom: {scene.mesh.topology.index_map(3).size_global} cells; our flags: "
          f"{kernel_options().get('cffi_extra_compile_args', 'no (the user chose flags)')}")
    print("| degree | dolfinx's arguments (s) | with KERNEL_FLAGS (s) | ratio | matrices differ by (relative) |")
    print("|---|---|---|---|---|")
    for degree in (2, 3):
        V = fem.functionspace(scene.mesh, ("Lagrange", degree, (3,)))
        plain, A = assembled(stiffness_form(scene, V, E, nu, jit_options=default), args.repeat)
        ours, B = assembled(stiffness_form(scene, V, E, nu), args.repeat)
        B.axpy(-1.0, A)
        print(f"| {degree} | {plain:.2f} | {ours:.2f} | {ours / plain:.2f}x | {B.norm() / A.norm():.1e} |")
        A.destroy()
        B.destroy()


if __name__ == "__main__":
    main()
