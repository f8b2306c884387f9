"""How far the forward solve scales: the prostate phantom at growing sizes, direct vs
iterative, 1 vs 2 MPI ranks (prints a markdown table).

    python benchmarks/scale.py [--sizes 1.6 1.0 0.59 0.47] [--ranks 1 2]
                               [--methods direct iterative] [--direct-limit 400000]

Per size: the mesh is generated once (its time is a column). Per (size, method, ranks)
a child process (`mpiexec -n R python benchmarks/scale.py --child ...`) loads the scene,
assembles the material matrices, builds the solver (MUMPS factorization, or the GAMG
hierarchy) and solves `simulate`'s problem (the bladder's prescribed inflation) through
ElasticModel -- no output writing. Peak memory is each rank's resident high-water mark
(VmHWM in /proc/<pid>/status, the whole process included): the largest over the ranks
and the sum.

The children read the mesh's parallel copy (model/mesh_copy.py), each rank a slice. The
copy is written once per mesh by a serial child (``--copy``) before them; its time and
peak memory are the "first read" columns: the gmsh read on one rank that every later
run is spared.

Direct runs above --direct-limit DOFs would take hours or not fit: for those the child
runs MUMPS's analysis only (the workspace capped with ICNTL(23) so that the numeric
phase stops at once) and reports its estimates -- memory of the factorization and
flops -- with the time predicted from the flop rate of the largest direct run
measured. Such cells are marked "est.".
"""

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import fenics_elasto  # noqa: F401  (imports dolfinx_solver before petsc4py)
from mpi4py import MPI

from fenics_elasto.model.elasticity import ElasticModel
from fenics_elasto.util.logs import quiet
from fenics_elasto.mesh.builtin import build_scene
from fenics_elasto.model.scene import load_scene
from fenics_elasto.model.simulate import material_values, simulate
from fenics_elasto.model.solvers import SolverSettings, mumps_analysis

HERE = Path(__file__).resolve()
BIN = Path(sys.executable).parent


def peak_memory_gb(comm) -> tuple[float, float]:
    """The largest VmHWM (resident high-water mark) of any rank, and their sum, in GB."""
    text = Path("/proc/self/status").read_text()
    kb = next(int(line.split()[1]) for line in text.splitlines() if line.startswith("VmHWM"))
    return comm.allreduce(kb, op=MPI.MAX) / 1024**2, comm.allreduce(kb, op=MPI.SUM) / 1024**2


def first_read(problem: str) -> dict:
    """Load the scene once, in one process, as a new .msh is: gmsh reads it and the
    parallel copy is written."""
    clock = time.perf_counter()
    load_scene(problem, command="simulate")
    return {"first read s": time.perf_counter() - clock, "first read GB": peak_memory_gb(MPI.COMM_WORLD)[0]}


def child(problem: str, method: str, analysis_only: bool) -> dict:
    comm = MPI.COMM_WORLD
    quiet()
    clock = time.perf_counter()
    scene = load_scene(problem, command="simulate")
    E, nu = material_values(scene)
    model = ElasticModel(scene, SolverSettings(method=method), fixed=(E, nu))  # as simulate's own
    model.stiffness.terms
    comm.barrier()
    row = {"dofs": model.dofs.num_dofs, "ranks": comm.size, "method": method, "load + matrices s": time.perf_counter() - clock}
    c = model.stiffness.coefficients(E, nu)
    clamped = model.dofs.clamped_dofs(scene.fixed + list(scene.displacement))
    if analysis_only:
        row.update(mumps_estimates(model, c, clamped))
    else:
        clock = time.perf_counter()
        model.factorize(c, clamped)  # the factorization or the AMG hierarchy
        comm.barrier()
        row["setup s"] = time.perf_counter() - clock
        clock = time.perf_counter()
        sim = simulate(scene, model)  # finds the solver in the cache: the solve itself
        comm.barrier()
        row["solve s"] = time.perf_counter() - clock
        row["max |u|"] = sim.result["max_displacement"]
        row["iterations"] = model.stats.iterations
        if method == "direct":
            F = next(iter(model.solvers)).factor
            row["flops"] = F.getMumpsRinfog(3)  # performed in the elimination
    row["peak GB per rank"], row["peak GB"] = peak_memory_gb(comm)
    return row


def mumps_estimates(model, c, clamped) -> dict:
    """MUMPS's analysis of K: estimated factorization memory and flops (no numeric phase)."""
    K = model.stiffness.constrained(c, clamped)
    clock = time.perf_counter()
    analysis = mumps_analysis(K)
    out = {"analysis s": time.perf_counter() - clock, "est. factor GB": analysis["total MB"] / 1024,
           "est. flops": analysis["flops"], "infog1": analysis["infog1"]}
    K.destroy()
    return out


def run_child(problem: Path, method: str, ranks: int, analysis_only: bool, copy: bool = False) -> dict:
    if copy:
        cmd = [sys.executable, str(HERE), "--copy", str(problem)]
    else:
        cmd = [sys.executable, str(HERE), "--child", str(problem), method] + (["--analysis-only"] if analysis_only else [])
    if ranks > 1:
        cmd = [str(BIN / "mpiexec"), "-n", str(ranks)] + cmd
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        return {"dofs": None, "ranks": ranks, "method": method, "error": proc.stderr.strip().splitlines()[-1:]}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def msh_dofs(path: Path) -> int:
    """P2 DOFs of a quadratic gmsh mesh before loading it: 3 x its node count (the
    $Nodes header: blocks, nodes, min tag, max tag) -- a direct run too big to fit must
    be known before it is tried (the OOM killer ended one at 500k DOFs)."""
    with open(path) as f:
        for line in f:
            if line.strip() == "$Nodes":
                return 3 * int(next(f).split()[1])
    raise ValueError(f"{path}: no $Nodes section")


def fmt(value, digits=3) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}g}"
    return str(value)


def table(rows, mesh_times, first_reads) -> None:
    rate = max((r["flops"] / r["setup s"] for r in rows if r.get("flops")), default=None)
    print("| h | DOFs | mesh s | first read s / GB | method | ranks | load + matrices s | solver setup s | solve s "
          "| CG its | peak GB per rank (largest) | peak GB (all ranks) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        first = first_reads[r["h"]]
        first_text = f"{fmt(first.get('first read s'))} / {fmt(first.get('first read GB'))}"
        if "error" in r:
            print(f"| {r['h']} | | | {first_text} | {r['method']} | {r['ranks']} | failed: {' '.join(r['error'])} "
                  "| | | | | |")
            continue
        if "est. flops" in r:
            predicted = r["est. flops"] / rate if rate else None
            setup = f"~{fmt(predicted)} (est.; analysis {fmt(r['analysis s'])})"
            memory = f"~{fmt(r['est. factor GB'])} factors (est.) + {fmt(r['peak GB'])}"
            solve, its = "-", "-"
        else:
            setup, solve, memory = fmt(r["setup s"]), fmt(r["solve s"]), fmt(r["peak GB"])
            its = fmt(r["iterations"]) if r["method"] == "iterative" else "-"
        per_rank = fmt(r["peak GB per rank"]) if "est. flops" not in r else "-"
        print(f"| {r['h']} | {r['dofs']} | {fmt(mesh_times[r['h']])} | {first_text} | {r['method']} | {r['ranks']} | "
              f"{fmt(r['load + matrices s'])} | {setup} | {solve} | {its} | {per_rank} | {memory} |")
    if rate:
        print(f"\n(direct flop rate measured: {rate / 1e9:.1f} GFlop/s; est. = from MUMPS's analysis)")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=float, nargs="+", default=[1.6, 1.0, 0.59, 0.47])
    parser.add_argument("--ranks", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--methods", nargs="+", default=["direct", "iterative"])
    parser.add_argument("--direct-limit", type=int, default=400_000)
    parser.add_argument("--child", nargs=2, metavar=("PROBLEM", "METHOD"))
    parser.add_argument("--analysis-only", action="store_true")
    parser.add_argument("--copy", metavar="PROBLEM")
    args = parser.parse_args()
    if args.copy:
        print(json.dumps(first_read(args.copy)))
        return
    if args.child:
        row = child(*args.child, args.analysis_only)
        if MPI.COMM_WORLD.rank == 0:
            print(json.dumps(row))
        return
    rows, mesh_times, first_reads = [], {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        for h in args.sizes:
            clock = time.perf_counter()
            problem = build_scene("prostate-phantom", Path(tmp) / f"h{h}", size=h)
            mesh_times[h] = time.perf_counter() - clock
            dofs = msh_dofs(problem.parent / "phantom.msh")
            first_reads[h] = run_child(problem, "", 1, False, copy=True)
            for method in args.methods:
                for ranks in args.ranks:
                    analysis_only = method == "direct" and dofs > args.direct_limit
                    row = run_child(problem, method, ranks, analysis_only)
                    row["h"] = h
                    rows.append(row)
                    print(json.dumps(row), file=sys.stderr, flush=True)
    table(rows, mesh_times, first_reads)


if __name__ == "__main__":
    main()
