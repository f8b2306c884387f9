"""How the prostate E estimate converges with the meshes (patient 0, true E = 50 kPa).

    python benchmarks/convergence.py [--out DIR]      # about 10 minutes

The stiffness signal is tiny (~1e-3 cm of prostate-surface motion per 10 % of E), so
the estimate is as good as the meshes. Two tables:

1. The reference ("truth") side: the default source against targets simulated on
   ever finer meshes, their curved facets written as 4x4 or 8x8 flat pieces -- what a
   coarse target hides.
2. The source side: sources refined at the organ walls and at the prostate against
   the finest target; rank-12 bases trained on each source's own examples.
"""

import argparse
import tempfile
import time
from pathlib import Path

import fenics_elasto  # noqa: F401
from fenics_elasto.mesh.builtin import ORGAN_SIZE, PROSTATE_SIZE, build_scene
from fenics_elasto.inverse.objective import InverseProblem
from fenics_elasto.inverse.reduction.bases import train_bases
from fenics_elasto.model.scene import load_scene

from fenics_elasto.app.study import SIZE, recovered, run_case  # noqa: E402

from fenics_elasto.app.study import simulate_examples, simulate_targets  # noqa: E402

TRUE_E = 50.0
TARGETS = ((1.3, 4), (1.0, 4), (0.8, 4), (0.8, 8))  # (h of the target mesh, pieces per facet edge)
SOURCES = ((ORGAN_SIZE, PROSTATE_SIZE), (ORGAN_SIZE, 0.15), (0.25, PROSTATE_SIZE), (0.2, PROSTATE_SIZE))


def target(out: Path, size: float, pieces: int) -> str:
    return simulate_targets(out / f"target_{size:g}_{pieces}", (TRUE_E,), size, pieces=pieces)[TRUE_E].settings()


def source_with_bases(out: Path, organ: float, prostate: float):
    source = build_scene("prostate-phantom", out / f"source_{organ:g}_{prostate:g}", size=SIZE,
                         organ_size=organ, prostate_size=prostate)
    examples = simulate_examples(source, source.parent / "examples", 12)
    trainer = InverseProblem(load_scene(source), target=False)
    return source, train_bases(trainer, examples, rank=12).W


def row(label: str, result: dict) -> str:
    E = recovered(result)
    return (f"| {label} | {result['dofs']:,} | {result['force_dofs']:,} | {E:.2f} | {100 * (E - TRUE_E) / TRUE_E:+.1f} | "
            f"{result['surface_distance']['rms']:.1e} | {result['seconds']:.1f} |")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="convergence_"))
    header = ["| {} | DOFs | force DOFs | E | error % | rms misfit cm | estimate s |", "|---|---|---|---|---|---|---|"]

    print(f"source h = {SIZE}, organs {ORGAN_SIZE} h, prostate {PROSTATE_SIZE} h; true E = {TRUE_E:g}", flush=True)
    source, W = source_with_bases(out, ORGAN_SIZE, PROSTATE_SIZE)
    lines = [header[0].format("target mesh h, pieces per facet edge"), header[1]]
    targets = {}
    for size, pieces in TARGETS:
        start = time.perf_counter()
        targets[size, pieces] = target(out, size, pieces)
        made = time.perf_counter() - start
        result = run_case(source, targets[size, pieces], W)
        lines.append(row(f"{size:g}, {pieces} (made in {made:.0f} s)", result))
        print(lines[-1], flush=True)

    finest = targets[TARGETS[-1]]
    lines += ["", header[0].format(f"source: organs, prostate (x h = {SIZE})"), header[1],
              row(f"{ORGAN_SIZE:g}, {PROSTATE_SIZE:g} (the default, as above)", result)]
    for organ, prostate in SOURCES[1:]:
        source, W = source_with_bases(out, organ, prostate)
        lines.append(row(f"{organ:g}, {prostate:g}", run_case(source, finest, W)))
        print(lines[-1], flush=True)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
