"""Joint E and nu in 3D (the paper tried and could not): what do organ surfaces and a few
fiducials determine on the prostate phantom, and how sure is each answer?

    python benchmarks/joint.py [--E 50] [--out DIR] [--synthetic 60 --rank 40]

The target is independent (tests/independent.py: scikit-fem P2 on a finer, differently
built curved mesh; bladder and rectum moved non-affinely; prostate E given, nu = 0.4 in
prostate and tissue; 4 fiducials inside the prostate). The source is the default phantom
with bases from `train --synthetic`. Estimated sets: prostate E; prostate E and nu;
prostate E, prostate nu and tissue nu -- each from the surfaces, then surfaces +
fiducials. Printed: the values, their std and 95 % interval, the correlations, the
share of each constant's effect the boundary forces cannot mimic, or the refusal.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
import independent as ind  # noqa: E402  (tests/independent.py: the scikit-fem targets)

_spec = importlib.util.spec_from_file_location("bench_independent", ROOT / "benchmarks" / "independent.py")
bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench)  # benchmarks/independent.py: its CLI runner and sources
source, toolkit = bench.source, bench.toolkit

SETS = {
    "E": ["materials.prostate.E={estimate=true, initial=30.0, bounds=[2.0, 300.0]}"],
    "E, nu": ["materials.prostate.E={estimate=true, initial=30.0, bounds=[2.0, 300.0]}",
              "materials.prostate.nu={estimate=true, initial=0.3, bounds=[0.05, 0.49]}"],
    "E, nu, tissue nu": ["materials.prostate.E={estimate=true, initial=30.0, bounds=[2.0, 300.0]}",
                         "materials.prostate.nu={estimate=true, initial=0.3, bounds=[0.05, 0.49]}",
                         "materials.tissue.nu={estimate=true, initial=0.3, bounds=[0.05, 0.49]}"],
}


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--E", type=float, default=50.0)
    parser.add_argument("--out", type=Path, default=ROOT / "out" / "bench-independent")
    parser.add_argument("--synthetic", type=int, default=60)
    parser.add_argument("--rank", type=int, default=40)
    args = parser.parse_args()
    out = args.out.resolve()
    problem = source("prostate-phantom", out / "source-phantom", "--size", "1.6")
    bases = out / "source-phantom" / f"synthetic{args.synthetic}_{args.rank}.npz"
    if not bases.is_file():
        proc = toolkit("train", problem, "--synthetic", args.synthetic, "--rank", args.rank, "--out", bases)
        if proc.returncode:
            sys.exit(proc.stderr)
    files = ind.phantom(out / "truth", args.E)
    surfaces = {g: files[g] for g in ("bladder", "prostate_surface", "rectum")}
    print(f"truth: prostate E = {args.E:g} (tissue 10), nu = 0.4 in both; bases synthetic {args.synthetic}/{args.rank}\n")
    print("| estimated | data | prostate E | prostate nu | tissue nu | correlations | separable | s |")
    print("|---|---|---|---|---|---|---|---|")
    for name, settings in SETS.items():
        for kind, target in (("surfaces", {"surfaces": surfaces}),
                             ("+ fiducials", {"surfaces": surfaces, "landmarks": files["fiducials"]})):
            toml = ind.retarget(problem, target, f"joint_{kind[0]}.toml")
            folder = out / f"joint-{name.replace(', ', '_').replace(' ', '')}-{kind[0]}"
            extra = [a for s in settings + [f"reduction={{bases='{bases}'}}"] for a in ("--set", s)]
            proc = toolkit("estimate", toml, "--out", folder, *extra)
            if proc.returncode:
                print(f"| {name} | {kind} | refused: {proc.stderr.strip().splitlines()[-1][:160]} | | | | | |", flush=True)
                continue
            print(row(name, kind, json.loads((folder / "result.json").read_text())), flush=True)


def row(name: str, kind: str, result: dict) -> str:
    unc = result["uncertainty"]

    def cell(label):
        material, key = label.split(".")
        value = result["materials"][material][key]
        if label not in unc:
            return f"{value:.3g} (fixed)"
        lo, hi = unc[label]["ci95"]
        return f"{value:.4g} ± {unc[label]['std']:.2g} ({lo:.3g}-{hi:.3g})"

    labels = result["estimated"]
    corr = unc.get("correlation")
    pairs = ", ".join(f"{a}/{b}: {corr[i][j]:+.2f}" for i, a in enumerate(labels) for j, b in enumerate(labels) if i < j) \
        if corr else ""
    separable = ", ".join(f"{v:.2f}" for v in unc.get("separable", {}).values())
    return (f"| {name} | {kind} | {cell('prostate.E')} | {cell('prostate.nu')} | {cell('tissue.nu')} | {pairs} | "
            f"{separable} | {result['wall_time_s']:.0f} |")


if __name__ == "__main__":
    main()
