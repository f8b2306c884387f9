"""What writing a result costs next to the solve: the phantom simulated at a few sizes,
then its result folder written (displacement.bp, surface_<group>.vtp, surface.vtp,
screenshot.png) as `fenics-elasto simulate` writes it.

    python benchmarks/output.py [--sizes 1.6 1.0] [--pieces 4]

Prints, per size: DOFs, the solve, the whole output, the matched surfaces alone, and
the output's share of solve + output.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import fenics_elasto  # noqa: F401  (imports dolfinx_solver first)
from fenics_elasto.app.results import write_solution
from fenics_elasto.files.writers import write_matched_surfaces
from fenics_elasto.mesh.builtin import build_scene
from fenics_elasto.files.outputs import prepare_folder
from fenics_elasto.model.scene import load_scene
from fenics_elasto.model.simulate import simulate


def measure(size: float, pieces: int | None, tmp: Path) -> dict:
    scene = load_scene(build_scene("prostate-phantom", tmp / f"scene{size:g}", size=size), command="simulate")
    start = time.perf_counter()
    sim = simulate(scene)
    solve = time.perf_counter() - start
    start = time.perf_counter()
    with prepare_folder(tmp / f"result{size:g}") as folder, folder.writing(sim.result):
        write_solution(folder, scene, sim.u, title=f"h = {size:g}")
    output = time.perf_counter() - start
    start = time.perf_counter()
    write_matched_surfaces(tmp / f"surfaces{size:g}", scene, sim.u, **({"pieces": pieces} if pieces else {}))
    surfaces = time.perf_counter() - start
    return {"size": size, "dofs": sim.result["dofs"], "solve": solve, "output": output, "surfaces": surfaces}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=float, nargs="+", default=[1.6, 1.0])
    parser.add_argument("--pieces", type=int, default=None, help="pieces per curved facet edge (default: the writer's)")
    args = parser.parse_args()
    print("| h | DOFs | solve s | whole output s | matched surfaces s | output share |")
    print("|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for size in args.sizes:
            r = measure(size, args.pieces, Path(tmp))
            share = r["output"] / (r["solve"] + r["output"])
            print(f"| {size:g} | {r['dofs']:,} | {r['solve']:.2f} | {r['output']:.2f} | {r['surfaces']:.2f} | {share:.0%} |",
                  flush=True)


if __name__ == "__main__":
    main()
