"""What each command does -- check the output, load, compute, write -- as functions the
command line and Python scripts call alike (cli.py only parses and prints).

Every command checks its output place first (outputs.py): a bad ``--out`` costs a
second, not an estimate. Result folders are written atomically, ``result.json`` last.
"""

from __future__ import annotations

from pathlib import Path

from fenics_elasto.util.errors import UserError, require
from fenics_elasto.util.logs import log
from fenics_elasto.files.outputs import prepare_file, prepare_folder
from fenics_elasto.app import api
from fenics_elasto.config.problem import map_files


def run_mesh(name: str, out: Path, size=None, seed=None, atlas_mesh: Path | None = None, **detail) -> Path:
    """The ``mesh`` command: a built-in scene (.msh + problem.toml) into ``out``, checked
    and locked first; gmsh on rank 0. Returns the problem.toml path."""
    return api.build_scene(name, out, size, seed, atlas_mesh, **detail)


def run_scene(spec: Path, out: Path, size=None) -> Path:
    """The ``scene`` command: a scene from organ surface files (anatomy.py) into ``out``."""
    return api.scene_from_spec(spec, out, size)


def run_simulate(problem_path: Path, out: Path, overrides=()) -> dict:
    """The ``simulate`` command: result.json, the displacement, surfaces, the picture."""
    from fenics_elasto.app.results import write_solution
    from fenics_elasto.app.render import caption
    from fenics_elasto.model.scene import load_scene

    with prepare_folder(out) as folder:
        scene = load_scene(problem_path, overrides, command="simulate")
        sim = api.simulate(scene)
        with folder.writing(sim.record):
            write_solution(folder, scene, sim.u, title=caption(sim.record, Path(out).name, units(scene)))
    log.info(f"dofs {sim.record['dofs']}, max |u| {sim.record['max_displacement']:.4g}, "
             f"{sim.record['wall_time_s']:.2f} s -> {out}")
    return sim.record


def run_estimate(problem_path: Path, out: Path, overrides=(), check_mesh: bool = False):
    """The ``estimate`` command: result.json, fields, surfaces, forces.csv, pictures;
    ``check_mesh``: also on the source refined once, and how far the answer moved."""
    from fenics_elasto.model.scene import load_scene

    with prepare_folder(out) as folder:
        scene = load_scene(problem_path, overrides, command="estimate")
        answer = api.estimate(scene)
        result = answer.outcome
        if check_mesh and not result["interrupted"]:
            result.record["mesh_check"] = mesh_check_or_why(problem_path, folder.path, overrides, result, answer.basis)
        with folder.writing(result.record):
            write_estimate(folder, answer.problem, result)
    distance = result["surface_distance"]
    log.info(f"{title(result)}; rms distance {distance['rms']:.3g}, "
             f"{result['factorizations']} factorizations, {result['wall_time_s']:.1f} s -> {out}")
    return result


def mesh_check_or_why(problem_path: Path, out: Path, overrides, result, basis) -> dict:
    """``mesh_check``, or why it did not finish -- a check refused or stopped by Ctrl-C --
    as a warning beside the estimate, which is written all the same."""
    try:
        return mesh_check(problem_path, out, overrides, result, basis)
    except (UserError, KeyboardInterrupt) as stopped:
        why = str(stopped) or type(stopped).__name__
        result.record["warnings"].append(f"the mesh check did not finish ({why}); the estimate stands as written")
        log.warning(result.record["warnings"][-1])
        return {"finished": False, "why": why}


def mesh_check(problem_path: Path, out: Path, overrides, result, basis) -> dict:
    """The estimate again on the source split once on its geometry (refine.py), started
    at the answer: how far it moves is what the source mesh still costs. Bases move to
    the refined loaded nodes exactly (nested meshes)."""
    import time

    from fenics_elasto.inverse.options import Options
    from fenics_elasto.inverse.estimator import estimate
    from fenics_elasto.inverse.objective import InverseProblem
    from fenics_elasto.model.refine import refine_scene, transfer_bases
    from fenics_elasto.model.scene import load_scene

    start = time.perf_counter()
    coarse = InverseProblem(load_scene(problem_path, overrides), target=False)
    fine_path = refine_scene(problem_path, out / ".refined")
    settings = list(overrides) + [("target", absolute_paths(coarse.scene, "target"))]
    settings += [(f"materials.{m}.{k}.initial", float(v)) for (m, k), v in zip(coarse.params.names, result.theta)]
    fine = InverseProblem(load_scene(fine_path, settings))
    W = None if basis is None else transfer_bases(basis, coarse.scene, fine.scene)
    options = Options.from_scene(fine.scene)
    options.scan = 1  # started at the coarse answer: no scan of the bounds
    log.info(f"mesh check: the estimate again on the source refined once ({fine.model.dofs.num_dofs} dofs)")
    refined = estimate(fine, options, W)
    change = {label: 100 * (refined.estimated[label] - value) / value for label, value in result.estimated.items()}
    for label, moved in change.items():
        if abs(moved) > 1.0:
            result.record["warnings"].append(f"{label} moved {moved:+.1f} % on the source refined once: the source "
                                             "mesh limits the accuracy; refine it (finer organ walls first)")
            log.warning(result.record["warnings"][-1])
    return {"finished": True, "refined_dofs": fine.model.dofs.num_dofs, "estimated": refined.estimated,
            "change_percent": change,
            "seconds": round(time.perf_counter() - start, 1)}


def absolute_paths(scene, table: str) -> dict:
    """A table of the scene's config with its file names absolute (they are relative to
    the problem file, which a derived scene elsewhere does not share)."""
    base = scene.path.parent.resolve()
    return {k: map_files((table, k), v, lambda name: str(base / name))
            for k, v in (scene.config[table] or {}).items() if v is not None}


def write_estimate(folder, problem, result) -> None:
    """An estimate's files into an OutputFolder (inside its ``writing()``)."""
    from fenics_elasto.app.results import write_solution
    from fenics_elasto.files.writers import point_csv
    from fenics_elasto.app.render import caption, plot_convergence, target_polydata

    scene = problem.scene
    target = target_polydata(problem) if scene.comm.rank == 0 else None
    write_solution(folder, scene, result.u, target=target, title=caption(result.record, folder.path.name, units(scene)))
    points = problem.loaded.gather(problem.loaded.coords)
    if scene.comm.rank == 0:
        assert target is not None
        target.save(folder.path_for("target.vtp"))
        plot_convergence(result.record, folder.path_for("convergence.png"))
        folder.write_text("forces.csv", point_csv(points, result.forces.reshape(len(points), -1), "f"))
        for name, forces in result.state_forces.items():
            folder.write_text(f"forces_{name}.csv", point_csv(points, forces.reshape(len(points), -1), "f"))


def units(scene) -> str:
    return scene.config.get("units") or ""


def title(result) -> str:
    return "estimate: " + ", ".join(f"{label} = {value:.4g}" for label, value in result.estimated.items())


def run_train(patients: list, out: Path, rank: int, atlas_mesh: Path | None = None, overrides=(), generator=None):
    """Bases from example targets: ``patients`` = [(problem.toml, [example, ...]), ...]
    (several only around an atlas), and/or from synthetic examples of the scene
    (``generator``: synthetic.Generator). Writes BASES.npz and its variance plot (.png)."""
    from fenics_elasto.model.scene import load_scene

    require(len(patients) == 1 or atlas_mesh, "train: several training scenes need --atlas (their shared mesh)")
    for problem, examples in patients:
        require(examples or generator is not None, f"train: no examples given for {problem}")
    bases_file = prepare_file(out, ".npz")
    picture = prepare_file(bases_file.path.with_suffix(".png"), ".png")
    scenes = [(load_scene(p, overrides, command="train"), e) for p, e in patients]
    if atlas_mesh:
        bases = train_on_atlas(scenes, atlas_mesh, rank)
    else:
        scene, examples = scenes[0]
        settings = {} if generator is None else {"synthetic": generator.count, "seed": generator.seed,
                                                 "length": generator.length, "amplitude": generator.amplitude}
        bases = api.train(scene, rank=rank, examples=examples, **settings)
    return save_bases(bases, bases_file, picture)


def train_on_atlas(scenes: list, atlas_mesh: Path, rank: int):
    """Bases in the numbering of the atlas every training scene was built around."""
    from fenics_elasto.mesh.atlas import atlas_surfaces
    from fenics_elasto.inverse.objective import InverseProblem
    from fenics_elasto.inverse.reduction.bases import train_atlas_bases

    problems = [(InverseProblem(scene, target=False), e) for scene, e in scenes]
    count = sum(len(e) for _, e in problems)
    log.info(f"train: {len(problems)} scene(s), {count} examples, {problems[0][0].force_dofs} force dofs, rank {rank}")
    atlas = atlas_surfaces(atlas_mesh, problems[0][0].scene.loaded)
    return train_atlas_bases(atlas, problems, rank)


def save_bases(bases, bases_file, picture):
    from fenics_elasto.app.render import plot_variance

    bases_file.write(bases.save)
    picture.write(lambda path: plot_variance(bases.variance, path))
    reach = "" if bases.held_out is None else f"; {100 * bases.held_out:.1f} % of examples left out of the training"
    log.info(f"wrote {bases_file.path} (rank {bases.W.shape[1]} of {bases.examples} examples: {100 * bases.variance.sum():.2f} "
             f"% of their energy{reach}) and {picture.path}")
    return bases


def run_render(folder: Path, out: Path | None = None) -> Path:
    """The ``render`` command: a result folder's picture again, from its saved surfaces."""
    plotter = api.render(folder)
    picture = prepare_file(out or Path(folder) / "screenshot.png", ".png")
    if plotter is not None:
        picture.write(lambda path: screenshot(plotter, path))
    log.info(f"wrote {picture.path}")
    return picture.path


def screenshot(plotter, path: Path) -> Path:
    """The plotter's picture into ``path``; the plotter closed."""
    plotter.screenshot(str(path))
    plotter.close()
    return path
