"""Linear solvers (solvers.py): iterative = direct to the tolerance, analysis reuse =
a fresh factorization, BLR refined to exact, warm starts that save iterations, and
failures that end in one line instead of a silently wrong (or infinite) field."""

import json

import numpy as np
import pytest
from petsc4py import PETSc

from conftest import TESTS, run_cli, run_mpi_script
from targets import letter_case
from fenics_elasto.model.elasticity import ElasticModel
from fenics_elasto.model.loads import boundary_load
from fenics_elasto.model.forward import BoundaryForward
from fenics_elasto.model.scene import load_scene
from fenics_elasto.model.simulate import material_values, simulate
from fenics_elasto.model import solvers
from fenics_elasto.model.solvers import (AUTO_BLR, AUTO_BLR_DOFS, DIRECT_LIMIT, DirectSolver, SolverError,
                                         SolverSettings, SolverStats, rhs_blocking)
from fenics_elasto.model.responses import response_block

MPI_SCRIPT = TESTS / "mpi" / "solvers.py"


@pytest.fixture(scope="module")
def phantom_p1(scenes):
    """The 3D phantom at P1 (~5k DOFs): quick, and every solver path is the same as at P2."""
    return load_scene(scenes["prostate-phantom"], ["degree=1"])


@pytest.fixture(scope="module")
def cantilever(scenes):
    return load_scene(scenes["cantilever"])


def relative(a, b) -> float:
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


def forward_and_block(scene, settings: SolverSettings, columns: int = 3):
    """A forward solve from random forces and a block response of random boundary modes
    (its free rows)."""
    forward = BoundaryForward(scene, ElasticModel(scene, settings))
    rng = np.random.default_rng(1)
    theta = np.array([40.0])
    u = forward.from_forces(theta, rng.standard_normal(forward.force_dofs)).x.array.copy()
    X = response_block(forward, theta, rng.standard_normal((forward.force_dofs, columns)))
    free = np.ones(len(X), bool)
    free[forward.clamped_boundary] = False  # the clamped rows are the modes themselves
    return u, X[free], forward.model


def test_iterative_equals_direct_forward_and_block(phantom_p1):
    u_d, X_d, direct = forward_and_block(phantom_p1, SolverSettings(method="direct"))
    u_i, X_i, iterative = forward_and_block(phantom_p1, SolverSettings(method="iterative", rtol=1e-8))
    assert direct.method == "direct" and iterative.method == "iterative"
    assert iterative.factorizations == 0 and iterative.stats.setups == 2  # two clamped sets
    assert iterative.stats.iterations > 0 and direct.factorizations == 2
    assert relative(u_i, u_d) < 1e-6
    assert relative(X_i, X_d) < 1e-6


@pytest.mark.slow
def test_iterative_equals_direct_p2(scenes):
    """The 32k-DOF P2 phantom (what `auto` gives a real scene)."""
    scene = load_scene(scenes["prostate-phantom"])
    u_d, X_d, _ = forward_and_block(scene, SolverSettings(method="direct"), columns=2)
    u_i, X_i, _ = forward_and_block(scene, SolverSettings(method="iterative"), columns=2)
    assert relative(u_i, u_d) < 1e-6
    assert relative(X_i, X_d) < 1e-6


def _solve_at(model, scene, E, rhs):
    clamped = model.dofs.clamped_dofs(scene.fixed)
    _, nu = material_values(scene)
    return model.solve(model.stiffness.coefficients(E, nu), clamped, rhs.x.petsc_vec).x.array.copy()


def _load(model, seed=0):
    rhs = model.dofs.function("f")
    rhs.x.array[:] = np.random.default_rng(seed).standard_normal(len(rhs.x.array))
    return rhs


@pytest.mark.parametrize("factor", ["lu", "cholesky"])
def test_analysis_reuse_equals_fresh_factorization(cantilever, factor):
    settings = SolverSettings(method="direct", factor=factor)
    reused = ElasticModel(cantilever, settings, cache_size=1)
    rhs = _load(reused)
    _solve_at(reused, cantilever, np.array([500.0]), rhs)
    u = _solve_at(reused, cantilever, np.array([2000.0]), rhs)  # refilled K, numeric refactor only
    assert reused.stats.analyses == 1 and reused.factorizations == 2
    fresh = ElasticModel(cantilever, settings)
    assert relative(u, _solve_at(fresh, cantilever, np.array([2000.0]), rhs)) < 1e-12
    # the same answer as the stiffer material by scaling: u(E) = u(1) / E
    assert relative(2000.0 * u, 500.0 * _solve_at(reused, cantilever, np.array([500.0]), rhs)) < 1e-10


def test_cache_keeps_two_values_and_reuses_the_oldest(cantilever):
    model = ElasticModel(cantilever, SolverSettings(method="direct"))
    rhs = _load(model)
    for E in (500.0, 1000.0, 500.0, 1000.0):  # alternating: no refactorization
        _solve_at(model, cantilever, np.array([E]), rhs)
    assert model.factorizations == 2 and model.stats.analyses == 2
    _solve_at(model, cantilever, np.array([3000.0]), rhs)  # refills the least recently used
    assert model.factorizations == 3 and model.stats.analyses == 2


def test_values_one_at_a_time_refill_one_solver(cantilever):
    """Training's levels: each refills the previous one's factors (one analysis, one
    solver alive); afterwards the cache holds two again."""
    model = ElasticModel(cantilever, SolverSettings(method="direct"))
    rhs = _load(model)
    for E in (500.0, 1000.0, 3000.0):
        with model.solvers.one_at_a_time():
            _solve_at(model, cantilever, np.array([E]), rhs)
    assert model.factorizations == 3 and model.stats.analyses == 1 and len(list(model.solvers)) == 1
    _solve_at(model, cantilever, np.array([500.0]), rhs)
    assert model.stats.analyses == 2 and len(list(model.solvers)) == 2


def test_a_nearby_material_value_borrows_the_factors(phantom_p1):
    """A single solve at a new material value within NEARBY_RATIO of a factorized one
    (simulate's) runs CG on the factors already made -- no factorization -- and equals a
    fresh direct solve to rtol; a value beyond that ratio factorizes."""
    model = ElasticModel(phantom_p1, SolverSettings(method="direct"))
    clamped = model.dofs.clamped_dofs(phantom_p1.fixed)
    load = _load(model)  # kept alive: its petsc_vec borrows the Function's memory
    E, nu = material_values(phantom_p1)

    def solve(m, scale, nearby=True):
        c = m.stiffness.coefficients(E * np.r_[scale, np.ones(len(E) - 1)], nu)
        return m.solve(c, clamped, load.x.petsc_vec, nearby=nearby)

    solve(model, 1.0)
    assert model.factorizations == 1
    near = solve(model, 2.5).x.array.copy()
    assert model.factorizations == 1 and model.stats.iterations > 0
    fresh = ElasticModel(phantom_p1, SolverSettings(method="direct"))
    exact = solve(fresh, 2.5, nearby=False).x.array
    assert relative(near, exact) < 1e-7
    # a looser rtol (a diagnostic's) stops CG earlier, still near the answer
    steps = model.stats.iterations
    c = model.stiffness.coefficients(E * np.r_[2.5, np.ones(len(E) - 1)], nu)
    loose, b = model.dofs.function(), load.x.petsc_vec.copy()
    b.array[clamped] = 0.0  # as ElasticModel.solve's
    with model.solver(c, clamped, nearby=True, rtol=1e-4) as borrowed:
        borrowed.solve(b, loose.x.petsc_vec)
    assert model.stats.iterations - steps < steps and model.factorizations == 1
    assert 1e-9 < relative(loose.x.array, exact) < 1e-3
    solve(model, 10.0)  # outside NEARBY_RATIO of the factors at 1.0
    assert model.factorizations == 2


@pytest.mark.slow
def test_blr_is_refined_to_the_tolerance(scenes):
    """P2 phantom (BLR compresses nothing below ~10k DOFs): factors compressed at 1e-3
    solve to ~1e-1 alone; refinement, then GMRES on them, reach the uncompressed answer."""
    scene = load_scene(scenes["prostate-phantom"])
    E = material_values(scene)[0]
    exact = ElasticModel(scene, SolverSettings(method="direct"))
    rhs = _load(exact)
    u = _solve_at(exact, scene, E, rhs)
    compressed = ElasticModel(scene, SolverSettings(method="direct", blr=1e-3, rtol=1e-10))
    u_blr = _solve_at(compressed, scene, E, rhs)
    solver = next(iter(compressed.solvers))
    assert solver.factor.getMumpsInfog(35) < solver.factor.getMumpsInfog(29)  # it did compress
    assert compressed.stats.iterations >= 1  # the compressed factor alone is not enough...
    assert relative(u_blr, u) < 1e-8  # ...the refined answer is
    # loosened (as training's examples are): fewer refinement steps, the residual within the looser rtol
    tight = compressed.stats.iterations
    with solver.loosened(1e-4) as loose:
        assert loose.settings.rtol == 1e-4
        u_loose = _solve_at(compressed, scene, E, rhs)  # the same factors, the same load
    assert compressed.stats.iterations - tight < tight
    assert solver.settings.rtol == 1e-10  # restored after the block
    assert 1e-10 < relative(u_loose, u) < 1e-2  # the field to within ~10x its residual (1.0e-3 here)


def test_warm_start_saves_iterations(phantom_p1):
    """CG starts from the Galerkin projection onto the last solutions (a pressure load)."""
    model = ElasticModel(phantom_p1, SolverSettings(method="iterative"))
    clamped = model.dofs.clamped_dofs(phantom_p1.fixed)
    E, nu = material_values(phantom_p1)
    load = boundary_load(model.dofs, {}, {"bladder": 1.0})
    model.solve(model.stiffness.coefficients(E, nu), clamped, load)
    cold = model.stats.iterations
    model.solve(model.stiffness.coefficients(2 * E, nu), clamped, load)  # every E doubled: u / 2, in the span
    assert model.stats.iterations == cold
    stiffer = E * np.where([m.name == "prostate" for m in phantom_p1.materials], 1.01, 1.0)
    u = model.solve(model.stiffness.coefficients(stiffer, nu), clamped, load).x.array  # 1 % off the last one
    warm = model.stats.iterations - cold
    assert 0 < warm <= 0.75 * cold
    fresh = ElasticModel(phantom_p1, SolverSettings(method="iterative"))
    assert relative(u, fresh.solve(fresh.stiffness.coefficients(stiffer, nu), clamped, load).x.array) < 1e-6
    assert fresh.stats.iterations >= cold - 1  # the same kind of system from scratch


def test_auto_blr_compresses_only_factors_that_serve_few_solves(cantilever, monkeypatch):
    """blr = "auto" (the default): block low-rank factors from AUTO_BLR_DOFS up where a
    factorization serves few solves -- a simulation's model, training's material levels --
    and exact factors for the rest (an estimate's, which serve hundreds of solves)."""
    auto = SolverSettings(method="direct")
    assert auto.blr_for(AUTO_BLR_DOFS, few_solves=True) == AUTO_BLR
    assert auto.blr_for(AUTO_BLR_DOFS - 1, few_solves=True) == 0.0
    assert auto.blr_for(10 * AUTO_BLR_DOFS, few_solves=False) == 0.0
    assert SolverSettings(blr=0.0).blr_for(10 * AUTO_BLR_DOFS, few_solves=True) == 0.0
    assert SolverSettings(blr=1e-8).blr_for(10, few_solves=False) == 1e-8
    monkeypatch.setattr(solvers, "AUTO_BLR_DOFS", 0)  # the cantilever's few DOFs: the rule, not the gain
    E, nu = material_values(cantilever)

    def compression(model: ElasticModel) -> float:
        clamped = model.dofs.clamped_dofs(cantilever.fixed)
        F = model.factorize(model.stiffness.coefficients(E, nu), clamped).factor
        assert model.stats.as_dict()["blr"] == (F.getMumpsCntl(7) if F.getMumpsIcntl(35) else 0.0)  # result.json's
        return model.stats.blr

    assert compression(ElasticModel(cantilever, auto, fixed=(E, nu))) == AUTO_BLR  # a simulation
    assert compression(ElasticModel(cantilever, auto)) == 0.0  # an estimate
    training = ElasticModel(cantilever, auto)
    with training.solvers.one_at_a_time():
        assert compression(training) == AUTO_BLR


def test_auto_switches_by_size():
    assert SolverSettings().method_for(DIRECT_LIMIT) == "direct"
    assert SolverSettings().method_for(DIRECT_LIMIT + 1) == "iterative"
    assert SolverSettings(method="direct").method_for(10 * DIRECT_LIMIT) == "direct"


def test_cli_simulate_iterative(scenes, tmp_path):
    proc = run_cli("simulate", scenes["cantilever"], "--out", tmp_path / "out", "--set", "solver.method='iterative'")
    assert proc.returncode == 0, proc.stderr
    result = json.loads((tmp_path / "out" / "result.json").read_text())
    assert result["solver"]["method"] == "iterative" and result["solver"]["iterations"] > 0
    assert result["factorizations"] == 0
    scene = load_scene(scenes["cantilever"], command="simulate")
    direct = simulate(scene, ElasticModel(scene, SolverSettings(method="direct")))
    assert direct.result["solver"]["factorizations"] == 1
    assert result["max_displacement"] == pytest.approx(direct.result["max_displacement"], rel=1e-7)


@pytest.mark.slow
def test_estimate_iterative_equals_direct(tmp_path):
    """The whole nested estimate (letter A, nu) through either solver: the same nu."""
    source, target = letter_case(tmp_path, 0.25, 0.25)
    nu = {}
    for method in ("direct", "iterative"):
        proc = run_cli("estimate", source, "--out", tmp_path / method, "--set", f"target.surface='{target}'",
                       "--set", f"solver.method='{method}'")
        assert proc.returncode == 0, proc.stderr[-2000:]
        result = json.loads((tmp_path / method / "result.json").read_text())
        assert (result["factorizations"] > 0) == (method == "direct")
        nu[method] = result["materials"]["letter"]["nu"]
    assert abs(nu["iterative"] - nu["direct"]) < 1e-6
    assert abs(nu["direct"] - 0.25) < 0.01


# --------------------------------------------------------------------------- failures


def test_singular_stiffness_is_refused(cantilever):
    """Nothing clamped: MUMPS 'succeeds' on the singular K; the residual check does not."""
    model = ElasticModel(cantilever, SolverSettings(method="direct"))
    rhs = _load(model)
    _, nu = material_values(cantilever)
    with pytest.raises(SolverError, match="singular"):
        model.solve(model.stiffness.coefficients([1000.0], nu), np.zeros(0, np.int32), rhs.x.petsc_vec)


def test_nan_load_is_refused(cantilever):
    for method in ("direct", "iterative"):
        model = ElasticModel(cantilever, SolverSettings(method=method))
        rhs = _load(model)
        rhs.x.array[np.setdiff1d(np.arange(10), model.dofs.clamped_dofs(cantilever.fixed))[0]] = np.nan
        with pytest.raises(SolverError, match="right-hand side is not finite"):
            _solve_at(model, cantilever, np.array([1000.0]), rhs)


@pytest.fixture
def petsc_option():
    """Set a PETSc option for one test (as PETSC_OPTIONS would), then remove it."""
    set_here = []

    def put(name, value):
        PETSc.Options()[name] = value
        set_here.append(name)

    yield put
    for name in set_here:
        PETSc.Options().delValue(name)


def test_mumps_failure_is_an_error(cantilever, petsc_option):
    petsc_option("elasto_mat_mumps_icntl_23", 1)  # MUMPS may use 1 MB: it fails with INFOG(1) = -19
    model = ElasticModel(cantilever, SolverSettings(method="direct"))
    with pytest.raises(SolverError, match=r"INFOG\(1\) = -19.*ICNTL\(23\)"):
        _solve_at(model, cantilever, np.array([1000.0]), _load(model))


def test_factors_too_big_for_the_machine_are_refused_before_factorizing(cantilever, monkeypatch):
    """MUMPS's analysis first: its memory estimate against what the machine has (the
    OOM killer otherwise ends a too-big factorization without a word)."""
    import fenics_elasto.model.solvers as solvers

    model = ElasticModel(cantilever, SolverSettings(method="direct"))
    _, nu = material_values(cantilever)
    K = model.stiffness.constrained(model.stiffness.coefficients([1000.0], nu), model.dofs.clamped_dofs(cantilever.fixed))
    need = solvers.factor_memory(K, "lu")
    assert 1e5 < need < 1e9  # a few thousand DOFs: MBs, not GBs
    monkeypatch.setattr(solvers, "MEMORY_CHECK_DOFS", 0)
    _solve_at(model, cantilever, np.array([1000.0]), _load(model))  # fits: solved
    assert model.factorizations == 1
    # A second solver of the same clamped set: its pattern's need is known, so it is checked
    # against the memory available now (the first's factors take some) without a new analysis.
    analyses = []
    monkeypatch.setattr(solvers, "factor_memory", lambda *args: analyses.append(1) or need)
    monkeypatch.setattr(solvers, "available_memory", lambda: 0.5 * need)
    with pytest.raises(SolverError, match="needs ~"):
        _solve_at(model, cantilever, np.array([2000.0]), _load(model))
    monkeypatch.setattr(solvers, "available_memory", lambda: 2.0 * need)
    _solve_at(model, cantilever, np.array([2000.0]), _load(model))
    assert model.factorizations == 2 and analyses == []
    monkeypatch.setattr(solvers, "available_memory", lambda: 0.5 * need)
    fresh = ElasticModel(cantilever, SolverSettings(method="direct"))
    with pytest.raises(SolverError, match=r"the direct factorization of K \([\d,]+ DOFs\) needs ~.* GB.*iterative"):
        _solve_at(fresh, cantilever, np.array([1000.0]), _load(fresh))
    assert fresh.factorizations == 0


def _block_and_columns(model, scene, columns=40):
    """A block of right-hand sides solved at once and one column at a time, and the
    factor's ICNTL(27) (the block MUMPS passes over its factors at a time)."""
    clamped = model.dofs.clamped_dofs(scene.fixed)
    _, nu = material_values(scene)
    K = model.stiffness.constrained(model.stiffness.coefficients([1000.0], nu), clamped)
    solver = DirectSolver(K, clamped, SolverSettings(method="direct"), SolverStats("direct"))
    B, X = model.dofs.dense(columns), model.dofs.dense(columns)
    B.getDenseArray()[:] = np.random.default_rng(2).standard_normal(B.getDenseArray().shape)
    B.getDenseArray()[clamped] = 0.0
    solver.solve_many(B, X)
    b, x = K.createVecRight(), K.createVecRight()
    one_by_one = np.empty_like(X.getDenseArray())
    for j in range(columns):
        b.array[:] = B.getDenseArray()[:, j]
        solver.solve(b, x)
        one_by_one[:, j] = x.array
    return X.getDenseArray().copy(), one_by_one, solver.factor.getMumpsIcntl(27)


def test_blocks_of_right_hand_sides_pass_over_the_factors_in_wide_blocks(cantilever, petsc_option):
    """MUMPS's default block of 32 columns passes over the factors once per 32; ours
    is wider (solvers.rhs_blocking) with the same answer, and a user's option wins."""
    model = ElasticModel(cantilever, SolverSettings(method="direct"))
    X, one_by_one, blocking = _block_and_columns(model, cantilever)
    assert blocking == -rhs_blocking(model.dofs.num_dofs) == -512  # a few thousand DOFs: the cap
    assert relative(X, one_by_one) < 1e-12
    assert rhs_blocking(116_001) == 289 and rhs_blocking(1_000_000) == 33 and rhs_blocking(10**8) == 32
    petsc_option("elasto_mat_mumps_icntl_27", 3)
    X_user, _, blocking = _block_and_columns(model, cantilever)
    assert blocking == 3 and relative(X_user, one_by_one) < 1e-12


def test_cg_that_does_not_converge_is_an_error(cantilever, petsc_option):
    petsc_option("elasto_ksp_max_it", 2)
    model = ElasticModel(cantilever, SolverSettings(method="iterative"))
    with pytest.raises(SolverError, match="CG \\+ AMG stopped after 2 iterations.*DIVERGED_MAX_IT"):
        _solve_at(model, cantilever, np.array([1000.0]), _load(model))


def test_a_factorization_started_ahead_runs_beside_the_caller(phantom_p1, petsc_option):
    """factorize_ahead (an estimate's first factorization, started before its set-up):
    the call returns while MUMPS factorizes, the caller's Python runs meanwhile (the
    factorization does not hold the GIL), the first solve waits and gives the
    synchronous answer with one factorization counted, and a failed factorization is
    the same one-line error at that first solve."""
    scene = phantom_p1
    E = np.array([40.0])
    synchronous = ElasticModel(scene, SolverSettings(method="direct"))
    expected = _solve_at(synchronous, scene, E, _load(synchronous))
    model = ElasticModel(scene, SolverSettings(method="direct"))
    clamped = model.dofs.clamped_dofs(scene.fixed)
    c = model.stiffness.coefficients(E, material_values(scene)[1])
    model.factorize_ahead(c, clamped)
    solver = model.solvers.get(c, clamped)
    steps = 0
    while solver._pending is not None and solver._pending.is_alive():
        steps += 1  # a thread holding the GIL would leave this loop no turn until it ended
    assert steps > 1000, steps
    assert model.factorizations == 0  # counted once the caller has waited for it
    assert relative(_solve_at(model, scene, E, _load(model)), expected) < 1e-12
    assert model.factorizations == 1
    petsc_option("elasto_mat_mumps_icntl_23", 1)  # MUMPS may use 1 MB: it fails with INFOG(1) = -19
    failing = ElasticModel(scene, SolverSettings(method="direct"))
    failing.factorize_ahead(c, clamped)
    with pytest.raises(SolverError, match=r"INFOG\(1\) = -19.*ICNTL\(23\)"):
        _solve_at(failing, scene, E, _load(failing))


def test_the_memory_check_of_a_factorization_started_ahead_raises_at_its_first_solve(phantom_p1, monkeypatch):
    """factorize_ahead runs the memory check (MUMPS's analysis) in the factorization's
    thread, not before it: a K whose factors would not fit returns at once and its
    first solve raises the check's error, with nothing factorized."""
    import fenics_elasto.model.solvers as solvers

    scene = phantom_p1
    E = np.array([40.0])
    model = ElasticModel(scene, SolverSettings(method="direct"))
    clamped = model.dofs.clamped_dofs(scene.fixed)
    c = model.stiffness.coefficients(E, material_values(scene)[1])
    monkeypatch.setattr(solvers, "MEMORY_CHECK_DOFS", 0)
    monkeypatch.setattr(solvers, "available_memory", lambda: 1e3)
    model.factorize_ahead(c, clamped)
    assert model.solvers.get(c, clamped)._pending is not None
    with pytest.raises(SolverError, match=r"the direct factorization of K \([\d,]+ DOFs\) needs ~"):
        _solve_at(model, scene, E, _load(model))
    assert model.factorizations == 0


def test_cli_failed_factorization_is_one_line_and_exit_2(scenes, tmp_path, monkeypatch):
    monkeypatch.setenv("PETSC_OPTIONS", "-elasto_mat_mumps_icntl_23 1")
    proc = run_cli("simulate", scenes["cantilever"], "--out", tmp_path / "out", "--set", "solver.method='direct'")
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: MUMPS failed factorizing K"), proc.stderr
    assert "Traceback" not in proc.stderr and not (tmp_path / "out" / "result.json").exists()


# --------------------------------------------------------------------------- MPI


@pytest.mark.slow
def test_two_ranks_equal_serial(scenes, tmp_path):
    """Iterative on 2 ranks = direct serially (forward solve and block, canonical order),
    and so is direct on 2 ranks, its solves at other E on the first factors included (one
    at a nearby E, two in lock step)."""
    problem = scenes["prostate-phantom"]
    serial, parallel, direct2 = tmp_path / "serial.npz", tmp_path / "parallel.npz", tmp_path / "direct2.npz"
    run_mpi_script(MPI_SCRIPT, 1, problem, "direct", serial)
    run_mpi_script(MPI_SCRIPT, 2, problem, "iterative", parallel)
    run_mpi_script(MPI_SCRIPT, 2, problem, "direct", direct2)
    a, b, c = np.load(serial), np.load(parallel), np.load(direct2)
    assert int(b["ranks"]) == 2 and str(b["method"]) == "iterative"
    assert relative(b["u"], a["u"]) < 1e-6
    assert relative(b["X"], a["X"]) < 1e-6
    # one factorization per clamped set (forces; the block's boundary modes): the nearby solve adds none
    assert int(c["ranks"]) == 2 and int(a["factorizations"]) == int(c["factorizations"]) == 2
    for key in ("u", "X", "near", "lockstep"):
        assert relative(c[key], a[key]) < 1e-6, key
    assert np.linalg.norm(a["lockstep"]) > 0  # the lock-step CG's solutions (model.block_cg) were there to compare
