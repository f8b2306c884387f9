"""Are the 95 % intervals calibrated? Coverage and sigma against the spread, under noise.

    python benchmarks/coverage.py [--draws 30] [--cases letter,inclusion] [--noise 0.005,0.02] [--truth T]

For each case a target is simulated once on a finer mesh (letter A: h = 0.2 against the
source's 0.4, true nu = 0.3; inclusion: h = 0.25 against 0.5, true E ratio 5), then for
each noise level (a fraction of the body's size, as the std of Gaussian noise added to
every target point) ``--draws`` noisy copies are estimated. Printed per case and level:
the coverage of the 95 % interval (share of draws whose interval holds the truth), the
mean reported sigma against the spread (std) of the estimates over the draws, the mean
error, the mean noise std the estimate found from its residual, and what the
uncertainty cost (``uncertainty.seconds``: posterior, offset and profile interval)
against the rest of the estimate.

Draws whose interval is wider than the bounds are refused by default ("undetermined");
here they are estimated anyway (allow_undetermined) and counted in the last column.
The interval states noise only; without noise the discretisation bias (source against
target mesh) is all there is, and coverage then says how large that bias is against
the noise-free sigma (see docs/uncertainty.md).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import fenics_elasto  # noqa: F401
from fenics_elasto.inverse.options import Options
from fenics_elasto.inverse.estimator import estimate
from fenics_elasto.files.writers import write_matched_surfaces
from fenics_elasto.mesh.builtin import build_scene
from fenics_elasto.inverse.objective import InverseProblem
from fenics_elasto.model.scene import load_scene
from fenics_elasto.model.simulate import simulate

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import independent as ind  # noqa: E402  (tests/independent.py: noisy copies of targets)

CASES = {  # name: (scene, source h, target h, truth settings, estimated label, truth, body size)
    "letter": ("letter-a", 0.4, 0.2, {"materials.letter.nu": 0.3}, "letter.nu", 0.3, 10.0),
    "inclusion": ("inclusion", 0.5, 0.25, {"materials.inclusion.E": 50.0}, "inclusion.E", 5.0, 10.0),
}


def with_truth(name: str, value: float | None) -> None:
    """Another true value for a case (``--truth``: a case the rules were not chosen on);
    an E ratio scales the inclusion's E, the reference region's staying."""
    if value is None:
        return
    scene_name, h, fine, settings, label, truth, size = CASES[name]
    key, setting = next(iter(settings.items()))
    CASES[name] = (scene_name, h, fine, {key: setting * value / truth}, label, value, size)


def target_folder(tmp: Path, name: str) -> tuple[Path, dict[str, Path]]:
    """The source's problem.toml and the noise-free target surfaces (group -> file)."""
    scene_name, h, fine, truth, *_ = CASES[name]
    source = build_scene(scene_name, tmp / name / "source", size=h)
    scene = load_scene(build_scene(scene_name, tmp / name / "fine", size=fine), truth)
    write_matched_surfaces(tmp / name / "target", scene, simulate(scene).u, pieces=8)
    return source, {g: tmp / name / "target" / f"surface_{g}.vtp" for g in scene.matched}


def noisy_targets(surfaces: dict[str, Path], folder: Path, std: float, rng) -> dict:
    folder.mkdir(parents=True, exist_ok=True)
    out = {group: str(ind.noisy_copy(path, folder / f"{group}.vtp", std, rng)) for group, path in surfaces.items()}
    return {"target": {"surfaces": out}}


def one_case(tmp: Path, name: str, levels, draws: int, known_noise: bool = False) -> list[str]:
    *_, label, truth, size = CASES[name]
    source, surfaces = target_folder(tmp, name)
    rows = []
    for level in levels:
        rng = np.random.default_rng(7)
        found, sigmas, inside, noises, shares, start = [], [], [], [], [], time.perf_counter()
        determined = []
        for draw in range(draws if level > 0 else 1):
            settings = noisy_targets(surfaces, tmp / name / f"noisy_{level}_{draw}", level * size, rng) if level > 0 \
                else {"target": {"surfaces": {g: str(p) for g, p in surfaces.items()}}}
            if known_noise and level > 0:  # the user states the noise: [target] noise
                settings["target"]["noise"] = level * size
            problem = InverseProblem(load_scene(source, settings))
            options = Options.from_scene(problem.scene)
            options.allow_undetermined = True  # measured anyway; counted below
            result = estimate(problem, options)
            determined.append(not any("undetermined" in w for w in result.warnings))
            value = ratio(result, label)
            unc = result["uncertainty"][label]
            scale = value / result.estimated[label] if label.endswith(".E") else 1.0  # an E ratio: scaled alike
            found.append(value)
            sigmas.append(unc["std"] * scale)
            inside.append(unc["ci95"][0] * scale <= truth <= unc["ci95"][1] * scale)
            noises.append(result["uncertainty"]["noise_std"])
            spent = result["uncertainty"]["seconds"]
            shares.append(spent / (result["wall_time_s"] - spent))
        found, sigmas, inside, determined = map(np.array, (found, sigmas, inside, determined))
        rows.append(f"| {name} | {100 * level:g} % | {len(found)} | {coverage(found, sigmas, inside, truth)} | "
                    f"{np.mean(noises):.2g} | {(time.perf_counter() - start) / len(found):.1f} | "
                    f"{100 * np.median(shares):.0f} % ({100 * np.max(shares):.0f} %) | "
                    f"{len(found) - determined.sum()} | "
                    f"{coverage(found[determined], sigmas[determined], inside[determined], truth)} |")
        print(rows[-1], flush=True)
    return rows


def coverage(found, sigmas, inside, truth) -> str:
    """coverage | mean sigma | spread | sigma / spread | mean error, over these draws."""
    if not len(found):
        return "- | - | - | - | -"
    spread = float(np.std(found)) if len(found) > 1 else float("nan")
    return (f"{100 * np.mean(inside):.0f} % | {np.mean(sigmas):.3g} | {spread:.3g} | "
            f"{np.mean(sigmas) / spread if spread > 0 else float('nan'):.2f} | "
            f"{100 * (np.mean(found) - truth) / truth:+.2f} %")


def ratio(result, label: str) -> float:
    """The estimated value; for an E, the ratio to the reference region's E."""
    material, key = label.split(".")
    value = result.materials[material][key]
    if key == "E":
        reference = next(m for m, v in result.materials.items() if m != material)
        value /= result.materials[reference]["E"]
    return value


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--draws", type=int, default=30)
    parser.add_argument("--cases", default="letter,inclusion")
    parser.add_argument("--noise", default="0,0.005,0.02", help="noise std as fractions of the body size")
    parser.add_argument("--truth", type=float, help="another true value (nu, or the E ratio) for every case run")
    parser.add_argument("--known-noise", action="store_true", help="give the estimate the true noise ([target] noise)")
    args = parser.parse_args()
    levels = [float(v) for v in args.noise.split(",")]
    print("| case | noise (of body size) | draws | coverage of the 95 % interval | mean sigma | spread of estimates "
          "| sigma / spread | mean error | noise std found | s per estimate "
          "| uncertainty's cost: share of the rest of the estimate, median (max) | undetermined (refused by default) "
          "| determined draws only: coverage | mean sigma | spread | sigma / spread | mean error |")
    print("|" + "---|" * 17)
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.cases.split(","):
            with_truth(name, args.truth)
            one_case(Path(tmp), name, levels, args.draws, args.known_noise)


if __name__ == "__main__":
    main()
