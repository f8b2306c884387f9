"""How much each kind of data beyond surfaces narrows E, on one phantom (issue #36).

The 2D inclusion block (tests/independent.py): scikit-fem's P2 solution on a finer,
curved mesh is the truth; the source is a straight-sided plain-gmsh mesh (h = 0.2);
the inclusion E = 40 (matrix 10). The base case observes the outer outline only (the
inclusion unseen), with reduced bases (`train --synthetic 60 --rank 24`). Each row adds
one kind of data to it:

- fiducials: 4 points inside the inclusion, their scikit-fem displacement exact;
- a second state: the top moved another way (shifted and pressed), its outline too;
- a force: the top's total force, scikit-fem's, stated with 2 % noise, every E estimated
  (the matrix started at half its truth): absolute E;
- a field: scikit-fem's displacement on a 0.02 grid (1.5e5 samples) inside the block with a smooth 1 %
  error (0.005), its correlation length left to the default (the mesh cell size).

Printed: E, its error, sigma, the 95 % interval, whether it holds the truth, the time
of the estimate and its ratio to the base row's.

    .venv/bin/python benchmarks/more_than_surfaces.py [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import independent as ind  # noqa: E402
from fenics_elasto.app.cli import main  # noqa: E402

RATIO, TRUTH, SECOND_TOP = 4.0, 40.0, (0.2, 0.0, -0.4, 0.0)
FIDUCIALS = np.array([[0.3, 0.2], [-0.4, 0.1], [0.1, -0.5], [-0.2, -0.3]])


def data_files(out: Path) -> dict:
    import pyvista as pv

    first = ind.inclusion(out / "a", RATIO, source_size=0.2)
    second = ind.inclusion(out / "b", RATIO, top=SECOND_TOP, source_size=0.2)
    ind.write_landmarks(out / "fiducials.csv", FIDUCIALS, FIDUCIALS + ind.inclusion_displacement(FIDUCIALS, RATIO))
    x, y = np.meshgrid(np.arange(-4.99, 4.995, 0.02), np.arange(-2.99, 2.995, 0.02))  # 1.5e5 samples
    points = np.c_[x.ravel(), y.ravel()]
    field = ind.inclusion_displacement(points, RATIO) + ind.smooth_error(points, 0.005)
    cloud = pv.PolyData(np.c_[points, np.zeros(len(points))])
    cloud["displacement"] = np.c_[field, np.zeros(len(field))]
    cloud.save(out / "field.vtp")
    force = ind.inclusion_force(RATIO)
    return {"problem": first["problem"], "outline": first["outline"], "second": second["outline"],
            "fiducials": out / "fiducials.csv", "field": out / "field.vtp", "force": force}


def rows(files: dict) -> dict[str, list[str]]:
    outline = f"surfaces={{outline='{files['outline']}'}}"
    noise = 0.02 * float(np.linalg.norm(files["force"]))
    return {
        "surfaces only": [f"target={{{outline}}}"],
        "+ 4 fiducials": [f"target={{{outline}, landmarks='{files['fiducials']}'}}"],
        "+ a second state": [f"states=[{{name='first', target={{{outline}}}}}, "
                             f"{{name='second', target={{surfaces={{outline='{files['second']}'}}}}}}]"],
        "+ a force (2 %)": [f"target={{{outline}}}", "materials.matrix.E={estimate=true, initial=5.0, bounds=[0.5, 100.0]}",
                            f"boundary.measured_force.top={{value={files['force'].tolist()}, noise={noise}}}"],
        "+ a field (1 %)": [f"target={{{outline}, displacement='{files['field']}', displacement_noise=0.005}}"],
    }


def main_(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    files = data_files(out)
    bases = out / "bases.npz"
    if not bases.is_file():
        assert main(["train", str(files["problem"]), "--synthetic", "60", "--rank", "24", "--out", str(bases)]) == 0
    common = ["boundary.matched=['outline']", f"reduction={{bases='{bases}'}}"]
    table, base_time = [], None
    for name, sets in rows(files).items():
        folder = out / name.replace(" ", "_").replace("+", "plus").replace("(", "").replace(")", "").replace("%", "pc")
        args = ["estimate", str(files["problem"]), "--out", str(folder)]
        for s in common + sets:
            args += ["--set", s]
        start = time.perf_counter()
        assert main(args) == 0
        seconds = time.perf_counter() - start
        base_time = base_time or seconds
        result = json.loads((folder / "result.json").read_text())
        E = result["materials"]["inclusion"]["E"]
        entry = result["uncertainty"]["inclusion.E"]
        low, high = entry["ci95"]
        table.append(f"| {name} | {E:.2f} | {100 * (E / TRUTH - 1):+.2f} % | {entry['std']:.3f} | "
                     f"[{low:.2f}, {high:.2f}] | {'yes' if low < TRUTH < high else 'NO'} | {seconds:.1f} s "
                     f"({seconds / base_time:.2f}x) |")
    print("| data | E (truth 40) | error | sigma | 95 % interval | holds | time (vs surfaces only) |")
    print("|---|---|---|---|---|---|---|")
    print("\n".join(table))


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("out/more_than_surfaces"))
    main_(parser.parse_args().out.resolve())  # the problem files name their targets by absolute path
