"""The Python API (``import fenics_elasto as fe``): build or load a scene, simulate,
estimate, train bases, draw. The command line is a thin layer over these calls.

Every call checks its arguments first and raises ``UserError`` with the one line the
command line prints for the same mistake.
"""

from __future__ import annotations

import os
from dataclasses import replace
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from fenics_elasto.app.outcomes import Estimate, Simulation
from fenics_elasto.app.target import Target
from fenics_elasto.config.problem import map_files
from fenics_elasto.inverse.reduction.bases import Bases
from fenics_elasto.model.scene import Scene, reconfigure
from fenics_elasto.util.errors import UserError, require
from fenics_elasto.util.interrupts import python_interrupts
from fenics_elasto.util.logs import log

if TYPE_CHECKING:
    import pyvista as pv

    from fenics_elasto.inverse.objective import InverseProblem

PathLike = str | os.PathLike[str]


def build_scene(name: str, out: PathLike, size: float | None = None, seed: int | None = None,
                atlas: PathLike | None = None, organ_size: float | None = None,
                prostate_size: float | None = None) -> Path:
    """Write a built-in scene ("letter-a", "cantilever", "inclusion", "prostate-phantom")
    -- its gmsh mesh and problem.toml -- into the folder ``out``; returns the
    problem.toml path. ``size``: element size (scene units); ``seed``: the phantom's
    patient variation (0 = nominal); ``atlas``: a phantom mesh whose bladder and rectum
    this one is built around; ``organ_size``, ``prostate_size``: the phantom's element
    sizes there, relative to ``size``. Collective (gmsh runs on rank 0)."""
    from mpi4py import MPI

    from fenics_elasto.files.outputs import prepare_folder
    from fenics_elasto.mesh.atlas import atlas_surfaces
    from fenics_elasto.mesh.builtin import build_scene as build
    from fenics_elasto.util.errors import on_root

    def work() -> Path:
        require(atlas is None or name == "prostate-phantom", "--atlas: only prostate-phantom takes an atlas")
        surfaces = atlas_surfaces(Path(atlas)) if atlas else None
        return build(name, Path(out), size, seed, surfaces, organ_size=organ_size, prostate_size=prostate_size)

    with prepare_folder(Path(out)):  # a bad out costs nothing; a second run into it waits its turn
        return on_root(MPI.COMM_WORLD, work)


def scene_from_spec(spec: PathLike, out: PathLike, size: float | None = None) -> Path:
    """A scene from organ surface files or a label map (the ``scene`` command: a spec
    TOML naming the body, its regions and cavities; docs/scenes.md), meshed into the
    folder ``out``; returns its problem.toml path. ``size``: the element size, instead
    of the spec's. Collective (gmsh runs on rank 0)."""
    from mpi4py import MPI

    from fenics_elasto.files.outputs import prepare_folder
    from fenics_elasto.mesh.anatomy import build_scene_from_spec
    from fenics_elasto.util.errors import on_root

    with prepare_folder(Path(out)):
        return on_root(MPI.COMM_WORLD, lambda: build_scene_from_spec(Path(spec), Path(out), size))


def _override_items(overrides: Mapping[str, Any] | None) -> list[tuple[str, Any]]:
    if overrides is None:
        return []
    require(isinstance(overrides, Mapping), "overrides: expected a mapping of dotted keys to values, like "
                                            f"{{'materials.letter.nu': 0.25}}, got {type(overrides).__name__}")
    items = []
    for key, value in overrides.items():
        require(isinstance(key, str) and all(key.split(".")), f"overrides: {key!r} is not a dotted key like 'optimizer.scan'")
        # file names in overrides are the caller's, relative to the working directory
        items.append((key, map_files(tuple(key.split(".")), value, lambda name: str(Path(name).resolve()))))
    return items


def load_scene(path: PathLike, overrides: Mapping[str, Any] | None = None) -> Scene:
    """A scene from its problem.toml and mesh, checked. ``overrides``: values that replace
    the file's, by dotted key (``{"materials.letter.nu": 0.25, "target.surface":
    "out/surface.vtp"}``); file names in them are relative to the working directory
    (those in the file, to the file's folder). Collective."""
    from fenics_elasto.model.scene import load_scene as load

    return load(Path(path), _override_items(overrides))


def for_command(scene: Scene, command: str, overrides: Iterable = ()) -> Scene:
    """The scene checked for ``command`` ("simulate", "estimate", "train") as the command
    line checks it, on the same mesh; ``overrides`` set first."""
    require(isinstance(scene, Scene), f"{command}: expected a Scene (from load_scene or Scene.from_mesh), "
                                      f"got {type(scene).__name__}")
    return reconfigure(scene, list(overrides), command=command)


def simulate(scene: Scene) -> Simulation:
    """The forward solve of the scene's [boundary] loads and displacements with its
    materials' values: a Simulation (``.u``, ``.surface(group)``, ``.record``). Collective."""
    from fenics_elasto.model.simulate import simulate as solve

    scene = for_command(scene, "simulate")
    solved = solve(scene)
    return Simulation(scene, solved.u, solved.result)


def _bases_of(problem: InverseProblem, bases: Bases | PathLike | None) -> tuple[np.ndarray | None, float | None]:
    """(W on the problem's loaded nodes, the share of held-out examples' energy the bases
    kept): from ``bases`` (a Bases or a file), else from the scene's [reduction] (file
    and rank), else (None, None)."""
    from fenics_elasto.inverse.reduction.bases import load_bases

    if isinstance(bases, Bases):
        return bases.on(problem), bases.held_out
    if bases is not None:
        require(isinstance(bases, (str, os.PathLike)), f"bases: expected a Bases or a bases file, got {type(bases).__name__}")
        return load_bases(Path(bases).resolve(), problem, None)
    table = problem.scene.config["reduction"]
    return (None, None) if table is None else load_bases(problem.scene.path.parent / table["bases"], problem, table["rank"])


def inverse_problem(scene: Scene, target: Target | Mapping[str, Target] | None = None,
                    bases: Bases | PathLike | None = None) -> tuple[InverseProblem, np.ndarray | None, float | None]:
    """The estimate's set-up, checked: (the inverse problem, W or None, the bases' held-out
    energy). ``target`` None: the scene's [target] files; a mapping: several states."""
    from fenics_elasto.inverse.measured_force import with_force_reference
    from fenics_elasto.inverse.misfit import FieldTerm
    from fenics_elasto.inverse.objective import InverseProblem

    if isinstance(target, Mapping):  # several states of one body
        require(len(target) > 0, "estimate: an empty mapping of states; give {name: Target, ...}")
        wrong = [str(name) for name, t in target.items() if not isinstance(t, Target)]
        require(not wrong, f"estimate: several states are a mapping {{name: Target, ...}}; state {wrong[:1]} is not a Target")
        states = [{"name": str(name), "target": t.spec(), **({"measured_force": t.measured_force} if t.measured_force else {})}
                  for name, t in target.items()]
        scene = with_force_reference(for_command(scene, "estimate", [("states", states)]))
        # each state's data with its own checked [target] numbers (noises, weights), as a file's
        problem = InverseProblem(scene, target=[(str(name), replace(t.data(scene.gdim, scene), spec=state["target"],
                                                                    source=f"state {str(name)!r}: Target"))
                                                for (name, t), state in zip(target.items(), scene.config["states"])])
    else:
        require(target is None or isinstance(target, Target), f"estimate: expected a Target, got {type(target).__name__}")
        items = [] if target is None else [("target", target.spec())]
        if target is not None and target.measured_force:
            items.append(("boundary.measured_force", target.measured_force))
        scene = with_force_reference(for_command(scene, "estimate", items))
        problem = InverseProblem(scene, target=None if target is None else target.data(scene.gdim, scene))
    basis, held_out = _bases_of(problem, bases)
    field = len(problem.misfit.rows_of(FieldTerm))
    landmarks = len(problem.misfit.landmark_rows()) - field
    log.info(f"estimate {', '.join(problem.params.labels)}: {problem.model.dofs.num_dofs} dofs, {problem.force_dofs} "
             "force dofs" + (f" reduced to rank {basis.shape[1]}" if basis is not None else "")
             + f", {problem.observation.node_count} matched nodes" + (f", {landmarks} landmarks" if landmarks else "")
             + (f", {field} displacement-field cells" if field else ""))
    return problem, basis, held_out


def estimate(scene: Scene, target: Target | Mapping[str, Target] | None = None,
             bases: Bases | PathLike | None = None) -> Estimate:
    """Estimate the scene's estimated constants (``estimate = true`` in [materials]) and
    the unknown forces on its loaded groups from ``target`` (None: the scene's [target]
    or [[states]]; ``{name: Target, ...}``: several states of the body, each with its own
    forces, the materials shared).
    ``bases``: reduced force bases (a Bases or a file from ``train``); None uses the
    scene's [reduction] if it has one, else the full force space. On Ctrl-C it returns
    the best answer so far (``interrupted``). Collective."""
    from fenics_elasto.inverse.estimator import estimate as run

    problem, basis, held_out = inverse_problem(scene, target, bases)
    with python_interrupts(problem.scene.comm):  # gmsh, used to mesh before, leaves Ctrl-C killing the process
        result = run(problem, basis=basis, held_out=held_out)
    return Estimate(problem.scene, result, problem, basis)


def train(scene: Scene, synthetic: int | None = None, rank: int = 80, seed: int = 0, examples: Iterable[PathLike] = (),
          length: float | None = None, amplitude: float | None = None) -> Bases:
    """Reduced force bases for the scene's loaded groups: the principal directions of
    ``synthetic`` example deformations of the scene itself (smooth random pressures and
    tractions, affine and displacement-mode wall motions; ``seed``, ``length`` and
    ``amplitude`` shape them) and/or of ``examples`` (target surface files, or folders
    of surface_<group>.vtp as simulate writes), at most ``rank`` of them. Collective."""
    from fenics_elasto.inverse.objective import InverseProblem
    from fenics_elasto.inverse.reduction.bases import train_bases
    from fenics_elasto.inverse.reduction.synthetic import Generator

    examples = [Path(p).resolve() for p in examples]
    require(examples or synthetic is not None, "train: give examples or synthetic=N")
    require(synthetic is None or (isinstance(synthetic, int) and synthetic >= 1),
            f"train: synthetic must be an integer >= 1, got {synthetic!r}")
    require(isinstance(rank, int) and rank >= 1, f"train: rank must be an integer >= 1, got {rank!r}")
    generator = None if synthetic is None else Generator(synthetic, seed, length, amplitude)
    problem = InverseProblem(for_command(scene, "train"), target=False)
    log.info(f"train: 1 scene(s), {len(examples)} examples, {problem.force_dofs} force dofs, rank {rank}")
    return train_bases(problem, examples, rank, generator)


def render(what: Simulation | Estimate | PathLike, off_screen: bool = True, title: str | None = None) -> pv.Plotter | None:
    """A pyvista Plotter with the picture of a simulation, an estimate or a result
    folder, drawn but not shown: ``.show()`` it, or ``.screenshot(path)``. Off-screen
    unless ``off_screen`` is False; no global setting of pyvista's is changed.
    Collective; the plotter on rank 0, None elsewhere."""
    from fenics_elasto.app.render import caption, picture, read_result_folder, target_polydata
    from fenics_elasto.app.results import picture_arguments

    if isinstance(what, (str, os.PathLike)):
        return picture(**{**read_result_folder(Path(what)), **({"title": title} if title is not None else {})},
                       off_screen=off_screen)
    require(isinstance(what, (Simulation, Estimate)),
            f"render: expected a Simulation, an Estimate or a result folder, got {type(what).__name__}")
    drawn = picture_arguments(what.scene, what.u)
    target = target_polydata(what.problem) if isinstance(what, Estimate) and drawn is not None else None
    if drawn is None:
        return None
    text = caption(what.record, "", drawn["units"]) if title is None else title
    return picture(**drawn, target=target, title=text, off_screen=off_screen)


__all__ = ["Bases", "Estimate", "Scene", "Simulation", "Target", "UserError", "build_scene", "estimate", "load_scene",
           "render", "scene_from_spec", "simulate", "train"]
