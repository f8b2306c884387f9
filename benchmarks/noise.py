"""Noise study: error and sigma of the estimate against the noise on the target.

    python benchmarks/noise.py [--cases letter,phantom] [--levels 0,0.25,0.5,1,2]
                               [--draws-letter 10] [--draws-phantom 3] [--out DIR]

Targets from the independent FE code (tests/independent.py: scikit-fem P2 on finer,
differently built meshes): the letter A (nu = 0.25 estimated, outline only) and the
prostate phantom (prostate E = 50 estimated, organ surfaces only, bases from
`train --synthetic 120 --rank 80`). Gaussian noise of std = level % of the organ's size
(the letter's height, the prostate's longest side) is added to every target point in
every direction the target has; each level is drawn ``--draws`` times (level 0 once) and
estimated through the command line with default settings. Printed per case and level:
the mean error, the spread (std) of the estimates over the draws, the mean reported
sigma, how many intervals hold the truth, the noise std the estimate found, refusals
and seconds; the plot (--plot docs/noise_study.png) shows error and 95 % interval per
draw, keeping the points of cases run before (stored beside it as .json).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pyvista as pv

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
import independent as ind  # noqa: E402  (tests/independent.py: the scikit-fem targets)

_spec = importlib.util.spec_from_file_location("bench_independent", ROOT / "benchmarks" / "independent.py")
bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench)  # benchmarks/independent.py: its CLI runner and sources

LETTER_NU, PROSTATE_E = 0.25, 50.0


def organ_size(path) -> float:
    """The longest side of a target's bounding box."""
    lo_hi = np.reshape(pv.read(path).bounds, (3, 2))
    return float(np.max(lo_hi[:, 1] - lo_hi[:, 0]))


def letter(out: Path):
    """(problem, {target key: file}, organ size, (material, key), truth, extra --set settings)."""
    problem = bench.source("letter-a", out / "source-letter-a")
    target = ind.letter_a(out / "truth", LETTER_NU)["target"]
    return problem, {"surface": target}, organ_size(target), ("letter", "nu"), LETTER_NU, []


def phantom(out: Path):
    problem = bench.source("prostate-phantom", out / "source-phantom", "--size", "1.6")
    bases = out / "source-phantom" / "synthetic120_80.npz"
    if not bases.is_file():
        proc = bench.toolkit("train", problem, "--synthetic", 120, "--rank", 80, "--out", bases)
        if proc.returncode:
            sys.exit(proc.stderr)
    files = ind.phantom(out / "truth", PROSTATE_E)
    surfaces = {g: files[g] for g in ("bladder", "prostate_surface", "rectum")}
    return (problem, surfaces, organ_size(files["prostate_surface"]), ("prostate", "E"), PROSTATE_E,
            [f"reduction={{bases='{bases}'}}"])


def one_case(name: str, out: Path, levels, draws: int) -> tuple[list[str], list[tuple]]:
    problem, targets, size, (material, key), truth, settings = {"letter": letter, "phantom": phantom}[name](out)
    rows, points = [], []
    for level in levels:
        rng = np.random.default_rng(11)
        found, sigmas, held, noises, seconds, refused = [], [], [], [], [], 0
        for draw in range(draws if level > 0 else 1):
            folder = out / f"noise-{name}-{level:g}-{draw}"
            (folder / "target").mkdir(parents=True, exist_ok=True)
            files = {k: str(ind.noisy_copy(p, folder / "target" / Path(p).name, level / 100 * size, rng)) if level > 0
                     else p for k, p in targets.items()}
            table = {"surface": files["surface"]} if "surface" in files else {"surfaces": files}
            toml = ind.retarget(problem, table, f"noise_{name}.toml")
            outcome = bench.estimate(toml, folder, settings)
            seconds.append(outcome["seconds"])
            if "error" in outcome:
                refused += 1
                continue
            value = outcome["materials"][material][key]
            unc = outcome["uncertainty"][f"{material}.{key}"]
            found.append(value)
            sigmas.append(unc["std"])
            held.append(unc["ci95"][0] <= truth <= unc["ci95"][1])
            noises.append(outcome["uncertainty"]["noise_std"])
            low, high = unc["ci95"]
            points.append((name, level, 100 * (value - truth) / truth, 100 * (low - truth) / truth,
                           100 * (high - truth) / truth))
        rows.append(row(name, level, size, truth, found, sigmas, held, noises, seconds, refused))
        print(rows[-1], flush=True)
    return rows, points


def row(name, level, size, truth, found, sigmas, held, noises, seconds, refused) -> str:
    if not found:
        return f"| {name} | {level:g} % | {level / 100 * size:.3g} | - | - | - | - | - | {refused} | {np.mean(seconds):.0f} |"
    spread = f"{np.std(found):.3g}" if len(found) > 1 else "-"
    return (f"| {name} | {level:g} % | {level / 100 * size:.3g} | {100 * (np.mean(found) - truth) / truth:+.2f} % | "
            f"{spread} | {np.mean(sigmas):.3g} | {sum(held)} of {len(held)} | {np.mean(noises):.3g} | {refused} | "
            f"{np.mean(seconds):.0f} |")


def plot(points, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = sorted({p[0] for p in points})
    fig, axes = plt.subplots(1, len(names), figsize=(5.5 * len(names), 4), squeeze=False)
    for ax, name in zip(axes[0], names):
        mine = np.array([p[1:] for p in points if p[0] == name])
        jitter = (np.arange(len(mine)) % 5 - 2) * 0.03
        # The reported 95 % intervals themselves: a profile interval is not symmetric
        below, above = mine[:, 1] - mine[:, 2], mine[:, 3] - mine[:, 1]
        ax.errorbar(mine[:, 0] + jitter, mine[:, 1], yerr=[below, above], fmt="o", ms=3, capsize=2)
        ax.axhline(0.0, color="k", lw=0.8)
        ax.set_xlabel("noise std, % of the organ's size")
        ax.set_ylabel("error %  (bars: 95 % interval)")
        ax.set_title({"letter": f"letter A, nu = {LETTER_NU}", "phantom": f"phantom, prostate E = {PROSTATE_E:g}"}[name])
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cases", default="letter,phantom")
    parser.add_argument("--levels", type=bench.numbers, default=[0, 0.25, 0.5, 1, 2], help="noise std, %% of organ size")
    parser.add_argument("--draws-letter", type=int, default=10)
    parser.add_argument("--draws-phantom", type=int, default=3)
    parser.add_argument("--out", type=Path, default=ROOT / "out" / "bench-independent")
    parser.add_argument("--plot", type=Path, help="write the error and 95 %% interval plot here (png)")
    args = parser.parse_args()
    print("| case | noise, % of size | noise std | mean error | spread | mean sigma | interval holds the truth "
          "| noise std found | refused | s per estimate |\n|" + "---|" * 10, flush=True)
    points = []
    for name in args.cases.split(","):
        draws = args.draws_letter if name == "letter" else args.draws_phantom
        points += one_case(name, args.out.resolve(), args.levels, draws)[1]
    if args.plot:  # cases run separately land in one plot: the other cases' points are kept
        store = args.plot.with_suffix(".json")
        ran = {p[0] for p in points}
        kept = [p for p in json.loads(store.read_text()) if p[0] not in ran] if store.is_file() else []
        store.write_text(json.dumps(kept + points))
        plot(kept + points, args.plot)


if __name__ == "__main__":
    main()
