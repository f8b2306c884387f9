"""A stand-in for a fenics-elasto command, driven by tests/test_outputs.py; also the
small demonstration of how a command uses ``fenics_elasto.outputs`` and ``.interrupts``.

    python outputs_child.py OUT HOLD [--steps N] [--tag T]

It "computes" (a collective sum per step, as the estimator evaluates), then writes a
result folder: forces.csv (rank 0), field.bp (a directory every rank writes a piece of,
like the VTX output), big.bin (in chunks), and result.json last. HOLD is where it waits
for the test: "first" (before the first result, until a signal), "compute" (computing
until a signal), "writing" (after forces.csv, until a line on stdin), "big" (half-way
through big.bin, until a line on stdin) or "none". Markers on stdout time the test's
signals; the exit status is the CLI's: 0, 2 (UserError), 130 (interrupted).
"""

import argparse
import sys
import time

from mpi4py import MPI

from fenics_elasto.util.errors import UserError
from fenics_elasto.util.interrupts import Interrupted, check_interrupt, handle_signals
from fenics_elasto.files.outputs import prepare_folder

COMM = MPI.COMM_WORLD
CHUNKS, CHUNK = 8, 1 << 16


def say(text: str) -> None:
    if COMM.rank == 0:
        print(text, flush=True)


def big_chunk(tag: str, i: int) -> bytes:
    return (f"{tag}{i}".encode() * CHUNK)[:CHUNK]


def compute(args) -> tuple[list[int], bool]:
    """Steps until done (HOLD compute: until a signal); an interrupt keeps the steps so far."""
    history = []
    try:
        if args.hold == "first":
            say("waiting")
            while True:
                check_interrupt(COMM)
                time.sleep(0.01)
        while len(history) < args.steps or args.hold == "compute":
            check_interrupt(COMM)  # every rank at the same point: under MPI all stop together
            history.append(COMM.allreduce(len(history) + 1))
            say(f"step {len(history)}")
            time.sleep(0.01)
        return history, False
    except KeyboardInterrupt:
        if not history:
            raise Interrupted("before the first result: nothing written") from None
        if COMM.rank == 0:
            print("interrupted: writing the best result so far", file=sys.stderr, flush=True)
        return history, True


def hold() -> None:
    say("holding")
    if COMM.rank == 0:
        sys.stdin.readline()
    COMM.barrier()


def write(folder, history: list[int], interrupted: bool, args) -> None:
    result = {"interrupted": interrupted, "steps": len(history), "tag": args.tag, "ranks": COMM.size}
    with folder.writing(result):
        say("writing")
        folder.write_text("forces.csv", "".join(f"{args.tag},{h}\n" for h in history))
        if args.hold == "writing":
            hold()
        field = folder.path_for("field.bp")  # every rank writes a piece, as VTXWriter does
        if COMM.rank == 0:
            field.mkdir()
        COMM.barrier()
        (field / f"rank{COMM.rank}.txt").write_text(f"{args.tag}\n")
        if COMM.rank == 0:
            with open(folder.path_for("big.bin"), "wb") as f:
                for i in range(CHUNKS):
                    f.write(big_chunk(args.tag, i))
                    f.flush()
                    if args.hold == "big" and i == CHUNKS // 2:
                        hold()
    say("done")


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("out")
    parser.add_argument("hold", choices=["first", "compute", "writing", "big", "none"])
    parser.add_argument("--steps", type=int, default=3)
    parser.add_argument("--tag", default="A")
    args = parser.parse_args()
    with handle_signals(COMM):
        try:
            folder = prepare_folder(args.out, COMM)
            say("prepared")
            history, interrupted = compute(args)
            write(folder, history, interrupted, args)
            return 130 if interrupted else 0
        except UserError as err:
            if COMM.rank == 0:
                print(f"error: {err}", file=sys.stderr, flush=True)
            return 2
        except KeyboardInterrupt as err:
            if COMM.rank == 0:
                print(f"interrupted: {err}" if str(err) else "interrupted", file=sys.stderr, flush=True)
            return 130


if __name__ == "__main__":
    sys.exit(main())
