"""Block low-rank factors where a factorization serves few solves (`[solver] blr = "auto"`)
against exact factors, on the default phantom (116k DOFs).

`simulate` and `train --synthetic 120 --rank 80` with `--set solver.blr=0` (exact) and
with the default ("auto": MUMPS's block low-rank factors at 1e-5, every solution refined
on the true K to rtol), alternating, each command its own process on the same machine.
simulate is timed by result.json's `wall_time_s`, train around its process; the table
gives each pair's ratio.

    .venv/bin/python benchmarks/compressed_factors.py [--out DIR] [--repeats 2]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ranks import cli, result  # the rank table's: one command in its own process, its result.json

SETTINGS = {"exact": ["--set", "solver.blr=0"], "auto": []}


def simulate_seconds(problem: Path, out: Path, setting: list[str]) -> float:
    cli("simulate", problem, "--out", out, *setting)
    return result(out)["wall_time_s"]


def train_seconds(problem: Path, out: Path, setting: list[str]) -> float:
    return cli("train", problem, "--synthetic", 120, "--rank", 80, "--out", out / "bases.npz", *setting)


def main(out: Path, repeats: int) -> None:
    out = out.resolve()
    problem = out / "phantom" / "problem.toml"
    if not problem.exists():
        cli("mesh", "prostate-phantom", "--out", problem.parent)
    times: dict = {}
    for command, run in (("simulate", simulate_seconds), ("train --synthetic 120 --rank 80", train_seconds)):
        for _ in range(repeats):
            for name, setting in SETTINGS.items():
                times.setdefault((command, name), []).append(run(problem, out / name, setting))
    bases = [np.linalg.qr(np.load(out / name / "bases.npz")["W"])[0] for name in SETTINGS]
    cosines = np.linalg.svd(bases[0].T @ bases[1], compute_uv=False)
    print("\n| command | exact factors s | blr auto s | auto / exact |")
    print("|---|---|---|---|")
    for command in ("simulate", "train --synthetic 120 --rank 80"):
        exact, auto = (times[command, name] for name in SETTINGS)
        print(f"| {command} | {', '.join(f'{t:.1f}' for t in exact)} | {', '.join(f'{t:.1f}' for t in auto)} | "
              f"{np.median(auto) / np.median(exact):.2f} |")
    print(f"\nthe two trainings' bases span the same space: principal cosines {cosines.max():.12f} .. {cosines.min():.12f}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("out/compressed_factors"))
    parser.add_argument("--repeats", type=int, default=2)
    arguments = parser.parse_args()
    main(arguments.out, arguments.repeats)
