"""Reduced estimates of this checkout against an earlier revision's, side by side in one
run, on the targets and bases `make demo` wrote.

    python benchmarks/before_after.py out/demo [--before 0392dae^] [--repeats 2]

The earlier revision is checked out (``git worktree``) into a temporary folder and each
case -- true prostate E 25/50/75, organ surfaces then landmarks -- runs in a fresh
process of each version in turn, ``repeats`` times: this machine's speed drifts by
20-35 % between runs of the same code, so only interleaved timings compare. Each process
pays its one-off costs (imports, JIT cache, the first mesh) on a warm-up estimate first;
the seconds are those of ``estimate()`` alone, as `make demo`'s tables give them. The
default revision is the one the speed issue (#13: "a reduced estimate takes 9.3-9.7 s")
was measured on. Both versions accept the scene overrides written here (``--set``
strings) and ``estimate(problem, basis=W)``.
"""

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
GROUPS = ("bladder", "prostate_surface", "rectum")
CASES = [(kind, E) for kind in ("surfaces", "landmarks") for E in (25, 50, 75)]

# One estimate in a child process; prints "RESULT <E found> <seconds>".
CHILD = """
import sys, time
import dolfinx_solver  # noqa
import numpy as np
from pathlib import Path
from fenics_elasto.objective import InverseProblem
from fenics_elasto.scene import load_scene
from fenics_elasto.estimate import estimate
out, kind, E = Path(sys.argv[1]), sys.argv[2], int(sys.argv[3])
W = np.load(out / "bases.npz")["W"]
def overrides(kind, E):
    folder = (out / f"target_E{E}").resolve()
    if kind == "surfaces":
        return ["target.surfaces={ " + ", ".join(f'{g} = "{folder}/surface_{g}.vtp"' for g in GROUPS) + " }"]
    return [f"target={{landmarks='{folder}/landmarks.csv'}}"]
def run(kind, E):
    problem = InverseProblem(load_scene(out / "source" / "problem.toml", overrides(kind, E)))
    start = time.perf_counter()
    record = estimate(problem, basis=W).record
    return record["materials"]["prostate"]["E"], time.perf_counter() - start
run("surfaces", 50)  # warm-up: imports, forms, caches
print("RESULT", *run(kind, E), flush=True)
""".replace("GROUPS", repr(GROUPS))


def one(code: Path, demo: Path, kind: str, E: int) -> tuple[float, float]:
    """(E found, seconds) of one estimate by the package in ``code``."""
    out = subprocess.run([sys.executable, "-c", CHILD, str(demo), kind, str(E)], capture_output=True, text=True,
                         env={**os.environ, "PYTHONPATH": str(code)},
                         cwd=tempfile.gettempdir())
    line = next((line for line in out.stdout.splitlines() if line.startswith("RESULT")), None)
    if line is None:
        raise SystemExit(f"{code}: {kind} E={E} failed:\n{out.stderr[-2000:]}")
    _, found, seconds = line.split()
    return float(found), float(seconds)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("demo", type=Path, help="a `make demo` output folder (bases.npz, source/, target_E*/)")
    parser.add_argument("--before", default="0392dae^", help="the earlier revision (default: before the #13 work)")
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    demo = args.demo.resolve()
    with tempfile.TemporaryDirectory() as tmp:
        before = Path(tmp) / "before"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "-q", str(before), args.before], check=True)
        try:
            rows = []
            for kind, E in CASES:
                runs = {"before": [], "after": []}
                for _ in range(args.repeats):
                    runs["before"].append(one(before, demo, kind, E))
                    runs["after"].append(one(ROOT, demo, kind, E))
                rows.append((kind, E, runs))
                print(f"   {kind} E={E}: " + ", ".join(f"{k} {' / '.join(f'{s:.2f}' for _, s in v)} s"
                                                       for k, v in runs.items()), flush=True)
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(before)], check=True)
    print("\n| target | true E | E before | E after | seconds before | seconds after | speed-up "
          "(median) |\n|---|---|---|---|---|---|---|")
    for kind, E, runs in rows:
        b, a = (np.median([s for _, s in runs[k]]) for k in ("before", "after"))
        print(f"| {kind} | {E} | {runs['before'][0][0]:.2f} | {runs['after'][0][0]:.2f} | "
              f"{' / '.join(f'{s:.2f}' for _, s in runs['before'])} | {' / '.join(f'{s:.2f}' for _, s in runs['after'])} "
              f"| {b / a:.2f}x |")


if __name__ == "__main__":
    main()
