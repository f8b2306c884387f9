"""Two label maps of a kidney -> the tumour's E, against a truth the toolkit did not make.

benchmarks/labelmap_chain.py checks the commands on a truth `simulate` made. Here the
truth is tests/independent.py's ``kidney``: scikit-fem P2 on a finer, curved gmsh mesh
of an exact ellipsoid (100 x 56 x 48 mm) holding a 22 mm ball, its hilum end clamped and
one side pressed by a rounded probe that also drags and ripples it (motion no training
example was made from); imaged as label maps at rest and pressed, on 1 x 1 x 1.5 mm
voxels in a rotated, shifted frame (a voxel takes the label of the exact surfaces that
enclose its centre). The toolkit meshes the rest map itself (`scene`), trains on its
own mesh and estimates from the pressed map, as a user would:

    fenics-elasto scene spec.toml --out src
    fenics-elasto train src/problem.toml --synthetic 60 --rank 24 --out bases.npz (boundary --set)
    fenics-elasto estimate src/problem.toml --out est --set "reduction={bases='../bases.npz'}" \\
        --set "target={labels={image='../deformed.nii.gz', outer=[1, 2], tumour_surface=2}}" (boundary --set)

    .venv/bin/python benchmarks/kidney_labelmaps.py [--ratios 2 4 8] [--push 6] [--targets labels surfaces]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import independent  # noqa: E402


def run_case(out: Path, ratio: float, push: float, organ_size: float, kind: str = "labels") -> dict:
    """One truth and the user's chain on it (tests/independent.py's kidney_chain)."""
    truth = independent.kidney(out / "truth", ratio, push=push)
    start = time.perf_counter()
    result = independent.kidney_chain(truth, out / f"ratio_{ratio:g}_push_{push:g}", organ_size, kind)
    entry = result["uncertainty"]["tumour.E"]
    return {"kind": kind, "ratio": ratio, "push": push, "E": result["materials"]["tumour"]["E"], "truth": 10.0 * ratio,
            "ci95": entry["ci95"], "parts": entry.get("parts", {}), "estimate_s": result["wall_time_s"],
            "chain_s": time.perf_counter() - start, "rms": result["surface_distance"]["rms"]}


def table(rows: list[dict]) -> str:
    lines = ["| pressed state | true E (ratio) | push mm | E | error | 95 % interval | holds | parts: noise / mesh / bases | "
             "estimate s | scene + train + estimate s |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        low, high = r["ci95"]
        parts = " / ".join(f"{r['parts'].get(k, 0.0):.2f}" for k in ("noise", "mesh", "bases"))
        lines.append(f"| {r['kind']} | {r['truth']:g} ({r['ratio']:g}) | {r['push']:g} | {r['E']:.2f} | "
                     f"{100 * (r['E'] / r['truth'] - 1):+.1f} % | {low:.2f}-{high:.2f} | "
                     f"{'yes' if low <= r['truth'] <= high else 'no'} | {parts} | {r['estimate_s']:.0f} | {r['chain_s']:.0f} |")
    return "\n".join(lines)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ratios", type=float, nargs="+", default=[4.0])
    parser.add_argument("--push", type=float, nargs="+", default=[6.0])
    parser.add_argument("--organ-size", type=float, default=3.0)
    parser.add_argument("--targets", nargs="+", choices=sorted(independent.KIDNEY_TARGETS), default=["labels"])
    parser.add_argument("--out", type=Path, default=Path("out/kidney_labelmaps"))
    args = parser.parse_args()
    rows = [run_case(args.out, ratio, push, args.organ_size, kind)
            for push in args.push for ratio in args.ratios for kind in args.targets]
    print(table(rows))
