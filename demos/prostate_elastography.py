# %% [markdown]
# # Prostate elastography with reduced force bases
#
# This demo repeats the 3D study of Lee & Lin (2012, §3.3-4) on a synthetic pelvis: soft
# tissue (E = 10 kPa) around a bladder, a prostate and a rectum, clamped at the bones.
# Bladder and rectum fill and shift by amounts nobody measured; all we are shown is where
# the three organ surfaces went, as a CT would show them. From those surfaces we recover
# Young's modulus $E$ of the prostate -- stiffer tissue there is what the examination
# looks for.
#
# Run it with `python demos/prostate_elastography.py` (`make demo`, 4-6.5 min; the
# results land in `out/demo/`, with `index.md` listing the tables and pictures). Three
# options change the run:
#
# - `--quick` (`make demo-quick`): one target $E$, no full-space comparison, ranks 1 and
#   12 only in the rank sweep, no atlas study;
# - `--out DIR`: the folder for the results;
# - `--organ-size 0.2` (`make demo-accurate`): the organ walls meshed at 0.2 $h$ instead
#   of 0.35 $h$ in sources and targets, which takes $E$ from about +5 % to about +1 % of
#   its converged value at about 3x the time.
#
# ## The problem
#
# Linear elasticity with Lagrange elements of degree 2 on the pelvis $\Omega$, curved
# tetrahedra at the organs. The walls of bladder and rectum are *loaded*: the unknown
# forces $F$ on their nodes move the body,
#
# $$
# K(E)\, u = P F ,
# $$
#
# with $K(E)$ the stiffness matrix, linear in the Lamé coefficients of each region. With
# unknown forces only ratios of Young's moduli are identifiable, so the tissue's
# $E = 10$ kPa is the reference and the prostate's $E$ is the one unknown material
# constant. The misfit compares every node $x_l$ of the three organ surfaces, moved by
# $u_l$, with its closest point on the observed surface $\Gamma$ of its organ:
#
# $$
# \Phi(F, E) = \frac{1}{2} \sum_l \left| x_l + u_l - \mathrm{cp}_\Gamma(x_l + u_l) \right|^2 .
# $$
#
# ## Reduced force bases
#
# The walls carry thousands of force unknowns, and with surfaces as data they are too
# free: a wall node may slide along its target surface at no cost, so the full force
# space fits the organs whatever $E$ is. The paper's answer is a basis $W$ of the wall
# motions that actually occur. Given example deformations of the patient, each
# surface-matched to give the wall displacement $d_i$, $W$ holds the first $r$ principal
# directions (the uncentred PCA) of
#
# $$
# D = \begin{bmatrix} d_1 & d_2 & \cdots & d_n \end{bmatrix},
# $$
#
# and the walls move by $d = W q$ with $r$ generalised forces $q$. The estimate is
# nested: for each $E$ the $q$ are fitted, and the outer problem minimises the profile
#
# $$
# \Phi^*(E) = \min_q \Phi(q, E) + \frac{\alpha}{2} \left| q - q_0 \right|^2
# $$
#
# over $\log E$, with $q_0$ from surface matching and a small $\alpha$ (see
# [the method](../method.md)). One factorization of $K(E)$ and an $r$-column block solve
# give the response of every basis; the inner iterations then need no finite-element
# solve at all.
#
# ## Set-up
#
# The three options are read straight from the command line (anything else there is
# ignored, so that the script also runs as a notebook). `fenics_elasto.app.study` holds
# what this demo shares with the benchmarks and tests: the phantom's wall motions, the
# simulated example scans and targets, one timed estimate (`run_case`) and the tables.

# %%
import json
import sys
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pyvista as pv

import fenics_elasto as fe  # first: it sets up the DOLFINx wheel's MPI and PETSc
from fenics_elasto.app.render import offscreen_plotter
from fenics_elasto.app.study import (FINE, SIZE, TRUE_E, iterations, rank_sweep, rank_table, recovered, run_case,
                                     simulate_examples, simulate_targets, speedup_table, table1)
from fenics_elasto.inverse.objective import InverseProblem
from fenics_elasto.inverse.reduction.bases import train_atlas_bases
from fenics_elasto.mesh.atlas import atlas_surfaces
from fenics_elasto.mesh.builtin import ORGAN_SIZE, PROSTATE_SIZE

argv = sys.argv[1:]
unknown = [a for a in argv if a.startswith("--") and a not in ("--quick", "--out", "--organ-size")]
if unknown and "ipykernel" not in sys.modules:  # run as a script: a mistyped option is an error, not ignored
    sys.exit(f"prostate_elastography.py: unknown option {unknown[0]} (known: --quick, --out DIR, --organ-size X)")
quick = "--quick" in argv
out = Path(argv[argv.index("--out") + 1]) if "--out" in argv else Path("out/demo")
detail = {"organ_size": float(argv[argv.index("--organ-size") + 1])} if "--organ-size" in argv else {}

out.mkdir(parents=True, exist_ok=True)
cases = (50.0,) if quick else TRUE_E  # the true prostate E (kPa) of the held-out targets
middle = cases[len(cases) // 2]
count = 12  # example deformations of the source patient

# %% [markdown]
# ## 1. The source patient and its example deformations
#
# `fe.build_scene` writes the phantom's gmsh mesh ($h$ = `SIZE` = 1.6 cm away from the
# organs) and its problem file: the prostate's $E$ estimated within $[2, 300]$ kPa, the
# bones fixed, bladder and rectum loaded, all three organs matched. The dozen examples
# inflate the bladder and widen the rectum by random amounts and shift both; the
# prostate keeps one $E$, drawn from 20, 40, 60 and 80 kPa. Each example is written as organ surfaces,
# the only thing a scan of it would give.

# %%
source = fe.build_scene("prostate-phantom", out / "source", size=SIZE, **detail)
print(f"1. {count} example deformations of the source patient", flush=True)
examples = simulate_examples(source, out / "examples", count)

# %% [markdown]
# ## 2. Training the bases
#
# `fe.train` surface-matches the source to every example and takes the principal
# directions of the bladder and rectum displacements: $W$, with one column per example
# here (rank 12), and the share of the examples' energy each column explains.

# %%
print("2. train the force bases", flush=True)
bases = fe.train(fe.load_scene(source), examples=examples, rank=count)
bases.save(out / "bases.npz")
force_dofs, rank = bases.W.shape
print(f"   rank {rank} of {force_dofs} force dofs; explained variance "
      + " ".join(f"{v:.3f}" for v in bases.variance), flush=True)

# %% [markdown]
# ## 3. Held-out targets
#
# The "measurements" must not come from the mesh the estimate runs on, nor from the
# motions the bases were trained on. So the targets are simulated on a finer mesh of the
# same patient ($h$ = `FINE` = 1.3 cm) with the true prostate $E$ of 25, 50 and 75 kPa
# and a wall motion unlike any example's. The curved organ facets are written as 8 x 8
# flat triangles each; beside the surfaces, each target also keeps *landmarks*: the fine
# solution at the source's matched nodes, used in step 4's comparison.

# %%
print(f"3. targets with prostate E = {', '.join(f'{E:g}' for E in cases)} kPa (fine mesh h = {FINE})", flush=True)
targets = simulate_targets(out, cases, FINE, source=source, **detail)

# %% [markdown]
# ## 4. Table 1: the prostate's E from the organ surfaces
#
# Each estimate is the one `fe.estimate` makes with bases; `run_case` makes it on the
# bases' raw columns (so that the rank sweep below can cut them) and times it. Its
# result is the record that `fenics-elasto estimate` writes to `result.json`.

# %%
results = {}
for E in cases:
    result = results[E] = run_case(source, targets[E].settings(landmarks=False), bases.W)
    print(f"   true E = {E:g}, reduced, surfaces: E = {recovered(result):.2f} ({result['seconds']:.1f} s, "
          f"{iterations(result)} outer/inner; uncertainty {result['uncertainty']['seconds']:.2f} s of it)", flush=True)
lines = table1(results, rank)

# %% [markdown]
# How much do the bases save? With surfaces as data the question has no answer: the full
# force space cannot tell $E$ at all (see [known limits](../limits.md)). On the landmark
# targets, where every source node that is matched has a known position, both can, so
# reduced and full force spaces are compared there. `--quick` skips this: a full-space
# estimate costs several reduced ones.

# %%
print("4. speed-up: full force space against reduced, landmark targets"
      + (" (skipped by --quick: a full-space estimate costs three reduced ones)" if quick else ""), flush=True)
speedups = []
for E in () if quick else cases:
    settings = targets[E].settings(landmarks=True)
    full, reduced = run_case(source, settings), run_case(source, settings, bases.W)
    speedups.append((E, full, reduced))
    print(f"   true E = {E:g}: full {recovered(full):.2f} ({full['seconds']:.1f} s), "
          f"reduced {recovered(reduced):.2f} ({reduced['seconds']:.1f} s)", flush=True)
lines += ([""] + speedup_table(speedups, force_dofs, rank)) if speedups else []
lines += ["", "With surface targets the full force space does not determine E: the organ walls slide "
              "along the target and every E fits (see docs/limits.md)."]
print("\n".join(lines), flush=True)

# %% [markdown]
# One run of `make demo` gave (the [measured run](../demo_index.md) keeps all its
# tables):
#
# | true $E$ | recovered $E$ | error % | seconds | outer/inner iterations |
# |---|---|---|---|---|
# | 25 | 25.76 | 3.0 | 4.4 | 2/10 |
# | 50 | 51.61 | 3.2 | 4.7 | 2/8 |
# | 75 | 77.59 | 3.5 | 4.6 | 2/10 |
#
# and on the landmark targets a speed-up of 4.6-5.3x over the full force space (3828
# force unknowns against 12). The paper reports errors of 0.1-8.1 %.
#
# ## 5. Fig. 8: the rank of the bases
#
# How many bases are needed? The target with the middle $E$ is estimated again with the
# first 1, 4 and 8 columns of $W$ (the full rank's estimate is known already), and the
# error, the inner iterations and the time are plotted against the rank.


# %%
def plot_rank_sweep(sweep, path: Path) -> None:
    ranks, errors, inner, seconds = map(np.array, zip(*sweep))
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    for ax, values, label in zip(axes, (100 * errors, inner, seconds), ("E error %", "inner iterations", "time s")):
        ax.plot(ranks, values, "o-")
        ax.set(xlabel="rank of the force bases", ylabel=label)
    fig.suptitle("Fig. 8: reduced rank against accuracy and cost")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


print("5. Fig. 8: rank against E error, iterations and time", flush=True)
ranks = [k for k in ((1,) if quick else (1, 4, 8)) if k < rank] + [rank]
sweep = rank_sweep(source, targets[middle].settings(landmarks=False), bases.W, ranks, middle,
                   known={rank: results[middle]})
plot_rank_sweep(sweep, out / "fig8_rank.png")
lines += ["", f"Fig. 8 data (surfaces, E = {middle:g})", ""] + rank_table(sweep)

# %% [markdown]
# ![rank sweep](../docs/fig8_rank.png)
#
# The error does not fall steadily with the rank: bases that miss part of the wall
# motion leave it to be explained by a wrong $E$ (one run: 15 % at rank 1, 25 % at
# rank 4); from rank 8 on the error stays near 3 %.
#
# ## Fig. 7: the first two bases
#
# Each column of $W$ is a displacement of the loaded nodes (`bases.loaded_coords`);
# drawn as arrows on the bladder and rectum, the first two show the dominant motions of
# the examples: the first is mostly the bladder filling, the second mostly a shift of
# both organs.


# %%
def render_bases(bases: fe.Bases, path: Path) -> None:
    plotter = offscreen_plotter(shape=(1, 2), window_size=(1600, 800))
    for k in range(min(2, bases.rank)):
        plotter.subplot(0, k)
        cloud = pv.PolyData(bases.loaded_coords)
        vectors = bases.W[:, k].reshape(-1, 3)
        cloud["mode"] = vectors
        cloud["|mode|"] = np.linalg.norm(vectors, axis=1)
        scale = 1.0 / max(cloud["|mode|"].max(), 1e-300)
        plotter.add_mesh(cloud.glyph(orient="mode", scale="|mode|", factor=0.8 * scale), scalars="|mode|",
                         cmap="plasma", show_scalar_bar=False)
        plotter.add_text(f"principal component {k + 1}", font_size=12)
        plotter.view_vector((1.0, -1.6, 0.7), viewup=(0.0, 0.0, 1.0))
    plotter.screenshot(str(path))
    plotter.close()


print("   Fig. 7: the first two force bases on bladder and rectum", flush=True)
render_bases(bases, out / "fig7_bases.png")
lines += ["", "![rank sweep](fig8_rank.png)", "", "![first two bases](fig7_bases.png)"]

# %% [markdown]
# ![the first two bases](../docs/fig7_bases.png)
#
# ## 6. Bases from several patients
#
# Bases trained on the patient being examined need example scans of that patient. The
# paper's §3.3.3 trains them on other patients instead, through an *atlas*: every
# patient's mesh is built around the atlas's bladder and rectum (here patient 0's,
# fitted onto the patient's own organs), so that all patients share the loaded nodes
# and one $W$ describes them all. Nine more phantoms (seeds 1-9) with a dozen examples
# each give one PCA of rank 24; two patients that were never trained on (seeds 10 and 11)
# then have their prostate's $E$ estimated with those bases. `--quick` skips this: its
# ten meshes and their examples cost as much as the rest of the quick run.


# %%
def atlas_study(out: Path, patients: int, examples: int, held_out, cases, rank: int) -> list[str]:
    atlas = fe.build_scene("prostate-phantom", out / "atlas", size=SIZE, **detail).parent / "phantom.msh"
    training = []
    for seed in range(1, patients + 1):
        source = fe.build_scene("prostate-phantom", out / f"patient{seed}", size=SIZE, seed=seed, atlas=atlas, **detail)
        folders = simulate_examples(source, out / f"patient{seed}" / "examples", examples, seed=100 + seed, patient=seed)
        training.append((InverseProblem(fe.load_scene(source), target=False), folders))
        print(f"   patient {seed}: {examples} example deformations", flush=True)
    bases = train_atlas_bases(atlas_surfaces(atlas), training, rank)
    print(f"   atlas bases: rank {bases.rank} from {bases.examples} examples; explained variance "
          + " ".join(f"{v:.3f}" for v in bases.variance[:8]) + " ...", flush=True)
    rows = []
    for seed in held_out:
        source = fe.build_scene("prostate-phantom", out / f"heldout{seed}", size=SIZE, seed=seed, atlas=atlas, **detail)
        targets = simulate_targets(out / f"heldout{seed}", cases, FINE, patient=seed, **detail)
        basis = bases.on(InverseProblem(fe.load_scene(source), target=False))  # the loaded nodes: once per patient
        for E in cases:
            result = run_case(source, targets[E].settings(landmarks=False), basis)
            rows.append((seed, E, result))
            print(f"   held-out patient {seed}, E = {E:g}: recovered {recovered(result):.2f} "
                  f"({result['seconds']:.1f} s)", flush=True)
    table = [f"Held-out patients with atlas bases ({patients} training patients x {examples} examples, rank {bases.rank})",
             "", "| patient | true E | recovered E | error % | seconds | outer/inner |", "|---|---|---|---|---|---|"]
    for seed, E, r in rows:
        table.append(f"| {seed} | {E:g} | {recovered(r):.2f} | {100 * abs(recovered(r) - E) / E:.1f} | "
                     f"{r['seconds']:.1f} | {iterations(r)} |")
    return table


print("6. multi-source bases through an atlas, held-out patients"
      + (" (skipped by --quick: its meshes and examples cost as much as the rest)" if quick else ""), flush=True)
if not quick:
    atlas_lines = atlas_study(out / "atlas_study", 9, 12, (10, 11), cases, rank=24)
    print("\n".join(atlas_lines))
    lines += [""] + atlas_lines

# %% [markdown]
# One run gave errors of 1.5-2.1 % for the two held-out patients, in 4-6 s per estimate:
# bases from other patients serve as well as the patient's own.
#
# ## The results
#
# `index.md` collects the tables and pictures, `table1.json` the numbers of Table 1 and
# of the speed-up comparison.

# %%
organ = detail.get("organ_size", ORGAN_SIZE)
meshes = (f"Meshes: sources h = {SIZE:g} cm, {organ:g} h at bladder and rectum, {PROSTATE_SIZE:g} h at the prostate; "
          f"targets likewise at h = {FINE:g}, curved facets written as 8 x 8 flat pieces.")
(out / "index.md").write_text("# Prostate elastography demo\n\n" + meshes + "\n\n" + "\n".join(lines) + "\n")
(out / "table1.json").write_text(json.dumps(
    {"table1": [{"E_true": E, "E": recovered(r), "seconds": r["seconds"], "iterations": r["iterations"]}
                for E, r in results.items()],
     "speedup": [{"E_true": E, "full": {"E": recovered(full), "seconds": full["seconds"]},
                  "reduced": {"E": recovered(reduced), "seconds": reduced["seconds"]}}
                 for E, full, reduced in speedups]}, indent=2))
print(f"results: {out / 'index.md'}")

# %% [markdown]
# The [validation page](../validation.md) keeps the measured tables of `make demo` and
# `make demo-accurate`, and what limits the accuracy on these meshes.
