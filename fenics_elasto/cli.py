"""Command line: parse, call the API, print, exit (0 ok, 2 bad input)."""

from __future__ import annotations

import argparse
import sys
import traceback
from pathlib import Path

from mpi4py import MPI

from fenics_elasto.errors import UserError, require


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="fenics-elasto", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("mesh", help="write a built-in scene (.msh + problem.toml)")
    p.add_argument("name", help="letter-a, cantilever or prostate-phantom")
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--size", type=float, default=None, help="element size (scene units)")
    p.add_argument("--seed", type=int, default=0, help="phantom patient variation (0 = nominal)")
    p.add_argument("--atlas", type=Path, default=None,
                   help="phantom: mesh around this mesh's bladder and rectum (shared loaded nodes)")
    p.add_argument("--organ-size", type=float, default=None,
                   help="phantom: element size at bladder and rectum, relative to --size (default 0.35)")
    p.add_argument("--prostate-size", type=float, default=None,
                   help="phantom: element size at the prostate, relative to --size (default 0.22)")

    p = sub.add_parser("scene", help="a scene (.msh + problem.toml) from organ surface files named in a spec")
    p.add_argument("spec", type=Path, help="scene spec (TOML): body, regions, cavities, patches")
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--size", type=float, default=None, help="element size in the body (the spec's units)")

    for name, text in (("simulate", "forward solve with prescribed loads/displacements"),
                       ("estimate", "estimate materials and boundary forces from a target")):
        p = sub.add_parser(name, help=text)
        p.add_argument("problem", type=Path)
        p.add_argument("--out", required=True, type=Path)
        p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a TOML value")

    p = sub.add_parser("train", help="PCA force bases from example target surfaces")
    p.add_argument("problem", type=Path, nargs="?", help="the scene the --examples deform")
    p.add_argument("--examples", nargs="+", default=[], type=Path,
                   help="target surfaces, or folders of surface_<group>.vtp (as simulate writes)")
    p.add_argument("--patient", nargs="+", action="append", default=[], type=Path, metavar="PROBLEM.toml EXAMPLE",
                   help="with --atlas: one more training scene and its examples (repeat per patient)")
    p.add_argument("--atlas", type=Path, default=None,
                   help="the mesh every training scene was built around (`mesh --atlas`): bases in its "
                        "numbering, usable on any patient built around it")
    p.add_argument("--rank", type=int, required=True)
    p.add_argument("--out", type=Path, required=True, help="bases .npz")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a TOML value (all scenes)")

    p = sub.add_parser("render", help="re-draw the picture of a result folder")
    p.add_argument("result_dir", type=Path)
    p.add_argument("--out", type=Path, default=None)
    return parser


def _mesh(args) -> None:
    from fenics_elasto.meshing import atlas_surfaces, build_scene

    path, error = None, None
    if MPI.COMM_WORLD.rank == 0:  # gmsh meshes on one rank; its verdict goes to all
        try:
            require(args.atlas is None or args.name == "prostate-phantom", "--atlas: only prostate-phantom takes an atlas")
            atlas = atlas_surfaces(args.atlas) if args.atlas else None
            path = build_scene(args.name, args.out, args.size, args.seed, atlas,
                               organ_size=args.organ_size, prostate_size=args.prostate_size)
        except UserError as err:
            error = str(err)
    path, error = MPI.COMM_WORLD.bcast((path, error), root=0)
    require(error is None, error)
    _say(f"wrote {path}")


def _scene(args) -> None:
    from fenics_elasto.anatomy import build_scene_from_spec

    path, error = None, None
    if MPI.COMM_WORLD.rank == 0:  # gmsh meshes on one rank; its verdict goes to all
        try:
            path = build_scene_from_spec(args.spec, args.out, args.size, say=_say)
        except UserError as err:
            error = str(err)
    path, error = MPI.COMM_WORLD.bcast((path, error), root=0)
    require(error is None, error)
    _say(f"wrote {path}")


def _simulate(args) -> None:
    from fenics_elasto.io import write_solution
    from fenics_elasto.scene import load_scene
    from fenics_elasto.simulate import simulate

    scene = load_scene(args.problem, args.set)
    sim = simulate(scene)
    write_solution(args.out, scene, sim.u, sim.result, title=f"simulate: {args.problem.parent.name}")
    _say(f"dofs {sim.result['dofs']}, max |u| {sim.result['max_displacement']:.4g}, "
         f"{sim.result['wall_time_s']:.2f} s -> {args.out}")


def _estimate(args) -> None:
    from fenics_elasto.estimate import run_estimate

    result = run_estimate(args.problem, args.out, args.set)
    return 130 if result["interrupted"] else 0


def _train(args) -> None:
    from fenics_elasto.meshing import atlas_surfaces
    from fenics_elasto.objective import InverseProblem
    from fenics_elasto.reduction import train_atlas_bases, train_bases
    from fenics_elasto.render import plot_variance
    from fenics_elasto.scene import load_scene

    patients = ([[args.problem, *args.examples]] if args.problem else []) + args.patient
    require(patients, "train: give PROBLEM.toml --examples ..., or --atlas with --patient PROBLEM.toml EXAMPLE...")
    require(not args.examples or args.problem, "train: --examples belong to a PROBLEM.toml (first argument)")
    require(len(patients) == 1 or args.atlas, "train: several training scenes need --atlas (their shared mesh)")
    for problem, *examples in patients:
        require(examples, f"train: no examples given for {problem}")
    problems = [(InverseProblem(load_scene(p, args.set), target=False), examples) for p, *examples in patients]
    count = sum(len(e) for _, e in problems)
    _say(f"train: {len(problems)} scene(s), {count} examples, {problems[0][0].force_dofs} force dofs, rank {args.rank}")
    if args.atlas:
        atlas = atlas_surfaces(args.atlas, problems[0][0].scene.loaded)
        bases = train_atlas_bases(atlas, problems, args.rank, say=_say)
    else:
        bases = train_bases(*problems[0], args.rank, say=_say)
    if MPI.COMM_WORLD.rank == 0:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        bases.save(args.out)
        plot_variance(bases.variance, args.out.with_suffix(".png"))
    kept = bases.variance.sum()
    _say(f"wrote {args.out} (rank {bases.W.shape[1]}, {100 * kept:.2f} % of the example energy) "
         f"and {args.out.with_suffix('.png')}")


def _render(args) -> None:
    from fenics_elasto.render import render_folder

    if MPI.COMM_WORLD.rank == 0:
        _say(f"wrote {render_folder(args.result_dir, args.out)}")


def _say(text: str) -> None:
    if MPI.COMM_WORLD.rank == 0:
        print(text, flush=True)


COMMANDS = {"mesh": _mesh, "scene": _scene, "simulate": _simulate, "estimate": _estimate, "train": _train, "render": _render}


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    try:
        return COMMANDS[args.command](args) or 0
    except UserError as err:
        if MPI.COMM_WORLD.rank == 0:
            print(f"error: {err}", file=sys.stderr, flush=True)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr, flush=True)
        return 130
    except Exception:
        if MPI.COMM_WORLD.size > 1:  # a bug on one rank would leave the others waiting forever
            traceback.print_exc()
            sys.stderr.flush()
            MPI.COMM_WORLD.Abort(1)
        raise


if __name__ == "__main__":
    sys.exit(main())
