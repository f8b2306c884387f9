"""Linear solves K x = b: direct factorizations that keep their analysis, CG with
algebraic multigrid for big meshes, and no failure that goes unnoticed.

Every K here is sum_j c_j M_j with identity rows and columns on the clamped DOFs
(elasticity.py): its values change with the materials, its sparsity never does.

* **direct** (MUMPS LU or Cholesky through PETSc). A solver object keeps its KSP and
  its matrix; new material values refill the matrix in place (same nonzero pattern),
  so PETSc refactors numerically only and MUMPS's ordering and symbolic analysis are
  paid once per object (measured: ~6 % of a factorization here; the numeric phase is
  the cost). Block low-rank compression (``blr``: MUMPS ICNTL(35), dropping
  tolerance CNTL(7)) makes factors smaller (116k DOFs: -13 % entries at 1e-8, -49 % at
  1e-4) and quicker to make, but approximate. By default ("auto") it is on from
  AUTO_BLR_DOFS up where a factorization serves few solves (a simulation, training's
  material levels) and off where it serves many (an estimate's). Every solution is
  refined against the true K
  (x += F^-1 (b - K x) while that halves the residual, then GMRES preconditioned by
  the same factors) until ||b - K x|| <= rtol ||b||, so the answer is exact to rtol
  with or without compression. The residual check costs one product with K and also
  catches a factorization that "succeeded" on a singular K.
* **iterative**: CG preconditioned by PETSc's GAMG (smoothed aggregation) with the
  rigid-body near-nullspace (translations and rotations at the DOF coordinates:
  3 modes in 2D, 6 in 3D); a new material value keeps the hierarchy's interpolation
  and recomputes only the coarse operators. Block right-hand sides are solved column by
  column (this PETSc has no block Krylov method), each from a warm start
  (``WarmStart``).
* **nearby** (``simulate``'s single solve, an estimate's solves after its first): a direct
  solver already holding the factors of K(c0) for the same clamped set solves K(c) x = b
  by CG preconditioned with those factors when c/c0 stays within ``NEARBY_RATIO``
  (``NearbySolver``): a handful of back-solves instead of a new factorization. The same
  factors (``SolverCache.closest``, ``DirectSolver.apply_factors``) precondition the
  reduced estimate's refinement at its optimum (surrogate.MaterialSurrogate.refine).
* **ahead** (a reduced estimate's one factorization, ``SolverCache.ahead``): serial, the
  memory check and the factorization run in a thread of its own through PETSc's C
  library, which lets go of the GIL, on K assembled at once (``AffineStiffness.at_once``),
  while the estimate sets itself up (the affine terms, matching, the surrogate's pieces)
  on the other core; its first solve waits for it. The default phantom at rank 80:
  49.4 -> 47.7 s, and the factors ready ~1 s sooner again with K at once (docs:
  performance, "The factorization beside the set-up").
* **auto**: direct up to ``DIRECT_LIMIT`` DOFs, iterative beyond (the crossover measured
  by benchmarks/scale.py on a 2-core, 24 GB machine).

**Tolerance.** Solves stop at ||b - K x|| <= rtol ||b|| (default 1e-8). The misfit,
its gradients (one adjoint solve) and the reduced responses are linear in the solved
fields, so they inherit the fields' relative error, ~rtol times a modest factor (the
fields' measured error at rtol 1e-8 is 1.5-2.6e-9 on the phantom at 32k and 116k DOFs,
benchmarks/solvers.py; each decade of rtol costs ~3 CG iterations). The optimiser
asks for far less: the outer loop stops when log E moves by less than 1e-3 and the
inner one at a relative gradient of 1e-6, so 1e-8 keeps two to three digits of margin
while a tighter rtol would only add CG iterations.

**Checks.** Before the first factorization of a K above ``MEMORY_CHECK_DOFS`` DOFs,
MUMPS's analysis alone (the numeric phase refused at once with a 1 MB workspace cap)
says how much memory the factors will take; more than ``MEMORY_SHARE`` of what the
machine has available (per node: the busiest rank's estimate times the ranks there)
ends the run in one line -- Linux's OOM killer otherwise ends it without a word (it
did, at 500k DOFs on 24 GB); started ``ahead``, the check runs in the factorization's
thread and its error is raised at the first solve. After every factorization: MUMPS INFOG(1) (PETSc does not raise when MUMPS
fails; a ``preonly`` solve then returns Inf). After every solve: the KSP converged
reason, the residual and a finite solution. A failure raises ``SolverError`` (a
UserError: the command line prints one line naming the cause and the remedy, exit 2).

PETSc options: every KSP here has the prefix ``elasto_``, so PETSC_OPTIONS can tune
what the toolkit does not expose (``-elasto_mat_mumps_icntl_14 100``,
``-elasto_pc_gamg_threshold 0.02``, ``-elasto_ksp_monitor``); options given that way
win over the defaults set here.
"""

from __future__ import annotations

import ctypes
import functools
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, replace

import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

from fenics_elasto.model.dofs import times_block
from fenics_elasto.util.budget import available_memory
from fenics_elasto.util.errors import UserError

PREFIX = "elasto_"
DIRECT_LIMIT = 300_000  # DOFs: "auto" factorizes up to here (benchmarks/scale.py)
MEMORY_CHECK_DOFS = 100_000  # direct: above this, MUMPS's analysis first (~6 % of a factorization)
MEMORY_SHARE = 0.8  # ... and refuse factors estimated above this share of the available memory
REFINEMENTS = 10  # direct: at most this many refinement steps per solve
MAX_ITERATIONS = 2000  # iterative: CG iterations per right-hand side
NEARBY_RATIO = 4.0  # NearbySolver: largest spread of c / c0 (CG ~ sqrt(ratio) log(2 / rtol) iterations)
# blr = "auto": MUMPS's block low-rank factors at this dropping tolerance, from this size up,
# where a factorization serves few solves (a simulation, training's material levels). On
# the default phantom (116k DOFs) a simulate took 12.8 s against 19.7 s and a `train
# --synthetic 120 --rank 80` 46 s against 57-59 s; 1e-4 factorizes faster still but its
# solutions need so many refinement steps that training took 72 s. Smaller phantoms: at 61k
# DOFs a simulate 0.82x and a training 0.88x, at 46k 0.88-0.94x, at 32k the fronts are
# too small to compress (2.5-2.9 s against 2.0 s). A reduced estimate keeps exact
# factors: its one factorization serves hundreds of block solves and preconditions its
# refinement, and with 1e-5 it took 53 s against 47-49 s (docs/performance.md).
AUTO_BLR = 1e-5
AUTO_BLR_DOFS = 50_000
RHS_BLOCK_BYTES = 256 * 2**20  # direct: MUMPS solves a block of right-hand sides this much at a time
WARM_COLUMNS = (8, 64)  # WarmStart keeps at least 8 recent solutions, at most 64

# GAMG beyond PETSc's defaults (benchmarks/solvers.py, 116k P2 DOFs): SOR smoothing
# instead of Jacobi halves the CG iterations (27 instead of 51) at no extra setup; a drop
# threshold of 0.02 would save 3 more iterations but costs 45 % more setup. The
# interpolation is kept across material values (a refresh costs half a setup).
GAMG_OPTIONS = {
    "pc_gamg_type": "agg",
    "pc_gamg_reuse_interpolation": "true",
    "mg_levels_pc_type": "sor",
}


class SolverError(UserError):
    """A factorization or solve failed; the message says why and what to change."""


# --------------------------------------------------------------------------- settings


@dataclass(frozen=True)
class SolverSettings:
    """The problem's ``[solver]`` table (config.py validates it)."""

    method: str = "auto"  # "direct" | "iterative" | "auto"
    rtol: float = 1e-8  # every solve: ||b - K x|| <= rtol ||b||
    factor: str = "lu"  # direct: "lu" | "cholesky"
    blr: float | str = "auto"  # direct: MUMPS block low-rank tolerance, 0 = off, "auto": AUTO_BLR's rule

    @classmethod
    def from_config(cls, table: dict | None) -> SolverSettings:
        table = table or {}
        return cls(**{key: table[key] for key in ("method", "rtol", "factor", "blr") if key in table})

    def method_for(self, dofs: int) -> str:
        if self.method != "auto":
            return self.method
        return "direct" if dofs <= DIRECT_LIMIT else "iterative"

    def blr_for(self, dofs: int, few_solves: bool) -> float:
        """The block low-rank tolerance of a factorization of K with ``dofs`` DOFs that
        serves few solves or many (0: exact factors)."""
        if self.blr != "auto":
            return float(self.blr)
        return AUTO_BLR if few_solves and dofs >= AUTO_BLR_DOFS else 0.0


@dataclass
class SolverStats:
    """What the solves cost, for result.json (``as_dict``)."""

    method: str
    factorizations: int = 0  # numeric factorizations (direct)
    analyses: int = 0  # orderings + symbolic analyses (direct)
    setups: int = 0  # AMG hierarchies built or refreshed (iterative)
    solves: int = 0  # right-hand sides solved
    iterations: int = 0  # CG iterations (iterative); refinement + GMRES steps (direct)
    blr: float = 0.0  # direct: the latest factors' block low-rank tolerance (0: exact)

    def as_dict(self) -> dict:
        return asdict(self)


# --------------------------------------------------------------------------- shared pieces


def _set_defaults(options: dict) -> None:
    """Our defaults under PREFIX, unless PETSC_OPTIONS (or the caller) set them already."""
    db = PETSc.Options()
    for key, value in options.items():
        if not db.hasName(PREFIX + key):
            db[PREFIX + key] = value


def _new_ksp(K: PETSc.Mat) -> PETSc.KSP:
    ksp = PETSc.KSP().create(K.getComm())
    ksp.setOptionsPrefix(PREFIX)
    ksp.setOperators(K)
    return ksp


def _norms(X: np.ndarray, comm) -> np.ndarray:
    """Euclidean norms of the columns of a row-distributed (owned rows, k) array."""
    return np.sqrt(comm.allreduce(np.einsum("ij,ij->j", X, X), op=MPI.SUM))


def _columns(M) -> np.ndarray:
    """A dense PETSc Mat's or a Vec's owned rows as a (rows, k) array view."""
    return M.getDenseArray(readonly=True) if isinstance(M, PETSc.Mat) else M.array_r[:, None]


def rigid_body_modes(coords: np.ndarray, comm) -> PETSc.NullSpace:
    """Translations and rotations at the owned DOF nodes (n, gdim): the near-nullspace
    that lets smoothed aggregation build elasticity's coarse spaces (PETSc's own
    MatNullSpaceCreateRigidBody: 3 modes in 2D, 6 in 3D)."""
    flat = np.ascontiguousarray(coords, dtype=PETSc.ScalarType).ravel()
    x = PETSc.Vec().createWithArray(flat, bsize=coords.shape[1], comm=comm)
    modes = PETSc.NullSpace().createRigidBody(x)
    x.destroy()
    return modes


def check_finite(X, what: str, comm, hint: str = "the solver failed without saying so; try the other "
                 "[solver] method (\"direct\" or \"iterative\")") -> np.ndarray:
    """Column norms of X; a SolverError if any entry is NaN or Inf (the same on every rank)."""
    norms = _norms(_columns(X), comm)
    if not np.all(np.isfinite(norms)):
        raise SolverError(f"{what} is not finite (NaN or Inf): {hint}")
    return norms


# --------------------------------------------------------------------------- MUMPS diagnosis

_BAD_INPUT = "a load, a prescribed displacement or a material value is NaN or Inf"
_SINGULAR = (-10, -6)
_ALLOCATION = (-13, -5, -7, -22)
_WORKSPACE = (-8, -9, -11, -12, -14, -15, -17, -20)


def mumps_failure(infog1: int, infog2: int, dofs: int) -> SolverError:
    """The one-line error for a MUMPS failure code INFOG(1) < 0 (MUMPS users' guide)."""
    where = f"MUMPS failed factorizing K ({dofs} DOFs; INFOG(1) = {infog1}, INFOG(2) = {infog2})"
    if infog1 in _SINGULAR:
        cause = "K is singular: the body can still move rigidly; clamp a group that holds it ([boundary] fixed)"
    elif infog1 in _ALLOCATION:
        cause = ("out of memory: use [solver] method = \"iterative\", or blr = 1e-8 (compressed factors), "
                 "or more MPI ranks (more machines)")
    elif infog1 in _WORKSPACE:
        cause = ("its workspace estimate was too small: raise it with PETSC_OPTIONS=\"-elasto_mat_mumps_icntl_14 200\" "
                 "(percent), or use [solver] method = \"iterative\"")
    elif infog1 == -19:
        cause = ("it needs more memory than ICNTL(23) allows: raise -elasto_mat_mumps_icntl_23, use "
                 "[solver] method = \"iterative\" or blr = 1e-8")
    else:
        cause = "see the MUMPS users' guide for this code; [solver] method = \"iterative\" avoids the factorization"
    return SolverError(f"{where}: {cause}")


def mumps_analysis(K: PETSc.Mat, factor: str = "lu", set_up: Callable = PETSc.KSP.setUp) -> dict:
    """MUMPS's analysis of K alone, no numeric phase: a throwaway KSP with a 1 MB
    workspace cap, so the factorization stops at once (INFOG(1) = -19). Its estimates:
    in-core factorization memory in MB (10^6 bytes) on the busiest rank, INFOG(16), and
    over all ranks, INFOG(17); flops, RINFOG(1); and INFOG(1) itself. ``set_up``: how
    the KSP is set up (``_SetUpAside`` does it without the GIL)."""
    ksp = _new_ksp(K)
    _use_mumps(ksp, factor, 0.0, K.getSize()[0])  # the exact factors' memory: an upper bound with compression
    F = ksp.getPC().getFactorMatrix()
    F.setMumpsIcntl(23, 1)
    set_up(ksp)
    out = {"busiest MB": F.getMumpsInfog(16), "total MB": F.getMumpsInfog(17), "flops": F.getMumpsRinfog(1),
           "infog1": F.getMumpsInfog(1)}
    ksp.destroy()
    return out


def factor_memory(K: PETSc.Mat, factor: str, set_up: Callable = PETSc.KSP.setUp) -> float:
    """Bytes MUMPS's analysis of K says its in-core factorization needs on the busiest
    node: the busiest rank's estimate times the ranks sharing its node, capped by the
    total."""
    analysis = mumps_analysis(K, factor, set_up)
    busiest, total = analysis["busiest MB"], analysis["total MB"]
    node = K.getComm().tompi4py().Split_type(MPI.COMM_TYPE_SHARED)
    ranks_here = node.Get_size()
    node.Free()
    return 1e6 * min(busiest * ranks_here, total)


def check_factor_fits(K: PETSc.Mat, factor: str, dofs: int, need: float | None = None,
                      set_up: Callable = PETSc.KSP.setUp) -> float:
    """A SolverError, the same on every rank, if the factors would not fit in the memory
    available now; else the bytes they need (``need``: known already, from the analysis
    of a matrix with K's pattern, which is all it depends on; ``set_up``: mumps_analysis's)."""
    comm = K.getComm().tompi4py()
    need = factor_memory(K, factor, set_up) if need is None else need
    have = available_memory()
    if comm.allreduce(need > MEMORY_SHARE * have, op=MPI.LOR):
        need, have = comm.allreduce(need, op=MPI.MAX), comm.allreduce(have, op=MPI.MIN)
        raise SolverError(f"the direct factorization of K ({dofs:,} DOFs) needs ~{need / 1e9:.3g} GB "
                          f"(MUMPS's analysis), over {MEMORY_SHARE:.0%} of the {have / 1e9:.3g} GB this machine "
                          f"has available: "
                          f"use [solver] method = \"iterative\" (or \"auto\"), or more machines")
    return need


def _check_factor(pc: PETSc.PC, dofs: int) -> None:
    F = pc.getFactorMatrix()
    infog1 = F.getMumpsInfog(1)  # global: the same on every rank
    if infog1 < 0:
        raise mumps_failure(infog1, F.getMumpsInfog(2), dofs)
    if pc.getFailedReason() != 0:
        raise SolverError(f"the factorization of K ({dofs} DOFs) failed (PETSc PC failed reason "
                          f"{pc.getFailedReason()}); try [solver] method = \"iterative\"")


# --------------------------------------------------------------------------- solvers


class LinearSolver:
    """K x = b for one K (owned: refilled in place by the model, then ``refresh``)."""

    def __init__(self, K: PETSc.Mat, clamped: np.ndarray, settings: SolverSettings, stats: SolverStats):
        self.K, self.clamped, self.settings, self.stats = K, clamped, settings, stats
        self.comm = K.getComm().tompi4py()
        self.dofs = K.getSize()[0]
        self.ksp = _new_ksp(K)

    def refresh(self) -> None:
        """K's values changed (same pattern): redo the numeric part only."""
        self.ksp.setOperators(self.K)
        self._setup()

    def ready(self) -> None:
        """Wait for a factorization started ahead (DirectSolver): what follows is timed alone."""

    def _setup(self) -> None:
        raise NotImplementedError

    def solve(self, b: PETSc.Vec, x: PETSc.Vec) -> None:
        raise NotImplementedError

    def solve_many(self, B: PETSc.Mat, X: PETSc.Mat) -> None:
        """A dense block of right-hand sides (owned rows, k columns) at once."""
        raise NotImplementedError

    @contextmanager
    def loosened(self, rtol: float) -> Iterator[LinearSolver]:
        """This solver with its solves in the ``with`` block to ``rtol`` where that is
        looser than the settings' (refinement steps or CG iterations saved where the
        caller needs fewer digits)."""
        settings = self.settings
        self.settings = replace(settings, rtol=max(rtol, settings.rtol))
        self.ksp.setTolerances(rtol=self.settings.rtol)  # CG's; a direct KSP (preonly) ignores it
        try:
            yield self
        finally:
            self.settings = settings
            self.ksp.setTolerances(rtol=settings.rtol)

    def destroy(self) -> None:
        self.ksp.destroy()
        self.K.destroy()


def _use_mumps(ksp: PETSc.KSP, factor: str, blr: float, dofs: int) -> None:
    """The KSP a direct solve of its operator by MUMPS, with this factor ("lu" or
    "cholesky") and block low-rank tolerance (0: off); a user's
    -elasto_mat_mumps_icntl_27 still wins."""
    ksp.setType("preonly")
    pc = ksp.getPC()
    pc.setType(factor)
    pc.setFactorSolverType("mumps")
    if factor == "cholesky":
        ksp.getOperators()[0].setOption(PETSc.Mat.Option.SPD, True)
    ksp.setFromOptions()
    pc.setFactorSetUpSolverType()
    F = pc.getFactorMatrix()
    F.setMumpsIcntl(27, -rhs_blocking(dofs))
    if blr > 0:
        F.setMumpsIcntl(35, 2)  # block low-rank in factorization and solve
        F.setMumpsCntl(7, blr)  # dropping tolerance of the low-rank blocks


class DirectSolver(LinearSolver):
    """MUMPS LU or Cholesky; analysis kept across refreshes; solutions refined to rtol.
    Above MEMORY_CHECK_DOFS the factors must fit the memory available first
    (``factor_need``: their size from an earlier analysis of this pattern, if known).
    ``few_solves``: the factors serve few solves, so [solver] blr = "auto" may compress
    them (SolverSettings.blr_for)."""

    def __init__(self, K, clamped, settings, stats, factor_need: float | None = None, ahead: bool = False,
                 few_solves: bool = False):
        super().__init__(K, clamped, settings, stats)
        self.blr = stats.blr = settings.blr_for(self.dofs, few_solves)
        _use_mumps(self.ksp, settings.factor, self.blr, self.dofs)
        self._analysed = False
        self._pending: _SetUpAside | None = None  # the memory check and factorization under way (``ahead``)
        self.factor_need = factor_need
        if ahead and _releases_the_gil(self.comm):  # its first use waits for it (_settle)
            self._pending = _SetUpAside(self.ksp, self._check_fits)
        else:
            self._check_fits()
            self._setup()

    def _check_fits(self, set_up: Callable = PETSc.KSP.setUp) -> None:
        """Above MEMORY_CHECK_DOFS, a SolverError if the factors would not fit (check_factor_fits)."""
        if self.dofs > MEMORY_CHECK_DOFS:
            self.factor_need = check_factor_fits(self.K, self.settings.factor, self.dofs, self.factor_need, set_up)

    def _setup(self) -> None:
        start = time.perf_counter()
        self.ksp.setUp()
        self._factored(time.perf_counter() - start)

    def _factored(self, seconds: float) -> None:
        _check_factor(self.ksp.getPC(), self.dofs)
        self.seconds = seconds  # what another factorization would cost
        self.stats.analyses += not self._analysed
        self.stats.factorizations += 1
        self._analysed = True

    def _settle(self) -> None:
        """Wait for a factorization started ahead, and check it as ``_setup`` does."""
        if self._pending is None:
            return
        pending, self._pending = self._pending, None  # waited for once, whatever it raises
        code, seconds = pending.wait()
        if code != 0:
            self._setup()  # again through petsc4py: its exception carries PETSc's message
            return
        self._factored(seconds)

    def refresh(self) -> None:
        self._settle()
        super().refresh()

    def ready(self) -> None:
        self._settle()

    def destroy(self) -> None:
        self._settle()
        super().destroy()

    @property
    def factor(self) -> PETSc.Mat:
        self._settle()
        return self.ksp.getPC().getFactorMatrix()

    def solve(self, b, x):
        self.apply_factors(b, x)
        self._refine(b, x)

    def solve_many(self, B, X):
        self.apply_factors(B, X)
        self._refine(B, X)

    def apply_factors(self, B, X) -> None:
        """X = F^-1 B through the factors, unrefined (a Vec, or a dense block by
        MatMatSolve): the first step of ``solve``, and a preconditioner of K at a nearby
        material value."""
        self._settle()
        if isinstance(B, PETSc.Vec):
            self.ksp.solve(B, X)
            if self.ksp.getConvergedReason() < 0:
                _check_factor(self.ksp.getPC(), self.dofs)
                raise SolverError(f"the direct solve failed (KSP reason {self.ksp.getConvergedReason()})")
        else:
            self.factor.matSolve(B, X)

    def _refine(self, B, X) -> None:
        """Iterative refinement on the true K, X += F^-1 (B - K X), while every open column's
        residual at least halves per step; columns still above rtol then go through GMRES
        preconditioned by the factors (loose BLR factors). With exact factors, a
        refinement that stalls means a singular K."""
        scale = self.settings.rtol * check_finite(B, "the right-hand side", self.comm, _BAD_INPUT)
        self.stats.solves += _columns(B).shape[1]
        last = None
        for step in range(REFINEMENTS + 1):
            R = _residual(self.K, B, X)
            r = check_finite(R, "the direct solution's residual", self.comm)
            open_ = r > scale
            slow = last is not None and np.any(r[open_] > 0.5 * last[open_])
            if not open_.any() or slow or step == REFINEMENTS:
                break
            D = R.duplicate()
            self.apply_factors(R, D)
            X.axpy(1.0, D)
            for M in (D, R):
                M.destroy()
            self.stats.iterations += 1
            last = r
        R.destroy()
        if open_.any():
            relative = float(np.max(r / np.maximum(scale / self.settings.rtol, 1e-300)))
            if self.blr == 0:
                raise self._stalled(relative)
            self._gmres(B, X, np.flatnonzero(open_))
        check_finite(X, "the direct solution", self.comm)

    def _gmres(self, B, X, columns) -> None:
        """GMRES on K preconditioned by the (compressed) factors, from X, for these columns."""
        ksp = PETSc.KSP().create(self.K.getComm())
        ksp.setOperators(self.K)
        ksp.setPC(self.ksp.getPC())  # the same factors, not a new factorization
        ksp.setType("gmres")
        ksp.setPCSide(PETSc.PC.Side.RIGHT)  # its residual norm is the true ||b - K x||
        ksp.setTolerances(rtol=self.settings.rtol, max_it=200)
        ksp.setInitialGuessNonzero(True)
        try:
            for i in columns:
                b, x = (B, X) if isinstance(B, PETSc.Vec) else (B.getDenseColumnVec(i, "r"), X.getDenseColumnVec(i))
                ksp.solve(b, x)
                self.stats.iterations += ksp.getIterationNumber()
                if not isinstance(B, PETSc.Vec):
                    B.restoreDenseColumnVec(i, "r")
                    X.restoreDenseColumnVec(i)
                if ksp.getConvergedReason() < 0:
                    raise SolverError(
                        f"the direct solve with block low-rank factors stays above rtol {self.settings.rtol:g} "
                        f"(GMRES: {_reason_name(ksp.getConvergedReason())}): lower [solver] blr, or set it to 0")
        finally:
            ksp.destroy()

    def _stalled(self, residual: float) -> SolverError:
        where = (f"the direct solve's relative residual stays at {residual:.2g} > rtol {self.settings.rtol:g} "
                 f"after {REFINEMENTS} refinement steps")
        if residual < 1e-11:
            return SolverError(f"{where}: that rtol is below what double precision reaches here; raise [solver] rtol")
        return SolverError(f"{where}: K is (nearly) singular -- clamp a group that stops every rigid motion -- "
                           "or [solver] blr is too loose")


class _SetUpAside:
    """A KSP's set-up (its factorization) in a thread of its own, through PETSc's C
    library: ctypes lets go of the GIL, where petsc4py holds it throughout, so the caller
    goes on meanwhile. ``check(set_up)``: run first in the thread, its own KSP set up the
    same way (DirectSolver._check_fits: MUMPS's analysis alone, 0.7 s at the phantom's
    116k DOFs); where it raises, no factorization, and ``wait`` raises the same. The
    thread is not a daemon: a process that ends meanwhile waits for it before PETSc is
    finalized."""

    def __init__(self, ksp: PETSc.KSP, check: Callable[[Callable], None]):
        library = _petsc_library()
        assert library is not None  # _releases_the_gil found it
        start = time.perf_counter()
        self.code, self.seconds = 1, 0.0  # an error until the set-up says otherwise
        self.refused: Exception | None = None

        def set_up() -> None:
            try:
                check(lambda other: library.KSPSetUp(other.handle))
            except Exception as error:  # noqa: BLE001 -- raised again in the caller's thread (wait)
                self.refused = error
                return
            self.code = library.KSPSetUp(ksp.handle)
            self.seconds = time.perf_counter() - start

        self._thread = threading.Thread(target=set_up, name="factorization")
        self._thread.start()

    def is_alive(self) -> bool:
        return self._thread.is_alive()

    def wait(self) -> tuple[int, float]:
        """(PETSc's error code, the set-up's seconds), once it has ended; the check's
        exception where it refused."""
        self._thread.join()
        if self.refused is not None:
            raise self.refused
        return self.code, self.seconds


@functools.cache
def _petsc_library() -> ctypes.CDLL | None:
    """The PETSc library petsc4py runs on (loaded already: found by its soname), for the
    calls made without the GIL; None where it is not found."""
    major, minor, _ = PETSc.Sys.getVersion()
    try:
        library = ctypes.CDLL(f"libpetsc.so.{major}.{minor}")
    except OSError:
        return None
    library.KSPSetUp.argtypes = [ctypes.c_void_p]
    library.KSPSetUp.restype = ctypes.c_int
    return library


def _releases_the_gil(comm) -> bool:
    """Whether a factorization can run beside the caller: serial only (on several ranks
    MUMPS's collectives and the caller's would share PETSc's communicators across
    threads, and the ranks already use the cores), where MPI allows calls from two
    threads at once (MUMPS calls it even alone), with PETSc's library at hand."""
    return comm.size == 1 and MPI.Query_thread() == MPI.THREAD_MULTIPLE and _petsc_library() is not None


def rhs_blocking(dofs: int) -> int:
    """MUMPS's largest block of right-hand sides per pass over the factors (ICNTL(27)):
    its default, 32, passes over the factors eight times for the 241 columns of a
    rank-240 snapshot. At 116k DOFs, 241 columns took 3.9 s at 32 and 2.9-3.0 s at up to
    512 (81 columns: 1.5 -> 1.1 s), with the same peak memory (benchmarks/forward.py).
    Capped so that one block of the solution stays within RHS_BLOCK_BYTES."""
    return int(np.clip(RHS_BLOCK_BYTES // (8 * dofs), 32, 512))


def _residual(K: PETSc.Mat, B, X):
    """B - K X, for a Vec or a dense block."""
    if isinstance(B, PETSc.Vec):
        R = B.duplicate()
        K.mult(X, R)
        R.aypx(-1.0, B)
        return R
    R = K.matMult(X)  # both PETSc dense blocks: one product, no round trip through numpy
    R.scale(-1.0)
    R.axpy(1.0, B)
    return R


class IterativeSolver(LinearSolver):
    """CG + GAMG (rigid-body near-nullspace), warm-started; checked after every solve."""

    name = "CG + AMG"

    def __init__(self, K, clamped, settings, stats, modes: PETSc.NullSpace | None, warm: WarmStart):
        super().__init__(K, clamped, settings, stats)
        if modes is not None:
            K.setNearNullSpace(modes)
        self.warm = warm
        ksp = self.ksp
        ksp.setType("cg")
        ksp.setNormType(PETSc.KSP.NormType.UNPRECONDITIONED)  # rtol bounds ||b - K x|| / ||b||
        ksp.setTolerances(rtol=settings.rtol, max_it=MAX_ITERATIONS)
        ksp.setInitialGuessNonzero(True)
        self._precondition(ksp.getPC())
        ksp.setFromOptions()
        self._setup()

    def _precondition(self, pc: PETSc.PC) -> None:
        pc.setType("gamg")
        _set_defaults(GAMG_OPTIONS)

    def _setup(self) -> None:
        self.ksp.setUp()
        reason = self.ksp.getPC().getFailedReason()
        if reason != 0:
            raise SolverError(f"the AMG preconditioner of K ({self.dofs} DOFs) failed to set up (PETSc reason "
                              f"{reason}); try [solver] method = \"direct\"")
        self.stats.setups += 1

    def solve(self, b, x):
        check_finite(b, "the right-hand side", self.comm, _BAD_INPUT)
        x.array[:] = self.warm.guess(self.K, b.array[:, None])[:, 0]
        self._krylov(b, x)
        self.warm.remember(self.K, x.array[:, None], b.array[:, None])

    def solve_many(self, B, X):
        check_finite(B, "the right-hand side", self.comm, _BAD_INPUT)
        X.getDenseArray()[:] = self.warm.guess(self.K, B.getDenseArray())
        for i in range(B.getSize()[1]):
            b, x = B.getDenseColumnVec(i, "r"), X.getDenseColumnVec(i, "rw")
            try:
                self._krylov(b, x)
            finally:
                B.restoreDenseColumnVec(i, "r")
                X.restoreDenseColumnVec(i, "rw")
        self.warm.remember(self.K, X.getDenseArray(), B.getDenseArray())

    def _krylov(self, b, x) -> None:
        _krylov(self, b, x, self.name, ": use [solver] method = \"direct\", or a larger rtol")

    def converge_from_start(self, rtol: float) -> None:
        """Stop each solve once its residual is ``rtol`` of its start's, not of ||b||: for
        solves started from a close guess, whose correction is then found to ``rtol``
        whatever share of b it is (the start's own rtol would be that share times it)."""
        self.ksp.setConvergenceTest(_FromStart(rtol))


class TwoLevelSolver(IterativeSolver):
    """CG on K_h (a space one degree higher than the model's, same mesh) preconditioned by
    a two-level cycle whose coarse level is the model's own factorized K (``coarse``, a
    DirectSolver): SSOR on K_h, the residual restricted by I^T (I: the model's space
    interpolated into K_h's, V_p inside V_p+1), one back-solve with the factors,
    prolonged by I, SSOR again. Since V_p lies inside V_p+1, I^T K_h I is the model's own
    K wherever the materials and the quadrature agree: no coarse operator to form, no
    AMG hierarchy to set up (the demo's coarse phantom, P3 at the answer: 10 iterations,
    1.5 s, against GAMG's 33 iterations, 2.5 s + 2.5 s setup). The clamped DOFs of both
    levels are the same walls' nodes, so the correction is zero there."""

    name = "CG + a two-level cycle over the model's factors"

    def __init__(self, K, clamped, settings, stats, warm: WarmStart, coarse: DirectSolver,
                 interpolation: PETSc.Mat):
        self._cycle = _TwoLevel(K, interpolation, coarse)
        super().__init__(K, clamped, settings, stats, None, warm)

    def _precondition(self, pc: PETSc.PC) -> None:
        pc.setType(PETSc.PC.Type.PYTHON)
        pc.setPythonContext(self._cycle)


class _FromStart:
    """A KSP convergence test: converged once the residual is ``rtol`` of the first one
    (the KSP's own max_it still ends a solve that never gets there: DIVERGED_ITS)."""

    def __init__(self, rtol: float):
        self.rtol, self.first = rtol, 0.0

    def __call__(self, ksp: PETSc.KSP, its: int, rnorm: float) -> int:
        reason = PETSc.KSP.ConvergedReason
        if its == 0:
            self.first = rnorm
        if not np.isfinite(rnorm):
            return reason.DIVERGED_NANORINF
        if rnorm <= self.rtol * self.first:
            return reason.CONVERGED_RTOL if its else reason.CONVERGED_ATOL
        return reason.ITERATING


class _TwoLevel:
    """A PETSc python PC: one symmetric two-level cycle (TwoLevelSolver). It owns the
    interpolation matrix it is given; the coarse solver stays its cache's."""

    def __init__(self, K: PETSc.Mat, interpolation: PETSc.Mat, coarse: DirectSolver):
        self.K, self.I, self.coarse = K, interpolation, coarse
        self.smoother = PETSc.PC().create(K.getComm())
        self.smoother.setType("sor")  # PETSc's default sweep is symmetric: the cycle stays SPD
        self.smoother.setOperators(K)
        self.smoother.setUp()
        self.r, self.t = K.createVecs()
        self.rc, self.ec = coarse.K.createVecs()

    def apply(self, pc, x, y):
        self.smoother.apply(x, y)
        self._residual(x, y)
        self.I.multTranspose(self.r, self.rc)
        self.rc.array[self.coarse.clamped] = 0.0
        self.coarse.apply_factors(self.rc, self.ec)
        self.ec.array[self.coarse.clamped] = 0.0
        self.I.multAdd(self.ec, y, y)
        self._residual(x, y)
        self.smoother.apply(self.r, self.t)
        y.axpy(1.0, self.t)

    def _residual(self, x, y) -> None:
        """r = x - K y."""
        self.K.mult(y, self.r)
        self.r.aypx(-1.0, x)

    def destroy(self, pc) -> None:
        """PETSc's call when the PC goes: free the cycle's own objects with it."""
        for obj in (self.smoother, self.I, self.r, self.t, self.rc, self.ec):
            obj.destroy()


class NearbySolver(LinearSolver):
    """K(c) x = b by CG preconditioned with the factors of K(c0) (a DirectSolver of the
    same clamped set): no factorization. K(c) and K(c0) are sums of the same positive
    semidefinite material matrices, so the preconditioned spectrum lies within
    [min c/c0, max c/c0] and CG needs at most ~sqrt(ratio) log(2 / rtol) steps -- far
    fewer when one region changes, most of the spectrum then sitting at 1 (the demo's
    55k-DOF target mesh, from the factors at prostate E 50: E 25 in 7 steps, 0.87 s, E 75
    in 5, 0.66 s, each against a 4.9 s factorization; equal to fresh direct solves to
    1.3e-8). Owns K(c); the factors stay the other solver's."""

    def __init__(self, K, clamped, settings, stats, base: DirectSolver):
        super().__init__(K, clamped, settings, stats)
        ksp = self.ksp
        ksp.setType("cg")
        ksp.setNormType(PETSc.KSP.NormType.UNPRECONDITIONED)  # rtol bounds ||b - K x|| / ||b||
        ksp.setTolerances(rtol=settings.rtol, max_it=MAX_ITERATIONS)
        pc = ksp.getPC()
        pc.setType(PETSc.PC.Type.PYTHON)
        pc.setPythonContext(_FactorsOf(base))
        ksp.setUp()

    def solve(self, b, x):
        check_finite(b, "the right-hand side", self.comm, _BAD_INPUT)
        _krylov(self, b, x, "CG preconditioned by the factors of a nearby material value", "")

    def solve_many(self, B, X):
        """Column by column (a few columns: a response to one more mode, a derivative per
        constant; big blocks borrow through the surrogate's refinement instead)."""
        b, x = self.K.createVecs()
        for j in range(B.getSize()[1]):
            b.array[:] = B.getDenseArray()[:, j]
            self.solve(b, x)
            X.getDenseArray()[:, j] = x.array_r
        b.destroy()
        x.destroy()


def _krylov(solver: LinearSolver, b, x, name: str, remedy: str) -> None:
    """One CG solve of ``solver`` (IterativeSolver, NearbySolver), counted and checked:
    a SolverError naming ``name`` (and ``remedy``) unless it converged to rtol."""
    ksp = solver.ksp
    ksp.solve(b, x)
    reason, its = ksp.getConvergedReason(), ksp.getIterationNumber()
    solver.stats.solves += 1
    solver.stats.iterations += its
    if reason < 0:
        raise SolverError(
            f"{name} stopped after {its} iterations at relative residual "
            f"{ksp.getResidualNorm() / max(b.norm(), 1e-300):.2g} (rtol {solver.settings.rtol:g}, "
            f"PETSc reason {_reason_name(reason)}){remedy}")
    x.array[solver.clamped] = b.array_r[solver.clamped]  # identity rows: exact, not to rtol
    check_finite(x, "the iterative solution", solver.comm)


class _FactorsOf:
    """A PETSc python PC: y = F^-1 x through another solver's factors."""

    def __init__(self, solver: DirectSolver):
        self.solver = solver

    def apply(self, pc, x, y):
        self.solver.apply_factors(x, y)


def _reason_name(reason: int) -> str:
    names = {v: k for k, v in vars(PETSc.KSP.ConvergedReason).items() if isinstance(v, int)}
    return names.get(reason, str(reason))


def coefficient_spread(c, c0) -> float | None:
    """The spread max(c / c0) / min(c / c0) of two material coefficient vectors, which
    bounds the condition number of K(c) preconditioned by the factors of K(c0); None
    where a coefficient is zero in one and not in the other."""
    c, c0 = np.asarray(c, float), np.asarray(c0, float)
    if np.any((c0 > 0) != (c > 0)):
        return None
    ratio = c[c > 0] / c0[c0 > 0]
    return float(ratio.max() / ratio.min()) if len(ratio) else 1.0


class SolverCache:
    """Ready solvers of K(c) per (c, clamped set), the ``size`` most recently used.

    Two by default: alternating material values (a line search, a finite difference)
    do not refactor. On a miss with a full cache, the least recently used solver of the
    same clamped set is refilled in place (``stiffness(c, clamped, out=K)``: same
    pattern) and refreshed -- MUMPS keeps its analysis, GAMG its interpolation --
    instead of being destroyed and rebuilt from scratch.
    """

    def __init__(self, settings: SolverSettings, stats: SolverStats, stiffness: Callable,
                 near_nullspace: Callable, size: int = 2, at_once: Callable | None = None, few_solves: bool = False):
        self.settings, self.stats, self.size = settings, stats, size
        self.few_solves = few_solves  # each factorization serves few solves (DirectSolver)
        self.stiffness = stiffness  # (c, clamped, out=None) -> K with identity rows on clamped
        self.at_once = at_once or stiffness  # (c, clamped) -> the same K, the quickest way from nothing (``ahead``)
        self.near_nullspace = near_nullspace  # () -> PETSc.NullSpace, built on first need
        self._modes = None
        self._solvers: OrderedDict = OrderedDict()
        self._warm: dict = {}  # clamped set -> WarmStart, shared by its iterative solvers
        self._factor_need: dict = {}  # clamped set -> bytes its direct factors need (one analysis each)

    @staticmethod
    def _key(c, clamped: np.ndarray) -> tuple:
        return tuple(np.round(np.asarray(c, float), 12)), clamped.tobytes()

    def get(self, c, clamped: np.ndarray) -> LinearSolver:
        key = self._key(c, clamped)
        if key in self._solvers:
            self._solvers.move_to_end(key)
            return self._solvers[key]
        full = len(self._solvers) >= self.size
        same = next((k for k in self._solvers if k[1] == key[1]), None) if full else None
        if same is not None:
            solver = self._solvers.pop(same)
            self.stiffness(c, clamped, out=solver.K)
            solver.refresh()
        else:
            while len(self._solvers) >= self.size:
                self._solvers.popitem(last=False)[1].destroy()
            solver = self._new(self.stiffness(c, clamped), clamped)
        self._solvers[key] = solver
        return solver

    def ahead(self, c, clamped: np.ndarray) -> None:
        """Start the factorization of K(c) now, to run beside whatever the caller does
        before its first solve (DirectSolver ``ahead``); nothing with the iterative
        method, or where K(c) is cached or the cache is full."""
        key = self._key(c, clamped)
        if self.stats.method == "direct" and key not in self._solvers and len(self._solvers) < self.size:
            self._solvers[key] = self._new(self.at_once(c, clamped), clamped, ahead=True)

    def nearby(self, c, clamped: np.ndarray, rtol: float | None = None) -> NearbySolver | None:
        """A NearbySolver for K(c) on the factors ``closest`` finds (to ``rtol`` if given,
        else the settings'); None if there are none. The caller destroys it after use: it
        is not cached, so it never outlives the factors it borrows."""
        base = self.closest(c, clamped)
        if base is None:
            return None
        settings = self.settings if rtol is None else replace(self.settings, rtol=rtol)
        return NearbySolver(self.stiffness(c, clamped), clamped, settings, self.stats, base)

    def factors_near(self, c, clamped: np.ndarray) -> DirectSolver | None:
        """The cached direct solver of K(c) itself, else ``closest``'s; None if neither."""
        solver = self._solvers.get(self._key(c, clamped))
        return solver if isinstance(solver, DirectSolver) else self.closest(c, clamped)

    def closest(self, c, clamped: np.ndarray) -> DirectSolver | None:
        """The cached direct solver of the same clamped set whose coefficients c0 differ
        from c by the least spread of c / c0 (which bounds the condition number of K(c)
        preconditioned by its factors), if at most NEARBY_RATIO; None if there is none,
        or if K(c) itself is cached."""
        c = np.asarray(c, float)
        key = self._key(c, clamped)
        if key in self._solvers or self.stats.method != "direct":
            return None
        best = None
        for (c0, pattern), solver in self._solvers.items():
            spread = coefficient_spread(c, c0)
            if pattern != key[1] or spread is None:
                continue
            if spread <= NEARBY_RATIO and (best is None or spread < best[0]):
                best = (spread, solver)
        return None if best is None else best[1]

    def _new(self, K: PETSc.Mat, clamped: np.ndarray, ahead: bool = False) -> LinearSolver:
        if self.stats.method == "direct":
            solver = DirectSolver(K, clamped, self.settings, self.stats, self._known_need(clamped), ahead,
                                  self.few_solves)
            self._factor_need[clamped.tobytes()] = solver.factor_need  # None while an ``ahead`` check runs
            return solver
        if self._modes is None:
            self._modes = self.near_nullspace()
        warm = self._warm.setdefault(clamped.tobytes(), WarmStart(K.getComm().tompi4py()))
        return IterativeSolver(K, clamped, self.settings, self.stats, self._modes, warm)

    def _known_need(self, clamped: np.ndarray) -> float | None:
        """The bytes the factors of K with this clamped set need, where an analysis said
        so already (kept, or in a cached solver whose check ran beside its caller)."""
        pattern = clamped.tobytes()
        needs = [self._factor_need.get(pattern)] + [solver.factor_need for (_, p), solver in self._solvers.items()
                                                    if p == pattern and isinstance(solver, DirectSolver)]
        return next((need for need in needs if need is not None), None)

    @contextmanager
    def one_at_a_time(self) -> Iterator[None]:
        """Material values solved one after another, never again (training's levels): each
        refills the previous one's solver instead of building a second. On the default
        phantom (116k DOFs) a refill took 16-17 s and a second solver's first
        factorization 27-28 s (MUMPS allocating its factors anew). A solver made here
        serves few solves (``few_solves``)."""
        size, few, self.size, self.few_solves = self.size, self.few_solves, 1, True
        try:
            yield
        finally:
            self.size, self.few_solves = size, few

    def __iter__(self):
        return iter(self._solvers.values())


class WarmStart:
    """CG initial guesses: the Galerkin projection of K x = b onto recent solutions.

    x0 = S a with (S^T K S) a = S^T b minimises the energy-norm error over span(S), so it is
    never worse than x0 = 0, for any right-hand side. S keeps the latest solutions of one
    clamped set across material values: the fields at the previous theta are close to the
    new ones, and the previous block of mode responses spans the new block well (the idea
    of surrogate.py, here only to start CG). K S is carried along (K x = b up to rtol) and
    recomputed when K changes.
    """

    def __init__(self, comm):
        self.comm = comm
        self.S: np.ndarray | None = None  # (owned rows, m)
        self.KS: np.ndarray | None = None
        self.state = None  # K's identity and state that KS belongs to
        self.capacity = WARM_COLUMNS[0]

    def guess(self, K: PETSc.Mat, B: np.ndarray) -> np.ndarray:
        if self.S is None:
            return np.zeros_like(B)
        if self.KS is None or self.state != _state(K):
            self.KS, self.state = times_block(K, self.S), _state(K)
        G = self.comm.allreduce(self.S.T @ self.KS, op=MPI.SUM)
        lam, V = np.linalg.eigh(0.5 * (G + G.T))
        keep = lam > 1e-12 * max(lam.max(), 0.0)
        if not keep.any():
            return np.zeros_like(B)
        V = V[:, keep]
        a = V @ ((V.T @ self.comm.allreduce(self.S.T @ B, op=MPI.SUM)) / lam[keep, None])
        return self.S @ a

    def seed(self, X: np.ndarray) -> None:
        """Guesses from span(X) (owned rows), whose K X is not known: e.g. a lower-degree
        solution interpolated, which leaves CG only the correction to find."""
        self.S, self.KS, self.state = np.array(X, float), None, None

    def remember(self, K: PETSc.Mat, X: np.ndarray, B: np.ndarray) -> None:
        """Keep the solutions X of K X = B (newest first, up to ``capacity`` columns)."""
        self.capacity = min(max(self.capacity, X.shape[1]), WARM_COLUMNS[1])
        current = self.KS is not None and self.state == _state(K)
        S = X if self.S is None else np.hstack([X, self.S])
        KS = B if self.KS is None or self.S is None else np.hstack([B, self.KS]) if current else None
        self.S = S[:, : self.capacity].copy()
        self.KS = None if KS is None else KS[:, : self.capacity].copy()
        self.state = None if KS is None else _state(K)


def _state(K: PETSc.Mat) -> tuple:
    """Which matrix, and which values: PETSc bumps the state whenever K changes."""
    return (K.handle, K.stateGet())


