"""Beyond surfaces on the 3D pelvis phantom: fiducials, a second state, a measured force, a field.

The source is the phantom meshed by plain gmsh at order 2 (tests/independent.py
``plain_source``); the truth is scikit-fem's P2 solution on a finer, curved mesh with
non-affine wall motion, prostate E = 50 (tissue 10). Bases: `train --synthetic 120
--rank 80`. The base row observes the organ surfaces of the "filled" state; each row
adds one kind of data:

- 4 fiducials inside the prostate (exact);
- the "emptied" state's organ surfaces (bladder emptied and sunk, rectum collapsed),
  and that state alone (not an addition: the case the bases are farthest from);
- the "probe" state's organ surfaces (the rectum widened 40 % towards the prostate, as by
  an endorectal balloon), and that state alone;
- the rectum wall's total force, scikit-fem's, stated with 2 % noise, every E estimated
  (the tissue started at half its truth);
- a displacement field: 20,000 vertices of the truth's mesh with their displacement and
  a smooth 1 % error, noise stated; the same with independent 1 % noise per sample; and
  ~10^5 samples of it (each point jittered by 1 mm twelve times) for the cost of a dense
  field; and the independent one alone, no surfaces (not an addition: the field carrying
  the estimate by itself).

    .venv/bin/python benchmarks/more_than_surfaces_3d.py [--out DIR] [--set KEY=VALUE ...] [--noise STD] [--far H]

``--set``: added to every row's estimate (e.g. optimizer.matched_motion='auto').
``--noise STD``: every state's organ surfaces with Gaussian noise of STD cm on every
point, each state its own draw (a segmentation's error: 0.05 is half a millimetre, a
voxel of fine MR), so that the data's noise, not the source mesh, leads sigma.
``--far H``: the source's element size away from the organs (default 1.5 cm; the organs
keep 0.45): the lever the run names when the mesh part leads, as it does for a field.
"""

from __future__ import annotations

import argparse
import functools
import json
import re
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import independent as ind  # noqa: E402
from fenics_elasto.app.cli import main  # noqa: E402

TRUTH = 50.0


@functools.cache
def _source_mesh(problem: Path):
    from fenics_elasto.model.scene import load_scene

    return load_scene(problem).mesh


def inside(points: np.ndarray, problem: Path, tolerance: float | None = None) -> np.ndarray:
    """Which points lie inside the source mesh (read once per run), within ``tolerance``:
    by default the toolkit's own for a point file (1e-6 of the mesh's size). A truth
    vertex on a curved wall can lie a hair outside the coarser source (gmsh's order-2
    nodes move by ~1e-5 from run to run), and a sample outside the body is refused."""
    from fenics_elasto.model.observation import farther_than

    mesh = _source_mesh(problem)
    if tolerance is None:
        tolerance = 1e-6 * float(np.ptp(mesh.geometry.x, axis=0).max())
    return ~farther_than(mesh, tolerance, points)


def cloud_of(points: np.ndarray, displacement: np.ndarray):
    import pyvista as pv

    cloud = pv.PolyData(points)
    cloud["displacement"] = displacement
    return cloud


def noisy_field(path: Path, out: Path, share: float, problem: Path, smooth: bool = True) -> tuple[Path, float]:
    """The field inside the source with an error of ``share`` x its largest displacement,
    smooth (a registration's kind) or independent per sample; (file, std)."""
    import pyvista as pv

    truth = pv.read(path)
    kept = inside(np.asarray(truth.points, float), problem)
    cloud = cloud_of(np.asarray(truth.points, float)[kept], np.asarray(truth["displacement"])[kept])
    u = np.asarray(cloud["displacement"])
    std = share * float(np.linalg.norm(u, axis=1).max())
    points = np.asarray(cloud.points, float)
    error = (ind.smooth_error(points, std, spread=0.6) if smooth  # ~3-10 cm waves
             else std * np.random.default_rng(0).standard_normal(u.shape))
    cloud["displacement"] = u + error
    cloud.save(out)
    return out, std


def dense_field(path: Path, out: Path, share: float, problem: Path, copies: int = 12) -> tuple[Path, float]:
    """~10^5 samples: the field's points jittered by 1 mm ``copies`` times, each keeping its
    vector, with independent noise of ``share`` x the largest; those inside the source
    kept; (file, std)."""
    import pyvista as pv

    cloud = pv.read(path)
    u, points = np.asarray(cloud["displacement"]), np.asarray(cloud.points, float)
    rng = np.random.default_rng(1)
    points = np.concatenate([points + rng.normal(0.0, 0.1, points.shape) for _ in range(copies)])
    std = share * float(np.linalg.norm(u, axis=1).max())
    u = np.tile(u, (copies, 1)) + std * rng.standard_normal(points.shape)
    kept = inside(points, problem, 0.0)
    cloud_of(points[kept], u[kept]).save(out)
    return out, std


GROUPS = ("bladder", "prostate_surface", "rectum")


def segmented(files: dict, out: Path, std: float, seed: int) -> dict:
    """``files`` with each organ surface replaced by a copy with Gaussian noise of ``std``."""
    rng = np.random.default_rng(seed)
    out.mkdir(parents=True, exist_ok=True)
    return {**files, **{g: ind.noisy_copy(files[g], out / f"{g}.vtp", std, rng) for g in GROUPS}}


def rows(filled: dict, emptied: dict, probe: dict, out: Path, problem: Path) -> dict[str, Callable[[], list[str]]]:
    """Each row's --set values, made when the row runs (a field's files only then)."""
    surfaces = lambda files: "surfaces={" + ", ".join(  # noqa: E731
        f"{g}='{files[g]}'" for g in GROUPS) + "}"
    filled_only = f"target={{{surfaces(filled)}}}"

    def force() -> list[str]:
        value = np.array(json.loads(Path(filled["forces"]).read_text())["rectum"])
        return [filled_only, "materials.tissue.E={estimate=true, initial=5.0, bounds=[0.5, 100.0]}",
                f"boundary.measured_force.rectum={{value={value.tolist()}, noise={0.02 * float(np.linalg.norm(value))}}}"]

    def field(kind: str, beside: str = f"{surfaces(filled)}, ") -> list[str]:
        truth = Path(filled["field"])
        if kind == "dense":
            path, std = dense_field(truth, out / "field_dense.vtp", 0.01, problem)
        else:
            path, std = noisy_field(truth, out / f"field_{kind}.vtp", 0.01, problem, smooth=kind == "noisy")
        return [f"target={{{beside}displacement='{path}', displacement_noise={std}}}"]

    return {
        "surfaces only": lambda: [filled_only],
        "+ 4 fiducials": lambda: [f"target={{{surfaces(filled)}, landmarks='{filled['fiducials']}'}}"],
        "+ a second state": lambda: [f"states=[{{name='filled', target={{{surfaces(filled)}}}}}, "
                                     f"{{name='emptied', target={{{surfaces(emptied)}}}}}]"],
        "the second state alone": lambda: [f"target={{{surfaces(emptied)}}}"],
        "+ a probe state": lambda: [f"states=[{{name='filled', target={{{surfaces(filled)}}}}}, "
                                    f"{{name='probe', target={{{surfaces(probe)}}}}}]"],
        "the probe state alone": lambda: [f"target={{{surfaces(probe)}}}"],
        "+ a force (2 %)": force,
        "+ a field (1 %)": lambda: field("noisy"),
        "+ a field (1 %, independent)": lambda: field("independent"),
        "+ a field (1 %, independent, 10^5 samples)": lambda: field("dense"),
        "a field alone (1 %, independent)": lambda: field("independent", beside=""),
    }


def run(out: Path, extra: list[str], only: list[str], noise: float = 0.0, far: float | None = None) -> None:
    out = out.resolve()  # the rows' file names are read relative to the problem's folder
    out.mkdir(parents=True, exist_ok=True)
    problem = ind.plain_source(out / "sources", 2, **({"far": far} if far else {}))
    bases = problem.parent / "bases.npz"
    if not bases.is_file():
        assert main(["train", str(problem), "--synthetic", "120", "--rank", "80", "--out", str(bases)]) == 0
    filled = ind.phantom(out / "truth", TRUTH, field=20000)
    emptied = ind.phantom(out / "truth", TRUTH, state="emptied")
    probe = ind.phantom(out / "truth", TRUTH, state="probe")
    if noise:  # each state its own draw
        filled, emptied, probe = (segmented(files, out / f"segmented_{noise:g}" / state, noise, seed)
                                  for seed, (state, files) in enumerate(
                                      (("filled", filled), ("emptied", emptied), ("probe", probe))))
        out = out / f"noise_{noise:g}"
    if far:
        out = out / f"far_{far:g}"
    out.mkdir(parents=True, exist_ok=True)
    table, base = [], None
    for name, make in rows(filled, emptied, probe, out, problem).items():
        if only and name not in only:
            continue
        sets = make()
        folder = out / re.sub(r"[(),]", "", name.replace(" ", "_").replace("+", "plus").replace("%", "pc"))
        args = ["estimate", str(problem), "--out", str(folder), "--set", f"reduction={{bases='{bases}'}}"]
        for s in sets + extra:
            args += ["--set", s]
        start = time.perf_counter()
        assert main(args) == 0
        seconds = time.perf_counter() - start
        base = base or seconds
        result = json.loads((folder / "result.json").read_text())
        E = result["materials"]["prostate"]["E"]
        entry = result["uncertainty"]["prostate.E"]
        low, high = entry["ci95"]
        parts = " ".join(f"{k} {v:.2f}" for k, v in entry.get("parts", {}).items())
        table.append(f"| {name} | {E:.2f} | {100 * (E / TRUTH - 1):+.2f} % | {entry['std']:.2f} | [{low:.2f}, {high:.2f}] "
                     f"| {'yes' if low < TRUTH < high else 'NO'} | {parts} | {seconds:.0f} s ({seconds / base:.2f}x) |")
        print(table[-1], flush=True)
    print("| data | prostate E (truth 50) | error | sigma | 95 % interval | holds | parts of sigma | time (vs surfaces only) |")
    print("|---|---|---|---|---|---|---|---|")
    print("\n".join(table))


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("out/more_than_surfaces_3d"))
    parser.add_argument("--set", action="append", default=[], help="extra --set for every estimate")
    parser.add_argument("--row", action="append", default=[], help="run only this row (by its name; repeatable)")
    parser.add_argument("--noise", type=float, default=0.0, help="segmentation noise on every target surface, cm")
    parser.add_argument("--far", type=float, help="the source's element size away from the organs, cm")
    options = parser.parse_args()
    run(options.out, options.set, options.row, options.noise, options.far)
