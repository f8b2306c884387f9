"""The reduced estimate's cost at rank 12, 80 and 240 beside one `simulate` of the same
mesh (issue #35's rank table).

The default phantom (`fenics-elasto mesh prostate-phantom`, its default size); the
target is prostate E = 50 simulated on a finer mesh (h 0.8 against the source's 1.0)
with wall motion unlike the
training's (app/study.simulate_targets: the held-out motion), organ surfaces only.
Bases: `train --synthetic N --rank r`, N = 120 for ranks 12 and 80, 400 for rank 240.
Every command runs in its own process, one after another on the same machine; simulate
(three runs, their median) and estimate are timed by result.json's `wall_time_s`, train
around its process.

    .venv/bin/python benchmarks/ranks.py [--out DIR] [--ranks 12 80 240] [--profile 80]

``--profile R``: then the rank-R estimate once more under cProfile, its time grouped as
in benchmarks/profile_estimate.py (where it goes, not how long it takes: the profiler
slows it).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import independent as ind  # noqa: E402
import profile_estimate  # noqa: E402
from fenics_elasto.app.study import simulate_targets  # noqa: E402

TARGET_SIZE = 0.8  # cm: finer than the default phantom's 1.0
EXAMPLES = {12: 120, 80: 120, 240: 400}
SIMULATES = 3  # simulate runs; their median is the ratios' unit
BIN = Path(sys.executable).parent


def cli(*args) -> float:
    """Run one command of the toolkit; its wall seconds."""
    start = time.perf_counter()
    subprocess.run([str(BIN / "fenics-elasto"), *map(str, args)], check=True, capture_output=True)
    return time.perf_counter() - start


def result(folder: Path) -> dict:
    return json.loads((folder / "result.json").read_text())


def main(out: Path, ranks: list[int], profiled: list[int]) -> None:
    out = out.resolve()  # the problem's file names are read relative to its own folder
    source = out / "phantom"
    if not (source / "problem.toml").exists():
        cli("mesh", "prostate-phantom", "--out", source)
    problem = source / "problem.toml"
    files = simulate_targets(out / "target", (50.0,), TARGET_SIZE)[50.0]
    target = ind.retarget(problem, {"surfaces": files.surfaces}, name="problem_ranks.toml")
    # one simulate took 18-33 s here across runs, by how much of its memory the VM's host
    # had taken back (docs/performance, "Freed memory kept"): the median of SIMULATES runs
    times = []
    for _ in range(SIMULATES):
        cli("simulate", problem, "--out", out / "simulate")
        simulated = result(out / "simulate")
        times.append(simulated["wall_time_s"])
    rows = []
    for rank in ranks:
        bases = out / f"bases_{rank}.npz"
        training = cli("train", problem, "--synthetic", EXAMPLES[rank], "--rank", rank, "--out", bases)
        folder = out / f"estimate_{rank}"
        cli(*profile_estimate.estimate_args(target, bases, folder))
        rows.append((rank, training, result(folder)))
    seconds = float(np.median(times))
    print(f"\ndefault phantom: {simulated['dofs']:,} DOFs; one simulate {seconds:.1f} s "
          f"(the median of {', '.join(f'{t:.1f}' for t in times)})")
    print("| rank (examples) | train s | train / simulate | estimate s | estimate / simulate | factorizations | prostate E |")
    print("|---|---|---|---|---|---|---|")
    for rank, training, r in rows:
        print(f"| {rank} ({EXAMPLES[rank]}) | {training:.1f} | {training / seconds:.1f}x | {r['wall_time_s']:.1f} | "
              f"{r['wall_time_s'] / seconds:.1f}x | {r['factorizations']} | {r['materials']['prostate']['E']:.2f} |")
    for rank in profiled:
        args = profile_estimate.estimate_args(target, out / f"bases_{rank}.npz", out / f"estimate_{rank}_profiled")
        total, groups = profile_estimate.profiled(args)
        print(f"\nrank {rank}: the estimate under cProfile, {total:.1f} s")
        profile_estimate.print_groups(total, groups)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("out/ranks"))
    parser.add_argument("--ranks", type=int, nargs="+", default=[12, 80, 240])
    parser.add_argument("--profile", type=int, nargs="*", default=[], help="ranks whose estimate to profile after")
    arguments = parser.parse_args()
    main(arguments.out, arguments.ranks, arguments.profile)
