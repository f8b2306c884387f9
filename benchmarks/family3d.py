"""Prostate E on the independent 3D family, through the README's workflow.

Sources are meshed by plain gmsh (order 1: straight-sided, curved on load by the
toolkit; order 2: gmsh's own curved mesh), targets come from scikit-fem on finer
curved meshes with non-affine wall motion (tests/independent.py), observed as the
organ surfaces plus 4 fiducials inside the prostate. For each case: `train
--synthetic 120 --rank 80`, then `estimate`; printed: E, its error, the 95 %
interval and whether it holds the truth, and the parts of sigma.

    .venv/bin/python benchmarks/family3d.py [--out DIR] [--orders 1 2] [--seeds 0 7] [--E 25 50 75]
        [--truth-sizes WALLS PROSTATE]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import independent as ind  # noqa: E402
from fenics_elasto.app.cli import main  # noqa: E402


# The truth's element sizes at the bladder and rectum walls and at the prostate (scikit-fem
# P2, curved). The default (tests/independent.py's) is not converged: on seed 7's order-1
# source at E = 25 the same estimate read -3.23 / -2.91 / -2.73 / -2.67 % against truths at
# (0.25, 0.15) / (0.2, 0.1) / (0.15, 0.075) / (0.12, 0.06): about -2.6 % in the limit
# (docs: validation). --truth-sizes 0.15 0.075 makes them 5x slower (153 s each).
TRUTH_SIZES = (0.25, 0.15)


def run_case(out: Path, order: int, seed: int, E: float, extra: list[str], data: str = "both",
             truth_sizes: tuple[float, float] = TRUTH_SIZES) -> dict:
    problem = ind.plain_source(out / "sources", order, seed=seed)
    return estimate_on(problem, out, f"o{order}-s{seed}", seed, E, extra, data, truth_sizes)


def estimate_on(problem: Path, out: Path, name: str, seed: int, E: float, extra: list[str], data: str = "both",
                truth_sizes: tuple[float, float] = TRUTH_SIZES) -> dict:
    """The README's workflow on the source ``problem`` (seed ``seed``'s geometry): bases
    beside it, then the estimate of the truth at E (made at ``truth_sizes``) into
    out/<name>-...; its result.json."""
    straight = "curve='off'" in extra  # bases on the nodes as the estimate sees them
    bases = problem.parent / ("bases_straight.npz" if straight else "bases.npz")
    if not bases.is_file():
        train = ["train", str(problem), "--synthetic", "120", "--rank", "80", "--out", str(bases)]
        assert main(train + (["--set", "curve='off'"] if straight else [])) == 0
    walls, prostate = truth_sizes
    files = ind.phantom(out / "truth", E, seed=seed, walls=walls, prostate=prostate)
    surfaces = {g: files[g] for g in ("bladder", "prostate_surface", "rectum")}
    observed = {"surfaces": surfaces} if data == "surfaces" else {"surfaces": surfaces, "landmarks": files["fiducials"]}
    fine = "" if tuple(truth_sizes) == TRUTH_SIZES else f"_truth{walls:g}-{prostate:g}"
    target = ind.retarget(problem, observed, name=f"problem_E{E:g}_{data}{fine}.toml")
    tag = "-".join(s.replace("'", "").replace("=", "") for s in extra) + fine
    result_dir = out / f"{name}-E{E:g}-{data}{'-' + tag if tag else ''}"
    args = ["estimate", str(target), "--out", str(result_dir), "--set", f"reduction={{bases='{bases}'}}"]
    for setting in extra:
        args += ["--set", setting]
    assert main(args) == 0
    return json.loads((result_dir / "result.json").read_text())


def row(order: int, seed: int, E: float, data: str, result: dict) -> str:
    found = result["materials"]["prostate"]["E"]
    u = result["uncertainty"]["prostate.E"]
    low, high = u["ci95"]
    parts = " ".join(f"{k} {v:.2f}" for k, v in u.get("parts", {}).items())
    holds = "yes" if low <= E <= high else "NO"
    return (f"| {order} | {seed} | {data} | {E:g} | {found:.2f} | {100 * (found / E - 1):+.2f} % | [{low:.2f}, {high:.2f}] | "
            f"{holds} | {parts} | {len(result['warnings'])} | {result['wall_time_s']:.0f} s |")


def run(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("out/family3d"))
    parser.add_argument("--orders", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 7])
    parser.add_argument("--E", type=float, nargs="+", default=[25.0, 50.0, 75.0])
    parser.add_argument("--data", nargs="+", default=["both"], choices=["both", "surfaces"],
                        help="both: organ surfaces and 4 fiducials; surfaces: the surfaces alone")
    parser.add_argument("--truth-sizes", type=float, nargs=2, default=list(TRUTH_SIZES), metavar=("WALLS", "PROSTATE"),
                        help="the truth's element sizes at the moved walls and at the prostate")
    parser.add_argument("--set", action="append", default=[], help="extra --set for estimate "
                        "(the state before #31: --set curve='off' --set uncertainty.mesh='off')")
    args = parser.parse_args(argv)
    lines = ["| order | seed | data | true E | E | error | 95 % interval | holds | parts of sigma | warnings | time |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    start = time.perf_counter()
    for seed in args.seeds:
        for order in args.orders:
            for E in args.E:
                for data in args.data:
                    result = run_case(args.out, order, seed, E, args.set, data, tuple(args.truth_sizes))
                    lines.append(row(order, seed, E, data, result))
                    print(lines[-1], flush=True)
    print("\n".join(lines))
    print(f"total {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    run()
