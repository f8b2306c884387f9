# %% [markdown]
# # A real prostate: from organ surface files to its stiffness
#
# This demo tells the story a user with segmentations lives, with the commands that user
# would type (each `command(...)` below is one `fenics-elasto ...` line, run in-process
# through `fenics_elasto.app.cli.main`). From three organ surfaces in millimetres it
# builds a pelvis, deforms it the way a filling bladder and a moving rectum do, makes
# targets that look like what imaging gives (noisy points, a voxel staircase), and
# recovers the prostate's Young's modulus $E$ relative to the tissue around it.
#
# Run it with `python demos/real_prostate.py` (`make demo-prostate`; the results land in
# `out/prostate/`, with `index.md` holding the table and pictures). Options:
#
# - `--quick` (`make demo-prostate-quick`, ~4 min): coarser meshes, one true $E$, two
#   targets;
# - `--ci`: the whole chain on coarse meshes with one target, for the tests (~2 min);
# - `--out DIR`: the folder for the results;
# - `--docs DIR`: also copy `index.md` and small pictures there (how
#   [the measured run](../real_prostate_index.md) got into the docs).
#
# ## The problem
#
# Linear elasticity with Lagrange elements of degree 2 on the body $\Omega$. The walls of
# bladder and rectum are loaded by unknown forces, so only ratios of Young's moduli are
# identifiable: the tissue's $E$ = 10 is the reference, and the prostate's is the
# unknown. The walls move by $d = W q$ in a basis $W$ of wall motions learnt from
# synthetic examples (`train --synthetic`), and the estimate minimises the surfaces'
# closest-point misfit
#
# $$
# \Phi^*(E) = \min_q \frac{1}{2} \sum_l \left| x_l + u_l(q, E) - \mathrm{cp}_{\Gamma}(x_l + u_l) \right|^2
#             + \frac{\alpha}{2} \left| q - q_0 \right|^2
# $$
#
# over $\log E$ (see [the method](../method.md)). Its interval comes from the residual,
# with the parts of the model's own error beside the noise (see
# [uncertainty](../uncertainty.md)).
#
# ## Set-up
#
# The options are read straight from the command line (anything else there is ignored
# when the script runs as a notebook). `SETTINGS` says what each variant meshes, which
# targets it makes per true $E$ ratio ("clean", "noise S mm": Gaussian noise of std S
# per coordinate, "voxels H mm": re-extracted from an H mm voxel image) and the bases it
# trains. The 24 affine wall motions come first in the bases, so the rank must exceed
# them well: the rectum's ripple needs rank ~80 (rank 50 of 80 examples put $E$ 22 % off,
# rank 80 of 120 0.7 %).

# %%
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import pyvista as pv

import fenics_elasto  # noqa: F401  (first: it sets up the DOLFINx wheel's MPI and PETSc)
from fenics_elasto.app.cli import main as cli
from fenics_elasto.app.render import offscreen_plotter
from fenics_elasto.mesh.builtin import PROSTATE_STL

argv = sys.argv[1:]
KNOWN = ("--quick", "--ci", "--out", "--docs")
unknown = [a for a in argv if a.startswith("--") and a not in KNOWN]
if unknown and "ipykernel" not in sys.modules:  # run as a script: a mistyped option is an error, not ignored
    sys.exit(f"real_prostate.py: unknown option {unknown[0]} (known: --quick, --ci, --out DIR, --docs DIR)")
variant = "ci" if "--ci" in argv else "quick" if "--quick" in argv else "full"
out = Path(argv[argv.index("--out") + 1]) if "--out" in argv else Path("out/prostate")
docs = Path(argv[argv.index("--docs") + 1]) if "--docs" in argv else None

TISSUE_E = 10.0  # the reference material written by `scene` (kPa, say)
ORGANS = ("bladder", "rectum", "prostate_surface")
GAP = 5.0  # mm between the prostate and the bladder / rectum
BLADDER_PRESSURE = 2.0  # in E's unit: about 8 mm of bladder filling
RECTUM = {"scale": 0.1, "shift": [0.0, 1.0, 0.0], "ripple": 1.0, "length": 30.0}  # widened, moved back, rippled
SCAN = 3  # start scan of the estimate: Phi*(E) is single-welled here (5 points gave the same E)
SETTINGS = {  # element sizes in mm; None: scene's default, size = diameter / 15
    "full": {"source": {"margin": 15.0}, "truth": {"margin": 18.0, "size": 12.0, "organ_size": 2.5},
             "cases": {3.0: ("clean", "noise 0.5 mm", "noise 1 mm", "voxels 1 mm"),
                       5.0: ("clean", "noise 0.5 mm", "voxels 1 mm")},
             "synthetic": 120, "rank": 80},
    "quick": {"source": {"margin": 15.0, "size": 16.0}, "truth": {"margin": 18.0, "size": 14.0, "organ_size": 3.5},
              "cases": {3.0: ("noise 0.5 mm", "voxels 1 mm")}, "synthetic": 120, "rank": 80},
    "ci": {"source": {"margin": 15.0, "size": 18.0, "organ_size": 7.0},
           "truth": {"margin": 18.0, "size": 16.0, "organ_size": 5.0},
           "cases": {3.0: ("voxels 1 mm",)}, "synthetic": 60, "rank": 40},
}
settings = SETTINGS[variant]
start = time.perf_counter(), time.process_time()


def command(*args) -> dict:
    """One command line; its wall and CPU seconds (the CPU time of this process: the
    machine may be shared)."""
    wall, cpu = time.perf_counter(), time.process_time()
    status = cli([str(a) for a in args])
    if status != 0:
        raise SystemExit(f"fenics-elasto {' '.join(map(str, args))}: exit status {status}")
    return {"wall_s": time.perf_counter() - wall, "cpu_s": time.process_time() - cpu}


# %% [markdown]
# ## 1. Organ surfaces
#
# The prostate is a real segmentation that ships with the package (MIT licence; +z
# points to the head and +y to the back, read from its shape: the base is wide and on
# top, the flat side faces the rectum). A bladder (an ellipsoid) sits 5 mm above it and
# a rectum (a capsule, tilted back along the sacral curve) 5 mm behind it; all three are
# written as STL files, as a segmentation tool would export them. The bones are the
# patch of the body's surface below and behind a plane at 45 degrees.


# %%
def ellipsoid(center, axes) -> pv.PolyData:
    sphere = pv.Icosphere(radius=1.0, nsub=4)
    sphere.points = np.asarray(center) + np.asarray(sphere.points) * np.asarray(axes)
    return sphere


def capsule(center, direction, radius: float, length: float) -> pv.PolyData:
    return pv.Capsule(center=center, direction=direction, radius=radius, cylinder_length=length,
                      resolution=40).triangulate().clean()


def pelvis_files(folder: Path) -> dict:
    """The prostate (copied), a bladder above it and a rectum behind it, as STL files;
    returns what the spec needs (bones plane included)."""
    folder.mkdir(parents=True, exist_ok=True)
    shutil.copy(PROSTATE_STL, folder / "prostate.stl")
    organ = pv.read(PROSTATE_STL).connectivity("largest")  # the file has four stray specks besides
    low, high = np.array(organ.bounds).reshape(3, 2).T
    middle = (low + high) / 2
    bladder_axes = np.array([26.0, 22.0, 16.0])
    ellipsoid([middle[0], middle[1] - 4.0, high[2] + GAP + bladder_axes[2]], bladder_axes).save(folder / "bladder.stl")
    radius, tilt = 12.0, np.array([0.0, 0.25, 1.0])  # the rectum leans back as it rises
    rectum_centre = [middle[0], high[1] + GAP + radius, middle[2] - 3.0]
    capsule(rectum_centre, tilt / np.linalg.norm(tilt), radius, 50.0).save(folder / "rectum.stl")
    bones = {"point": [float(middle[0]), float(rectum_centre[1]), float(low[2] - 15.0)],
             "normal": [0.0, 0.7071, -0.7071]}
    return {"rectum_centre": rectum_centre, "bones": bones}


print("1. organ surfaces: the real prostate, a bladder and a rectum (STL, mm)", flush=True)
anatomy = pelvis_files(out / "surfaces")

# %% [markdown]
# ## 2. Two scenes: the source and an independent truth
#
# A scene file names the organ surfaces and what each is: the prostate a region (its
# own material), bladder and rectum cavities (holes whose walls are loaded), the bones a
# fixed patch. `scene` meshes it with gmsh. The truth is meshed independently, with
# another body margin and finer organ elements, so that the targets do not come from the
# mesh the estimate runs on.


# %%
def write_spec(folder: Path, name: str, bones: dict, margin: float, size=None, organ_size=None) -> Path:
    lines = ['units = "mm"']
    lines += [f"size = {size}"] if size else []
    lines += [f"organ_size = {organ_size}"] if organ_size else []
    lines += ["[body]", f"box = {{ margin = {margin} }}",
              "[regions.prostate]", 'surface = "prostate.stl"',
              "[cavities.bladder]", 'surface = "bladder.stl"',
              "[cavities.rectum]", 'surface = "rectum.stl"',
              "[patches.bones]", f"side = {{ point = {bones['point']}, normal = {bones['normal']} }}"]
    spec = folder / f"{name}.toml"
    spec.write_text("\n".join(lines) + "\n")
    return spec


def scene(name: str, sizes: dict) -> Path:
    spec = write_spec(out / "surfaces", name, anatomy["bones"], **sizes)
    command("scene", spec, "--out", out / name)
    return out / name / "problem.toml"


def describe(sizes: dict) -> str:
    return ", ".join(f"{key.replace('_', ' ')} {value:g} mm" for key, value in sizes.items())


print("2. scenes: the source and an independent, finer truth", flush=True)
source = scene("source", settings["source"])
truth = scene("truth", settings["truth"])

# %% [markdown]
# ## 3. Bases from synthetic examples
#
# `train --synthetic N` deforms the source N times with random smooth wall motions
# (fillings, shifts, ripples, each with random stiffness ratios), matches its surfaces
# to each, and keeps the leading `rank` principal wall motions with their explained
# variance (`bases.png`).

# %%
print("3. bases: train --synthetic", flush=True)
bases = out / "bases.npz"
train = command("train", source, "--synthetic", settings["synthetic"], "--rank", settings["rank"], "--out", bases)

# %% [markdown]
# ## 4. The truth's motion and image-like targets
#
# The truth moves in a way no affine map makes: the bladder fills under pressure (a
# bulge), the rectum is widened about its centre, moved back and carries a smooth random
# ripple; the prostate is 3x (and, in the full run, 5x) as stiff as the tissue.
# `simulate` writes the moved organ surfaces, `surface_<organ>.vtp`. From them the
# targets are made as images give them: the clean surfaces; Gaussian noise on their
# points; or each organ's partial volume on a grid of 1 mm voxels at a random offset,
# re-extracted by marching cubes (VTK's flying edges), so that no vertex corresponds to
# the source.


# %%
def truth_motion(rectum_centre, seed: int = 3) -> list[str]:
    """--set overrides: the bladder fills under pressure, the rectum is widened about its
    centre, moved back and rippled (a smooth random field)."""
    r = RECTUM
    rectum = (f"rectum={{scale={r['scale']}, center={list(map(float, rectum_centre))}, value={r['shift']}, "
              f"ripple={{amplitude={r['ripple']}, length={r['length']}, seed={seed}}}}}")
    return ["--set", f"boundary.displacement={{{rectum}}}", "--set", f"boundary.pressure={{bladder={BLADDER_PRESSURE}}}"]


def organ_surface(path: Path) -> pv.PolyData:
    """A surface simulate wrote, as one closed, consistently oriented triangulation: the
    seams between its flat pieces merged, every triangle turned outward (simulate
    writes them in any orientation; inside tests need them consistent)."""
    mesh = pv.read(path).triangulate()
    mesh = mesh.clean(tolerance=1e-9, absolute=False)
    mesh = mesh.compute_normals(consistent_normals=True, auto_orient_normals=True, split_vertices=False,
                                cell_normals=False)
    return pv.PolyData(mesh.points, faces=mesh.faces)


def noisy_copy(clean: Path, folder: Path, sigma: float, seed: int) -> Path:
    """The organ surfaces with Gaussian noise of std ``sigma`` on every coordinate of
    every point (the seams merged first, so the noise opens no cracks)."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    for g in ORGANS:
        mesh = organ_surface(clean / f"surface_{g}.vtp")
        mesh.points = mesh.points + rng.normal(0.0, sigma, mesh.points.shape)
        mesh.save(folder / f"surface_{g}.vtp")
    return folder


def voxelised_copy(clean: Path, folder: Path, voxel: float, seed: int) -> Path:
    """Each organ surface as a CT would see it: the share of every voxel inside the
    organ, on a grid at a random offset, then the 0.5 iso-surface by marching cubes."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    for g in ORGANS:
        image = partial_volume(organ_surface(clean / f"surface_{g}.vtp"), voxel, rng.uniform(0.0, voxel, 3))
        surface = image.contour([0.5], scalars="fraction", method="flying_edges")
        pv.PolyData(surface.points, faces=surface.faces).save(folder / f"surface_{g}.vtp")
    return folder


def partial_volume(mesh: pv.PolyData, voxel: float, offset: np.ndarray, samples: int = 3) -> pv.ImageData:
    """ImageData with point data "fraction": the share of each voxel inside the closed
    surface (by winding number). A voxel whose centre is on the same side as all its
    neighbours' is wholly in or out; the others, along the surface, average samples^3
    points."""
    import igl
    from scipy.ndimage import binary_dilation, binary_erosion

    points, faces = np.asarray(mesh.points, float), mesh.faces.reshape(-1, 4)[:, 1:].astype(np.int64)
    low = np.floor((np.array(mesh.bounds[::2]) - offset) / voxel - 2) * voxel + offset
    shape = tuple(np.ceil((np.array(mesh.bounds[1::2]) - low) / voxel + 2).astype(int) + 1)
    axes = [low[i] + voxel * np.arange(shape[i]) for i in range(3)]
    centres = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    inside = (igl.fast_winding_number(points, faces, centres) > 0.5).reshape(shape)
    cube = np.ones((3, 3, 3), bool)
    near = np.flatnonzero(binary_dilation(inside, cube) & ~binary_erosion(inside, cube, border_value=0))
    sub = (np.arange(samples) + 0.5) / samples - 0.5
    shifts = voxel * np.stack(np.meshgrid(sub, sub, sub, indexing="ij"), axis=-1).reshape(-1, 3)
    probes = (centres[near, None, :] + shifts[None]).reshape(-1, 3)
    fraction = inside.ravel().astype(float)
    fraction[near] = (igl.fast_winding_number(points, faces, probes) > 0.5).reshape(len(near), -1).mean(axis=1)
    image = pv.ImageData(dimensions=shape, spacing=(voxel,) * 3, origin=low)
    image.point_data["fraction"] = fraction.reshape(shape).ravel(order="F")
    return image


def make_targets(folder: Path, truth_out: Path, kinds) -> dict:
    """kind -> folder of surface_<organ>.vtp, for kinds named "clean", "noise S mm",
    "voxels H mm" (each with its own seed)."""
    made = {}
    for seed, kind in enumerate(kinds):
        word, *size = kind.split()
        if word == "clean":
            made[kind] = truth_out
        elif word == "noise":
            made[kind] = noisy_copy(truth_out, folder / kind.replace(" ", "_"), float(size[0]), seed=10 + seed)
        else:
            made[kind] = voxelised_copy(truth_out, folder / kind.replace(" ", "_"), float(size[0]), seed=20 + seed)
    return made


def targets_picture(kinds: dict, path: Path) -> Path:
    """The prostate as each kind of target gives it, side by side."""
    plotter = offscreen_plotter(shape=(1, len(kinds)), window_size=(500 * len(kinds), 520))
    for k, (kind, folder) in enumerate(kinds.items()):
        plotter.subplot(0, k)
        mesh = pv.read(folder / "surface_prostate_surface.vtp")
        plotter.add_mesh(mesh, color="#e6a27a", show_edges=True, edge_color="#7a4a2a", line_width=0.3,
                         smooth_shading=False)
        plotter.add_text(f"{kind}\n{mesh.n_points} points", font_size=12)
        plotter.view_vector((1.0, -0.75, 0.45), viewup=(0.0, 0.0, 1.0))
        plotter.camera.zoom(1.2)
    plotter.link_views()
    plotter.screenshot(str(path))
    plotter.close()
    return path


# %% [markdown]
# ## 5. One estimate per target
#
# `estimate` takes the source scene, the target surfaces (`--set target=...`) and the
# bases (`--set reduction=...`), and writes `result.json`: the prostate's $E$ with its
# interval and the parts of $\sigma$, the surfaces' distance after the fit, how much of
# the wall motion the bases explain, and any warnings.


# %%
def target_setting(folder: Path) -> str:
    files = ", ".join(f"{g}='{(folder / f'surface_{g}.vtp').resolve()}'" for g in ORGANS)
    return f"target={{surfaces={{{files}}}}}"


def estimate_case(result_out: Path, target: Path) -> dict:
    """One estimate through the command line; result.json plus the times."""
    times = command("estimate", source, "--out", result_out, "--set", target_setting(target),
                    "--set", f"reduction={{bases='{bases.resolve()}'}}", "--set", f"optimizer.scan={SCAN}")
    return {**json.loads((result_out / "result.json").read_text()), **times}


def row(ratio: float, kind: str, r: dict) -> dict:
    E = r["materials"]["prostate"]["E"]
    sigma = ((r.get("uncertainty") or {}).get("prostate.E") or {}).get("std")
    return {"true_ratio": ratio, "target": kind, "E": E, "ratio": E / TISSUE_E,
            "error_percent": 100 * (E / TISSUE_E - ratio) / ratio, "sigma": sigma,
            "rms_mm": r["surface_distance"]["rms"], "max_mm": r["surface_distance"]["max"],
            "bases_fit": (r.get("bases_fit") or {}).get("wall_motion_explained"),
            "wall_s": r["wall_s"], "cpu_s": r["cpu_s"], "factorizations": r["factorizations"],
            "warnings": r["warnings"]}


rows, pictures, facts = [], {}, {}
first = next(iter(settings["cases"]))
for ratio, wanted in settings["cases"].items():
    case = f"E{ratio:g}x"
    print(f"4. truth: prostate E = {ratio:g} x tissue", flush=True)
    truth_out = out / f"truth_{case}"
    command("simulate", truth, "--out", truth_out, f"--set=materials.prostate.E={ratio * TISSUE_E:g}",
            *truth_motion(anatomy["rectum_centre"]))
    simulated = json.loads((truth_out / "result.json").read_text())
    facts.setdefault("max_displacement", simulated["max_displacement"])
    facts.setdefault("truth_dofs", simulated["dofs"])
    pictures.setdefault(f"truth ({case}): the moved organs", shutil.copy(truth_out / "screenshot.png", out / "truth.png"))
    kinds = make_targets(out / f"targets_{case}", truth_out, wanted)
    if ratio == first:
        pictures["the prostate as each target gives it"] = targets_picture(kinds, out / "targets.png")
    for kind, folder in kinds.items():
        result_out = out / f"estimate_{case}_{kind.replace(' ', '_')}"
        rows.append(row(ratio, kind, estimate_case(result_out, folder)))
        facts.setdefault("source_dofs", json.loads((result_out / "result.json").read_text())["dofs"])
        print(f"   {kind}: E ratio {rows[-1]['ratio']:.3f} ({rows[-1]['error_percent']:+.1f} %), rms misfit "
              f"{rows[-1]['rms_mm']:.3f} mm, {rows[-1]['wall_s']:.0f} s", flush=True)
        if ratio == first:
            pictures[f"estimate, {kind} target (truth {case})"] = shutil.copy(
                result_out / "screenshot.png", out / f"estimate_{kind.replace(' ', '_')}.png")
pictures["bases: explained variance"] = out / "bases.png"

# %% [markdown]
# ## 6. The table and the pictures
#
# `index.md` in the output folder gathers the table (the $E$ ratio found against the
# truth, its $\sigma$, the misfit left, how much of the wall motion the bases explain,
# time, warnings) and the pictures; `table.json` has the rows for the tests.


# %%
def table(rows: list[dict]) -> list[str]:
    lines = ["| true E ratio | target | E ratio found | error % | ± sigma | rms misfit mm | max misfit mm "
             "| bases fit % | wall s | CPU s | warnings |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        sigma = f"{r['sigma'] / TISSUE_E:.3f}" if r["sigma"] is not None else "-"
        fit = f"{100 * r['bases_fit']:.1f}" if r["bases_fit"] is not None else "-"
        lines.append(f"| {r['true_ratio']:g} | {r['target']} | {r['ratio']:.3f} | {r['error_percent']:+.1f} | {sigma} | "
                     f"{r['rms_mm']:.3f} | {r['max_mm']:.2f} | {fit} | {r['wall_s']:.0f} | {r['cpu_s']:.0f} | "
                     f"{'; '.join(r['warnings']) or '-'} |")
    return lines


def index_page(rows: list[dict], facts: dict, pictures: dict) -> str:
    """index.md: what was done, the table, the pictures (``pictures``: caption -> file)."""
    lines = ["# A real prostate: E from organ surfaces", "",
             f"Source mesh {facts['source_dofs']} DOFs (`scene` defaults{facts['source_note']}); truth mesh "
             f"{facts['truth_dofs']} DOFs, meshed independently ({facts['truth_note']}). Truth motion: the bladder "
             f"fills under pressure {BLADDER_PRESSURE:g} (tissue E = {TISSUE_E:g}), the rectum widens by "
             f"{100 * RECTUM['scale']:.0f} %, moves {RECTUM['shift'][1]:g} mm back and carries a smooth random ripple "
             f"({RECTUM['ripple']:g} mm, length {RECTUM['length']:g} mm); largest displacement "
             f"{facts['max_displacement']:.1f} mm. Bases: `train --synthetic {facts['synthetic']} --rank "
             f"{facts['rank']}` ({facts['train_wall_s']:.0f} s wall, {facts['train_cpu_s']:.0f} s CPU).",
             "", f"Reproduce: `{facts['command']}` (whole run {facts['total_wall_s'] / 60:.1f} min wall, "
             f"{facts['total_cpu_s'] / 60:.1f} min CPU).", "",
             "Targets: *clean* = the truth's organ surfaces; *noise s* = Gaussian noise of std s on every coordinate "
             "of every point; *voxels h* = each organ's partial volume on a grid of h mm voxels (random offset), "
             "marching cubes at 0.5, so no point corresponds to the source. The error is the E ratio found against "
             "the true one; sigma is its standard deviation with every part the estimate reports (noise, mesh, "
             "bases).", ""]
    lines += table(rows) + [""]
    for caption, name in pictures.items():
        lines += [f"**{caption}**", "", f"![{caption}]({name})", ""]
    text = "\n".join(lines)
    (out / "index.md").write_text(text)
    return text


facts.update(synthetic=settings["synthetic"], rank=settings["rank"], train_wall_s=train["wall_s"],
             train_cpu_s=train["cpu_s"], command={"full": "make demo-prostate", "quick": "make demo-prostate-quick",
                                                  "ci": "python demos/real_prostate.py --ci"}[variant],
             source_note=", " + describe(settings["source"]), truth_note=describe(settings["truth"]),
             total_wall_s=time.perf_counter() - start[0], total_cpu_s=time.process_time() - start[1])
names = {caption: Path(p).name for caption, p in pictures.items()}
text = index_page(rows, facts, names)
(out / "table.json").write_text(json.dumps(rows, indent=2))
print("\n".join(table(rows)), flush=True)

# %% [markdown]
# With `--docs DIR` the page and smaller copies of its pictures go to the docs, as
# `real_prostate_index.md` and `real_prostate_*.png`.


# %%
def small_copy(picture: Path, path: Path, width: int = 1000) -> Path:
    """A smaller PNG for the docs."""
    from PIL import Image

    image = Image.open(picture)
    if image.width > width:
        image = image.resize((width, round(image.height * width / image.width)), Image.LANCZOS)
    image.save(path, optimize=True)
    return path


if docs:
    docs.mkdir(parents=True, exist_ok=True)
    for name in set(names.values()):
        small_copy(out / name, docs / f"real_prostate_{name}")
        text = text.replace(f"]({name})", f"](real_prostate_{name})")
    (docs / "real_prostate_index.md").write_text(text)
