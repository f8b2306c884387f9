"""One factorization per reduced estimate: the optimum made exact on the start's factors
(MaterialSurrogate.refine) against solving it in full (a second factorization), on the
targets and bases `make demo` wrote.

    python benchmarks/one_factorization.py out/demo [--repeats 2]

Each case (true prostate E 25/50/75; organ surfaces, then landmarks) runs both ways in
turn, ``repeats`` times, in one process, so that a machine whose speed drifts (this one
varies by 20-25 % between runs of the same code) biases neither: the table gives the
median seconds of each, their ratio, the factorizations, and how far E, Phi* and sigma
differ between the two.
"""

import argparse
from pathlib import Path
from unittest import mock

import numpy as np

import fenics_elasto  # noqa: F401
from fenics_elasto.app.study import TRUE_E, TargetFiles, run_case

GROUPS = ("bladder", "prostate_surface", "rectum")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("demo", type=Path, help="a `make demo` output folder (bases.npz, source/, target_E*/)")
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    W = np.load(args.demo / "bases.npz")["W"]
    source = args.demo / "source" / "problem.toml"
    print("| target | true E | E | sigma | seconds, 1 factorization | seconds, 2 | ratio | factorizations "
          "| E, Phi*, sigma apart (relative) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for landmarks in (False, True):
        for E in TRUE_E:
            folder = args.demo / f"target_E{E:g}"
            target = TargetFiles({g: folder / f"surface_{g}.vtp" for g in GROUPS}, folder / "landmarks.csv")
            settings = target.settings(landmarks=True if landmarks else False)
            runs = {"refined": [], "solved": []}
            for _ in range(args.repeats):
                runs["refined"].append(run_case(source, settings, W))
                with mock.patch("fenics_elasto.inverse.profile.refine", lambda *args, **kwargs: None):
                    runs["solved"].append(run_case(source, settings, W))
            print(row("landmarks" if landmarks else "surfaces", E, runs), flush=True)


def row(kind: str, E: float, runs: dict) -> str:
    a, b = runs["refined"][0], runs["solved"][0]
    seconds = {way: float(np.median([r["seconds"] for r in rs])) for way, rs in runs.items()}
    sigma = {way: rs[0]["uncertainty"]["prostate.E"]["std"] for way, rs in runs.items()}
    apart = [abs(a["materials"]["prostate"]["E"] / b["materials"]["prostate"]["E"] - 1),
             abs(a["objective"]["final"] / b["objective"]["final"] - 1), abs(sigma["refined"] / sigma["solved"] - 1)]
    return (f"| {kind} | {E:g} | {a['materials']['prostate']['E']:.2f} | {sigma['refined']:.2f} | "
            f"{seconds['refined']:.1f} | {seconds['solved']:.1f} | {seconds['solved'] / seconds['refined']:.2f}x | "
            f"{a['factorizations']} / {b['factorizations']} | {' / '.join(f'{x:.0e}' for x in apart)} |")


if __name__ == "__main__":
    main()
