"""Command line: parse, call the API, print, exit (0 ok, 2 bad input)."""

from __future__ import annotations

import argparse
import sys
import traceback
from pathlib import Path

from mpi4py import MPI

from fenics_elasto.util.errors import UserError, require
from fenics_elasto.util.interrupts import handle_signals
from fenics_elasto.util.logs import log, show


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="fenics-elasto", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("mesh", help="write a built-in scene (.msh + problem.toml)")
    p.add_argument("name", help="letter-a, cantilever or prostate-phantom")
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--size", type=float, default=None, help="element size (scene units)")
    p.add_argument("--seed", type=int, default=None, help="phantom patient variation (0 = nominal)")
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
        if name == "estimate":
            p.add_argument("--check-mesh", action="store_true",
                           help="also estimate on the source mesh split once on its geometry; report how far it moves")

    p = sub.add_parser("train", help="PCA force bases from example target surfaces")
    p.add_argument("problem", type=Path, nargs="?", help="the scene the --examples deform")
    p.add_argument("--examples", nargs="+", default=[], type=Path,
                   help="target surfaces, or folders of surface_<group>.vtp (as simulate writes)")
    p.add_argument("--patient", nargs="+", action="append", default=[], type=Path, metavar="PROBLEM.toml EXAMPLE",
                   help="with --atlas: one more training scene and its examples (repeat per patient)")
    p.add_argument("--atlas", type=Path, default=None,
                   help="the mesh every training scene was built around (`mesh --atlas`): bases in its "
                        "numbering, usable on any patient built around it")
    p.add_argument("--synthetic", type=int, default=None, metavar="N",
                   help="N example deformations of the scene itself: smooth random pressure/traction, affine and "
                        "displacement-mode wall motions (with or instead of --examples)")
    p.add_argument("--seed", type=int, default=0, help="--synthetic: random seed")
    p.add_argument("--length", type=float, default=None, help="--synthetic: length scale of the random fields "
                   "(mesh units; default half the loaded walls' extent)")
    p.add_argument("--amplitude", type=float, default=None, help="--synthetic: rms wall displacement of an example "
                   "(mesh units; default 2 %% of the scene's diameter)")
    p.add_argument("--rank", type=int, required=True)
    p.add_argument("--out", type=Path, required=True, help="bases .npz")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a TOML value (all scenes)")

    p = sub.add_parser("render", help="re-draw the picture of a result folder")
    p.add_argument("result_dir", type=Path)
    p.add_argument("--out", type=Path, default=None)
    return parser


def _mesh(args) -> None:
    from fenics_elasto.app.commands import run_mesh

    path = run_mesh(args.name, args.out, args.size, args.seed, args.atlas,
                    organ_size=args.organ_size, prostate_size=args.prostate_size)
    log.info(f"wrote {path}")


def _scene(args) -> None:
    from fenics_elasto.app.commands import run_scene

    log.info(f"wrote {run_scene(args.spec, args.out, args.size)}")


def _simulate(args) -> None:
    from fenics_elasto.app.commands import run_simulate

    run_simulate(args.problem, args.out, args.set)


def _estimate(args) -> int:
    from fenics_elasto.app.commands import run_estimate

    result = run_estimate(args.problem, args.out, args.set, args.check_mesh)
    return 130 if result["interrupted"] else 0


def _train(args) -> None:
    from fenics_elasto.app.commands import run_train

    from fenics_elasto.inverse.reduction.synthetic import Generator

    patients = ([(args.problem, args.examples)] if args.problem else []) + [(p, e) for p, *e in args.patient]
    require(patients, "train: give PROBLEM.toml --examples ... or --synthetic N, "
                      "or --atlas with --patient PROBLEM.toml EXAMPLE...")
    require(not args.examples or args.problem, "train: --examples belong to a PROBLEM.toml (first argument)")
    require(args.rank >= 1, f"--rank must be >= 1, got {args.rank}")
    generator = None
    if args.synthetic is not None:
        require(args.synthetic >= 1, f"--synthetic must be >= 1, got {args.synthetic}")
        require(not args.atlas, "train: --synthetic trains one scene; it does not combine with --atlas")
        generator = Generator(args.synthetic, args.seed, args.length, args.amplitude)
    run_train(patients, args.out, args.rank, args.atlas, args.set, generator)


def _render(args) -> None:
    from fenics_elasto.app.commands import run_render

    run_render(args.result_dir, args.out)


COMMANDS = {"mesh": _mesh, "scene": _scene, "simulate": _simulate, "estimate": _estimate, "train": _train, "render": _render}


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    show()
    comm = MPI.COMM_WORLD
    try:
        with handle_signals(comm):  # SIGINT, SIGTERM, SIGHUP: stop, keep the best so far
            return COMMANDS[args.command](args) or 0
    except UserError as err:
        if comm.rank == 0:
            print(f"error: {err}", file=sys.stderr, flush=True)
        return 2
    except KeyboardInterrupt as err:
        if comm.rank == 0:
            print(f"interrupted{': ' + str(err) if str(err) else ''}", file=sys.stderr, flush=True)
        return 130
    except Exception:
        if comm.size > 1:  # a bug on one rank would leave the others waiting forever
            traceback.print_exc()
            sys.stderr.flush()
            comm.Abort(1)
        raise


if __name__ == "__main__":
    sys.exit(main())
