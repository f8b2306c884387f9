"""Prostate elastography on a synthetic pelvis with reduced force bases (paper §3.3-4).

    python demos/prostate_elastography.py [--out out/demo] [--quick]

The story:
1. A source patient (the prostate phantom) and a dozen example deformations of it:
   bladder and rectum inflated and shifted by random amounts (tissue 10 kPa,
   prostate somewhere in 20-80 kPa), written as surfaces like a CT would give them.
2. `train`: surface-match the source to every example, PCA of the bladder/rectum
   displacements -> force bases W.
3. Held-out targets: a finer mesh of the same patient, true prostate E in
   {25, 50, 75} kPa, organ displacements *not* drawn from the examples.
4. Estimate the prostate E from the organ surfaces only (closest-point distance), with
   the bases (rank r) and with the full force space, and print the paper's Table 1.
5. Fig. 8: rank vs E error vs iterations vs time; Fig. 7: the first two bases.
6. Multi-source (paper §3.3.3): nine more patients (phantom seeds 1-9) with a dozen
   examples each are brought into one atlas numbering; the bases are carried to two
   patients that were never trained on (seeds 10, 11) and estimate their prostate E.

Everything lands in --out, with index.md listing the tables and pictures.
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np

import fenics_elasto  # noqa: F401
from fenics_elasto.estimate import Options, estimate
from fenics_elasto.io import write_matched_surfaces
from fenics_elasto.meshing import build_scene, phantom_organs
from fenics_elasto.objective import InverseProblem
from fenics_elasto.reduction import bases_for_patient, train_atlas_bases, train_bases
from fenics_elasto.scene import load_scene
from fenics_elasto.simulate import simulate

TRUE_E = (25.0, 50.0, 75.0)
ORGANS = ("bladder", "prostate_surface", "rectum")


def organ_motion(organs: dict, bladder_scale, bladder_shift, rectum_scale, rectum_shift) -> list[str]:
    """--set overrides: the bladder inflates about its centre, the rectum about its axis."""
    bc = organs["bladder"]["center"]
    rc = organs["rectum"]["center"]
    return [
        f"boundary.displacement.bladder={{scale={bladder_scale}, center={list(map(float, bc))}, "
        f"value={list(map(float, bladder_shift))}}}",
        f"boundary.displacement.rectum={{gradient=[[{rectum_scale}, 0, 0], [0, {rectum_scale}, 0], [0, 0, 0]], "
        f"center={list(map(float, rc))}, value={list(map(float, rectum_shift))}}}",
    ]


def make_examples(source: Path, out: Path, count: int, seed: int = 1, patient: int = 0) -> list[Path]:
    """Example deformations of a patient (phantom seed), saved as organ surfaces."""
    rng = np.random.default_rng(seed)
    organs = phantom_organs(patient)
    folders = []
    for i in range(count):
        motion = organ_motion(organs, rng.uniform(0.0, 0.15), rng.uniform(-0.15, 0.15, 3),
                              rng.uniform(0.0, 0.2), rng.uniform(-0.1, 0.1, 3))
        scene = load_scene(source, motion + [f"materials.prostate.E={rng.uniform(20, 80):.1f}"])
        folders.append(out / f"example_{i:02d}")
        write_matched_surfaces(folders[-1], scene, simulate(scene).u)
    return folders


def make_target(out: Path, E: float, size: float, patient: int = 0) -> dict:
    """The held-out 'measurement': a finer mesh, organ motion unlike the examples."""
    organs = phantom_organs(patient)
    problem = build_scene("prostate-phantom", out / "fine", size=size, seed=patient)
    motion = organ_motion(organs, 0.12, [0.1, -0.1, 0.05], 0.15, [0.05, 0.0, 0.0])
    scene = load_scene(problem, motion + [f"materials.prostate.E={E}"])
    folder = out / f"target_E{E:g}"
    write_matched_surfaces(folder, scene, simulate(scene).u)
    return {g: str((folder / f"surface_{g}.vtp").resolve()) for g in ORGANS}


def run_case(source: Path, target: dict, basis=None, options=None):
    table = ", ".join(f"{g}='{f}'" for g, f in target.items())
    problem = InverseProblem(load_scene(source, [f"target={{surfaces={{{table}}}}}"]))
    start = time.perf_counter()
    result, u, _ = estimate(problem, options=options, say=lambda *_: None, basis=basis)
    result["seconds"] = time.perf_counter() - start
    return result, problem, u


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("out/demo"))
    parser.add_argument("--quick", action="store_true", help="fewer examples and cases (for CI)")
    args = parser.parse_args()
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    count, cases, fine = (6, (50.0,), 1.3) if args.quick else (12, TRUE_E, 1.3)

    source = build_scene("prostate-phantom", out / "source", size=1.6)
    print(f"1. {count} example deformations of the source patient", flush=True)
    examples = make_examples(source, out / "examples", count)
    print("2. train the force bases", flush=True)
    trainer = InverseProblem(load_scene(source), target=False)
    bases = train_bases(trainer, examples, rank=count, say=lambda *_: None)
    bases.save(out / "bases.npz")
    print(f"   rank {bases.W.shape[1]} of {trainer.force_dofs} force dofs; explained variance "
          + " ".join(f"{v:.3f}" for v in bases.variance), flush=True)

    rows, targets = [], {}
    for E in cases:
        print(f"3. target with prostate E = {E:g} kPa (fine mesh h = {fine})", flush=True)
        target = targets[E] = make_target(out, E, fine)
        reduced, _, _ = run_case(source, target, bases.W)
        full, _, _ = run_case(source, target, options=Options(inner_maxiter=15, outer_maxiter=4))
        rows.append((E, reduced, full))
        for name, r in (("reduced", reduced), ("full", full)):
            print(f"   {name:7s} E = {r['materials']['prostate']['E']:.2f}  ({r['seconds']:.1f} s, "
                  f"{r['iterations']['outer']} outer / {r['iterations']['inner']} inner)", flush=True)

    lines = table1(rows, bases.W.shape[1], trainer.force_dofs)
    print("\n".join(lines))
    print("4. Fig. 8: rank against E error, iterations and time", flush=True)
    ranks = sorted({r for r in (1, 4, 8, 12) if r <= count})
    sweep = []
    for rank in ranks:
        r, _, _ = run_case(source, targets[cases[len(cases) // 2]], bases.W[:, :rank])
        sweep.append((rank, abs(r["materials"]["prostate"]["E"] - cases[len(cases) // 2]) / cases[len(cases) // 2],
                      r["iterations"]["inner"], r["seconds"]))
        print(f"   rank {rank:2d}: E error {100 * sweep[-1][1]:.1f} %, {sweep[-1][2]} inner iterations, "
              f"{sweep[-1][3]:.1f} s", flush=True)
    plot_rank_sweep(sweep, out / "fig8_rank.png")
    print("5. Fig. 7: the first two force bases on bladder and rectum", flush=True)
    render_bases(trainer, bases.W, out / "fig7_bases.png")
    lines += ["", "| rank | E error % | inner iterations | seconds |", "|---|---|---|---|"]
    lines += [f"| {k} | {100 * e:.1f} | {it} | {sec:.1f} |" for k, e, it, sec in sweep]
    lines += ["", "![rank sweep](fig8_rank.png)", "", "![first two bases](fig7_bases.png)"]
    print("6. multi-source bases through an atlas, held-out patients", flush=True)
    patients, examples, held = (3, 4, (10,)) if args.quick else (9, 12, (10, 11))
    atlas_lines = atlas_study(out / "atlas_study", patients, examples, held, cases, fine, rank=24)
    print("\n".join(atlas_lines))
    lines += [""] + atlas_lines
    (out / "index.md").write_text("# Prostate elastography demo\n\n" + "\n".join(lines) + "\n")
    (out / "table1.json").write_text(json.dumps(
        [{"E_true": E, "reduced": r["materials"]["prostate"]["E"], "full": f["materials"]["prostate"]["E"],
          "reduced_s": r["seconds"], "full_s": f["seconds"]} for E, r, f in rows], indent=2))


def plot_rank_sweep(sweep, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ranks, errors, iterations, seconds = map(np.array, zip(*sweep))
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    for ax, values, label in zip(axes, (100 * errors, iterations, seconds),
                                 ("E error %", "inner iterations", "time s")):
        ax.plot(ranks, values, "o-")
        ax.set(xlabel="rank of the force bases", ylabel=label)
    fig.suptitle("Fig. 8: reduced rank against accuracy and cost")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def render_bases(problem: InverseProblem, W: np.ndarray, path: Path) -> None:
    """Arrows of the first two bases on the loaded nodes (bladder and rectum)."""
    import pyvista as pv

    from fenics_elasto.render import offscreen_plotter

    points = problem.loaded.gather(problem.loaded.coords)
    plotter = offscreen_plotter(shape=(1, 2), window_size=(1600, 800))
    for k in range(min(2, W.shape[1])):
        plotter.subplot(0, k)
        cloud = pv.PolyData(points)
        vectors = W[:, k].reshape(-1, 3)
        cloud["mode"] = vectors
        cloud["|mode|"] = np.linalg.norm(vectors, axis=1)
        scale = 1.0 / max(cloud["|mode|"].max(), 1e-300)
        plotter.add_mesh(cloud.glyph(orient="mode", scale="|mode|", factor=0.8 * scale), scalars="|mode|",
                         cmap="plasma", show_scalar_bar=False)
        plotter.add_text(f"principal component {k + 1}", font_size=12)
        plotter.view_vector((1.0, -1.6, 0.7), viewup=(0.0, 0.0, 1.0))
    plotter.screenshot(str(path))
    plotter.close()


def atlas_study(out: Path, patients: int, examples: int, held_out, cases, fine: float, rank: int):
    """Multi-source bases (paper §3.3.3): train on several patients through an atlas,
    estimate on patients that were not in the training set."""
    atlas = InverseProblem(load_scene(build_scene("prostate-phantom", out / "atlas", size=1.6)), target=False)
    training = []
    for seed in range(1, patients + 1):
        source = build_scene("prostate-phantom", out / f"patient{seed}", size=1.6, seed=seed)
        folders = make_examples(source, out / f"patient{seed}" / "examples", examples, seed=100 + seed, patient=seed)
        training.append((InverseProblem(load_scene(source), target=False), folders))
        print(f"   patient {seed}: {examples} example deformations", flush=True)
    bases = train_atlas_bases(atlas, training, rank, say=lambda *_: None)
    print(f"   atlas bases: rank {bases.W.shape[1]} from {bases.examples} examples; explained variance "
          + " ".join(f"{v:.3f}" for v in bases.variance[:8]) + " ...", flush=True)
    rows = []
    for seed in held_out:
        source = build_scene("prostate-phantom", out / f"heldout{seed}", size=1.6, seed=seed)
        for E in cases:
            target = make_target(out / f"heldout{seed}", E, fine, patient=seed)
            table = ", ".join(f"{g}='{f}'" for g, f in target.items())
            problem = InverseProblem(load_scene(source, [f"target={{surfaces={{{table}}}}}"]))
            start = time.perf_counter()
            basis = bases_for_patient(atlas, bases, problem)
            result, _, _ = estimate(problem, say=lambda *_: None, basis=basis)
            result["seconds"] = time.perf_counter() - start
            rows.append((seed, E, result))
            print(f"   held-out patient {seed}, E = {E:g}: recovered {result['materials']['prostate']['E']:.2f} "
                  f"({result['seconds']:.1f} s)", flush=True)
    lines = [f"Held-out patients with atlas bases ({patients} training patients x {examples} examples, "
             f"rank {bases.W.shape[1]})", "",
             "| patient | true E | recovered E | error % | seconds | outer/inner |", "|---|---|---|---|---|---|"]
    for seed, E, r in rows:
        found = r["materials"]["prostate"]["E"]
        lines.append(f"| {seed} | {E:g} | {found:.2f} | {100 * abs(found - E) / E:.1f} | {r['seconds']:.1f} | "
                     f"{r['iterations']['outer']}/{r['iterations']['inner']} |")
    return lines


def table1(rows, rank, force_dofs) -> list[str]:
    lines = [f"Table 1 (reduced: rank {rank}; full: {force_dofs} force dofs; tissue E = 10 kPa)", "",
             "| true E | reduced E | error % | full E | error % | speed-up | outer/inner (reduced) | outer/inner (full) |",
             "|---|---|---|---|---|---|---|---|"]
    for E, r, f in rows:
        er, ef = r["materials"]["prostate"]["E"], f["materials"]["prostate"]["E"]
        lines.append(f"| {E:g} | {er:.2f} | {100 * abs(er - E) / E:.1f} | {ef:.2f} | {100 * abs(ef - E) / E:.1f} | "
                     f"{f['seconds'] / r['seconds']:.1f}x | {r['iterations']['outer']}/{r['iterations']['inner']} | "
                     f"{f['iterations']['outer']}/{f['iterations']['inner']} |")
    return lines


if __name__ == "__main__":
    main()
