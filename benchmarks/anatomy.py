"""Cost of `fenics-elasto scene` on segmentation-sized surfaces (~10^5 triangles).

    python benchmarks/anatomy.py [--subdivide 2] [--nsub 5] [--size H] [--organ-size H]

The real prostate surface (8,084 triangles, four specks included) split linearly into
4^subdivide triangles each (same shape, 129k triangles at 2), with a bladder above it
and a rectum behind it as finely triangulated ellipsoids (20k triangles each at nsub
5), in a box with a clamped patch. Prints each stage's time as the scene reports it
(reading and repairing every file, nesting checks, meshing), the total, and the
element counts.
"""

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import pyvista as pv

import fenics_elasto  # noqa: F401  (imports dolfinx_solver before petsc4py)
from fenics_elasto.mesh.anatomy import build_scene_from_spec
from fenics_elasto.mesh.builtin import PROSTATE_STL
from fenics_elasto.util.logs import show

PROSTATE = PROSTATE_STL


def ellipsoid(center, radii, nsub):
    surface = pv.Icosphere(radius=1.0, nsub=nsub)
    surface.points = np.asarray(surface.points) * radii + np.asarray(center)
    return surface


def write_inputs(folder: Path, subdivide: int, nsub: int, size, organ_size) -> tuple[Path, int]:
    prostate = pv.read(PROSTATE).subdivide(subdivide, "linear") if subdivide else pv.read(PROSTATE)
    prostate.save(folder / "prostate.stl")
    bladder = ellipsoid((0.7, -2.0, 64.3), (25, 20, 15), nsub)
    rectum = ellipsoid((0.7, 29.2, 25.0), (10, 10, 30), nsub)
    bladder.save(folder / "bladder.stl")
    rectum.save(folder / "rectum.stl")
    sizes = (f"size = {size}\n" if size else "") + (f"organ_size = {organ_size}\n" if organ_size else "")
    (folder / "spec.toml").write_text(f"""units = "mm"
{sizes}[body]
box = {{ margin = 15.0 }}
[regions.prostate]
surface = "prostate.stl"
[cavities.bladder]
surface = "bladder.stl"
[cavities.rectum]
surface = "rectum.stl"
[patches.bones]
side = {{ point = [0.0, -25.0, 0.0], normal = [0.0, -1.0, 0.0] }}
""")
    return folder / "spec.toml", prostate.n_cells + bladder.n_cells + rectum.n_cells


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--subdivide", type=int, default=2, help="linear 1:4 splits of the prostate's triangles")
    parser.add_argument("--nsub", type=int, default=5, help="icosphere subdivisions of bladder and rectum")
    parser.add_argument("--size", type=float, default=None, help="element size in the body (default: the scene's)")
    parser.add_argument("--organ-size", type=float, default=None, help="element size at the organs")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        spec, triangles = write_inputs(folder, args.subdivide, args.nsub, args.size, args.organ_size)
        print(f"input: {triangles} triangles in 3 files")
        start = time.perf_counter()
        show()  # the library's progress lines: each step's time is the gap between two
        build_scene_from_spec(spec, folder / "out")
        print(f"scene: {time.perf_counter() - start:.1f} s in total")


if __name__ == "__main__":
    main()
