"""The paper's 2D experiment (Lee & Lin 2012, Fig. 5): recover Poisson's ratio of a
letter A from its deformed outline.

    python demos/letter_a_poisson.py [--out out/letter_a] [--degree 2]

For each true nu, a target is simulated on a finer mesh (h = 0.2) with the top pushed
down and sideways; the estimate runs on the coarser source mesh (h = 0.4) with the
top forces unknown and only the deformed outline known (closest-point distance, no
correspondence). It prints true / recovered / error / time and draws Phi*(nu) for
each case, like the paper's Fig. 5.
"""

import argparse
import time
from pathlib import Path

import numpy as np

import fenics_elasto  # noqa: F401
from fenics_elasto.inverse.estimator import Estimator, estimate
from fenics_elasto.inverse.options import Options
from fenics_elasto.files.writers import write_matched_surfaces
from fenics_elasto.mesh.builtin import build_scene
from fenics_elasto.inverse.objective import InverseProblem
from fenics_elasto.model.scene import load_scene
from fenics_elasto.model.simulate import simulate

CASES = (0.1, 0.25, 0.4, 0.49)


def make_target(out: Path, nu: float, degree: int) -> Path:
    """The 'measured' outline: a finer mesh, the same letter, the true nu."""
    scene = load_scene(build_scene("letter-a", out / "fine", size=0.2), [f"materials.letter.nu={nu}", f"degree={degree}"])
    write_matched_surfaces(out / f"target_nu{nu}", scene, simulate(scene).u)
    return out / f"target_nu{nu}" / "surface.vtp"


def profile(problem: InverseProblem, values) -> list[float]:
    """Phi*(nu): the inner optimum over the forces at each nu (the curve of Fig. 5)."""
    profile = Estimator(problem, Options.from_scene(problem.scene)).profile
    return [profile.solve(np.array([nu]), "probe").value for nu in values]


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("out/letter_a"))
    parser.add_argument("--degree", type=int, default=2)
    args = parser.parse_args()
    source = build_scene("letter-a", args.out / "source", size=0.4)

    rows, curves = [], {}
    for nu in CASES:
        target = make_target(args.out, nu, args.degree)
        scene = load_scene(source, [f"target.surface='{target.resolve()}'", f"degree={args.degree}"])
        problem = InverseProblem(scene)
        start = time.perf_counter()
        result = estimate(problem)
        seconds = time.perf_counter() - start
        found = result["materials"]["letter"]["nu"]
        rows.append((nu, found, 100 * abs(found - nu) / nu, seconds, result["iterations"]["outer"],
                     result["iterations"]["inner"], result["factorizations"]))
        grid = np.linspace(0.02, 0.495, 40)
        curves[nu] = (grid, profile(problem, grid), found)

    print(f"letter A, P{args.degree}, source h = 0.4 ({problem.model.dofs.num_dofs} dofs, {problem.force_dofs} force dofs), "
          "target h = 0.2, outline only")
    print("| true nu | recovered | error % | time s | outer it. | inner it. | factorizations |")
    print("|---|---|---|---|---|---|---|")
    for nu, found, err, sec, outer, inner, fact in rows:
        print(f"| {nu:.2f} | {found:.4f} | {err:.2f} | {sec:.2f} | {outer} | {inner} | {fact} |")
    print("(the paper: about 10 % error and 4 s per case)")
    plot(curves, args.out / "letter_a_poisson.png")
    print(f"Phi*(nu) curves: {args.out / 'letter_a_poisson.png'}")


def plot(curves: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(curves), figsize=(4 * len(curves), 3.6))
    for ax, (nu, (grid, phi, found)) in zip(axes, curves.items()):
        ax.semilogy(grid, phi, "-", color="C0")
        ax.axvline(nu, color="k", ls="--", lw=0.8, label="true")
        ax.axvline(found, color="C3", lw=1.0, label="recovered")
        ax.set(title=f"true nu = {nu}", xlabel="nu", ylabel="Phi*(nu)")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
