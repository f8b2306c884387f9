"""Where a reduced 3D estimate spends its time, at rank 80 and at rank 240 (issue #35).

The case is the plain-gmsh pelvis phantom at order 1 (curved on load), prostate E = 50
from organ surfaces and 4 fiducials, targets from scikit-fem (tests/independent.py),
bases from `train --synthetic N --rank R` (N = 120 for rank 80, 400 for rank 240). The
estimate runs under cProfile; its time is grouped by what it does (cumulative times of
the functions named, so a group holds what its functions call). Training is timed
apart.

    .venv/bin/python benchmarks/profile_estimate.py [--out DIR] [--ranks 80 240] [--mpi]

``--mpi``: the same estimate timed serial and under ``mpiexec -n 2`` instead (no
profiler), side by side.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import independent as ind  # noqa: E402
from fenics_elasto.app.cli import main  # noqa: E402

EXAMPLES = {80: 120, 240: 400}
# What the time goes to: (label, the functions whose cumulative time it is), in fenics_elasto.
GROUPS = [
    ("closest points on the target (libigl AABB)", [("geometry/surface.py", "_query")]),
    ("inner Gauss-Newton fits (dense algebra + closest points)", [("inverse/inner.py", "fit")]),
    ("factorizations (MUMPS)", [("model/solvers.py", "_setup")]),
    ("response blocks (back-solves, sensitivities)", [("model/responses.py", "response_block"),
                                                      ("model/responses.py", "response_sensitivities")]),
    ("surrogate: snapshots and refinement", [("inverse/surrogate.py", "add"), ("inverse/refinement.py", "refine")]),
    ("mesh part of sigma (degree-3 solve)", [("inverse/uncertainty/mesh_error.py", "mesh_shift")]),
    ("profile-likelihood interval", [("inverse/uncertainty/answer.py", "profile_likelihood_interval")]),
    ("bases' missing-motion check", [("inverse/reduction/bases.py", "missing_wall_motion")]),
    ("reading the scene and target, building the problem", [("app/api.py", "inverse_problem")]),
]  # the groups overlap (closest points are part of the fits); files are written by a child process


def cumulative(stats: pstats.Stats, path: str, name: str) -> float:
    return sum(row[3] for (file, _, func), row in stats.stats.items()  # type: ignore[attr-defined]
               if file.endswith(path) and func == name)


def prepare(out: Path, rank: int) -> tuple[Path, Path, float]:
    """The estimate's problem file and bases (trained first if not yet there), and the
    seconds training took."""
    problem = ind.plain_source(out / "sources", 1)
    bases = problem.parent / f"bases_{rank}.npz"
    start = time.perf_counter()
    if not bases.is_file():
        assert main(["train", str(problem), "--synthetic", str(EXAMPLES[rank]), "--rank", str(rank),
                     "--out", str(bases)]) == 0
    training = time.perf_counter() - start
    files = ind.phantom(out / "truth", 50.0)
    surfaces = {g: files[g] for g in ("bladder", "prostate_surface", "rectum")}
    target = ind.retarget(problem, {"surfaces": surfaces, "landmarks": files["fiducials"]}, name="problem_profile.toml")
    return target, bases, training


def estimate_args(target: Path, bases: Path, results: Path) -> list[str]:
    """The command line of the estimate, writing to ``results``."""
    return ["estimate", str(target), "--out", str(results), "--set", f"reduction={{bases='{bases}'}}"]


def serial_and_two_ranks(out: Path, rank: int) -> None:
    """The same estimate serial and under `mpiexec -n 2`, side by side (wall_time_s of
    result.json, each its own process)."""
    target, bases, _ = prepare(out, rank)
    binary = Path(sys.executable).parent
    rows = []
    for ranks in (1, 2):
        folder = out / f"rank{rank}_on_{ranks}"
        command = [str(binary / "fenics-elasto"), *estimate_args(target, bases, folder)]
        subprocess.run(([str(binary / "mpiexec"), "-n", "2"] if ranks == 2 else []) + command, check=True,
                       capture_output=True)
        result = json.loads((folder / "result.json").read_text())
        rows.append((ranks, result["wall_time_s"], result["materials"]["prostate"]["E"]))
    print(f"\nrank {rank}: one reduced estimate, serial and on 2 ranks")
    print("| ranks | wall s | ratio to serial | prostate E |")
    print("|---|---|---|---|")
    for ranks, seconds, E in rows:
        print(f"| {ranks} | {seconds:.1f} | {seconds / rows[0][1]:.2f} | {E:.2f} |")


def profiled(args: list[str]) -> tuple[float, list[tuple[str, float]]]:
    """Run the command line ``args`` of the toolkit under cProfile: its wall seconds and
    the seconds of each of GROUPS."""
    profiler = cProfile.Profile()
    start = time.perf_counter()
    profiler.runcall(main, args)
    total = time.perf_counter() - start
    stats = pstats.Stats(profiler)
    return total, [(label, sum(cumulative(stats, path, name) for path, name in functions)) for label, functions in GROUPS]


def print_groups(total: float, groups: list[tuple[str, float]]) -> None:
    print("| where | seconds | share |")
    print("|---|---|---|")
    for label, seconds in groups:
        print(f"| {label} | {seconds:.1f} | {100 * seconds / total:.0f} % |")


def profile(out: Path, rank: int) -> None:
    target, bases, training = prepare(out, rank)
    total, groups = profiled(estimate_args(target, bases, out / f"rank{rank}"))
    print(f"\nrank {rank}: estimate {total:.1f} s (training {training:.1f} s with {EXAMPLES[rank]} examples, "
          f"{'this run' if training > 1 else 'cached'})")
    print_groups(total, groups)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("out/profile_estimate"))
    parser.add_argument("--ranks", type=int, nargs="+", default=[80, 240])
    parser.add_argument("--mpi", action="store_true", help="time the estimate serial and on 2 ranks instead")
    arguments = parser.parse_args()
    for r in arguments.ranks:
        (serial_and_two_ranks if arguments.mpi else profile)(arguments.out, r)
