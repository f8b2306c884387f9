"""Reduced force bases: PCA, reduced = full when W spans the answer, Taylor test in
reduced coordinates, mismatched bases refused, train + reduced estimate end to end."""

import json

import numpy as np
import pytest

from conftest import logged, run_cli
from fenics_elasto.util.errors import UserError
from fenics_elasto.inverse.estimator import estimate
from fenics_elasto.mesh.builtin import build_scene
from fenics_elasto.inverse.objective import InverseProblem
from fenics_elasto.inverse.reduction.bases import Bases, load_bases, pca, train_bases, with_matched_motion
from fenics_elasto.model.scene import load_scene
from targets import fine_simulation, inclusion_ratio_4_target, letter_case
from targets import taylor_rates


def test_pca_recovers_a_known_low_rank_set():
    rng = np.random.default_rng(0)
    U = np.linalg.qr(rng.standard_normal((200, 3)))[0]
    data = U @ (rng.standard_normal((3, 20)) * np.array([[10.0], [3.0], [1.0]]))
    W, variance = pca(data, 4)
    assert np.abs(U - W[:, :3] @ (W[:, :3].T @ U)).max() < 1e-10
    assert abs(variance[:3].sum() - 1.0) < 1e-12 and variance[3] < 1e-20
    assert np.all(np.diff(variance) <= 0)
    assert np.allclose(W.T @ W, np.eye(4), atol=1e-12)


def test_matched_wall_motions_lead_the_bases_orthonormal_and_spanned():
    """Each state's matched motion becomes a leading column (the half-rank cut keeps it),
    the whole orthonormal; the bases span it afterwards; a motion they already span, or
    one the first state's column spans, adds nothing."""
    rng = np.random.default_rng(2)
    W = np.linalg.qr(rng.standard_normal((300, 12)))[0]
    filled, emptied = rng.standard_normal(300), rng.standard_normal(300)
    out = with_matched_motion(W, [filled, emptied])
    assert out.shape == (300, 14) and np.array_equal(out[:, 2:], W)
    assert np.allclose(out.T @ out, np.eye(14), atol=1e-12)
    for d in (filled, emptied):
        assert np.linalg.norm(d - out @ (out.T @ d)) < 1e-12 * np.linalg.norm(d)
    assert with_matched_motion(W, [W @ rng.standard_normal(12)]) is W
    assert with_matched_motion(W, [filled, 3.0 * filled + W[:, 0]]).shape == (300, 13)


@pytest.fixture(scope="module")
def letter(tmp_path_factory):
    return letter_case(tmp_path_factory.mktemp("reduction"), 0.25, 0.35)


def test_reduced_equals_full_when_the_bases_span_the_answer(letter):
    source, target = letter
    problem = InverseProblem(load_scene(source, [f"target.surface='{target}'"]))
    full = estimate(problem)
    d_star = problem.forward.on_loaded(full.u)
    rng = np.random.default_rng(1)
    W = np.linalg.qr(np.c_[d_star, rng.standard_normal((problem.force_dofs, 3))])[0]
    reduced = estimate(problem, basis=W)
    nu_full, nu_reduced = full["materials"]["letter"]["nu"], reduced["materials"]["letter"]["nu"]
    assert reduced["rank"] == 4 and full["rank"] is None
    assert abs(nu_reduced - nu_full) < 2e-3 * nu_full, (nu_full, nu_reduced)
    assert reduced["objective"]["final"] < 1.2 * full["objective"]["final"]


def test_taylor_in_reduced_coordinates(letter):
    source, target = letter
    problem = InverseProblem(load_scene(source, [f"target.surface='{target}'"]))
    rng = np.random.default_rng(2)
    W = np.linalg.qr(rng.standard_normal((problem.force_dofs, 6)))[0]
    theta, q = np.array([0.3]), 0.3 * rng.standard_normal(6)
    ev = problem.evaluate_displacement(theta, W @ q, "both")
    grad_q = W.T @ ev.grad_controls
    rates, _ = taylor_rates(lambda x: problem.evaluate_displacement(theta, W @ x).phi, q,
                            rng.standard_normal(6), grad_q, 0.1)
    assert rates[-2:].min() > 1.8, rates


def test_bases_from_another_mesh_are_refused(tmp_path, letter):
    """(And a rank above what the examples span is lowered, and said: a new user asked for
    rank 50 of 20 examples and was told "rank 32" with no word why.)"""
    source, _ = letter
    trainer = InverseProblem(load_scene(source), target=False)
    examples = [tmp_path / "ex"]
    fine_simulation("letter-a", tmp_path / "ex_scene", 0.4, ["boundary.displacement.top.value=[0.2, -0.5]"])
    (tmp_path / "ex").symlink_to(tmp_path / "ex_scene" / "target")
    lines: list[str] = []
    with logged(lines):
        assert train_bases(trainer, examples, rank=3).W.shape[1] == 1  # one example spans one direction
    assert any("train: rank 1, not 3: 1 examples" in line for line in lines), lines
    bases = train_bases(trainer, examples, rank=1)
    bases.save(tmp_path / "b.npz")
    W, held_out = load_bases(tmp_path / "b.npz", trainer, None)
    assert W.shape == (trainer.force_dofs, 1) and held_out is None  # one example: nothing to hold out
    other = InverseProblem(load_scene(build_scene("letter-a", tmp_path / "other", size=0.5)), target=False)
    with pytest.raises(UserError, match="other loaded nodes"):
        load_bases(tmp_path / "b.npz", other, None)


def test_bases_follow_their_nodes_renumbered_and_moved_a_little(letter):
    """Bases trained on the same mesh curved otherwise (curve on load, or "off"): the
    loaded nodes are the same but their edge midpoints moved and their canonical order
    changed. Each node nearer its own trained node than half that node's spacing: W's
    rows follow them (a new user's bases were refused, "up to 1.89 away", compared in
    order). Moved half-way to a neighbour, they are refused as before."""
    from scipy.spatial import cKDTree

    source, _ = letter
    problem = InverseProblem(load_scene(source), target=False)
    coords = problem.loaded.gather(problem.loaded.coords)
    (n, gdim), rng = coords.shape, np.random.default_rng(0)
    W = np.linalg.qr(rng.standard_normal((n * gdim, 3)))[0]
    spacing = cKDTree(coords).query(coords, k=2)[0][:, 1]
    direction = rng.standard_normal(coords.shape)
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    shuffled = rng.permutation(n)
    for share, kept in ((0.2, True), (0.6, False)):
        moved = coords + share * spacing[:, None] * direction
        trained = Bases(W.reshape(n, gdim, 3)[shuffled].reshape(-1, 3), np.full(3, 1 / 3), moved[shuffled], 10)
        if kept:
            assert np.allclose(trained.on(problem), W)
        else:
            with pytest.raises(UserError, match="as sets up to"):
                trained.on(problem)


@pytest.mark.slow
def test_train_then_reduced_estimate_from_the_command_line(tmp_path):
    """Inclusion scene: examples are simulated pushes of the top; the target (finer
    mesh, E ratio 4) uses a push that is not among them."""
    source = build_scene("inclusion", tmp_path / "source")
    rng = np.random.default_rng(3)
    examples = []
    for i in range(6):
        value = [float(rng.uniform(-0.8, 0.8)), float(rng.uniform(-1.0, 0.0))]
        out = tmp_path / f"sim{i}"
        proc = run_cli("simulate", source, "--out", out, "--set", f"boundary.displacement.top.value={value}",
                       "--set", f"materials.inclusion.E={rng.uniform(20, 80):.1f}")
        assert proc.returncode == 0, proc.stderr
        examples.append(out)
    proc = run_cli("train", source, "--examples", *examples, "--rank", 4, "--out", tmp_path / "bases.npz")
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "bases.png").exists()
    target = inclusion_ratio_4_target(tmp_path / "fine")
    proc = run_cli("estimate", source, "--out", tmp_path / "result", "--set", target,
                   "--set", f"reduction={{bases='{tmp_path / 'bases.npz'}', rank=4}}")
    assert proc.returncode == 0, proc.stderr[-2000:]
    result = json.loads((tmp_path / "result" / "result.json").read_text())
    assert result["rank"] == 4 and result["inner_solver"] == "gauss-newton"
    trained = Bases.read(tmp_path / "bases.npz").held_out
    assert result["bases_fit"]["held_out_energy"] == trained > 0.9  # stated in result.json; no warning below 0.9
    assert not any("left out of their training" in w for w in result["warnings"]), result["warnings"]
    ratio = result["materials"]["inclusion"]["E"] / result["materials"]["matrix"]["E"]
    assert abs(ratio - 4.0) / 4.0 < 0.03, ratio
    # The same bases (trained serially) under 2 MPI ranks: canonical node order.
    proc = run_cli("estimate", source, "--out", tmp_path / "result2", "--set", target,
                   "--set", f"reduction={{bases='{tmp_path / 'bases.npz'}', rank=4}}", mpi=2)
    assert proc.returncode == 0, proc.stderr[-2000:]
    parallel = json.loads((tmp_path / "result2" / "result.json").read_text())
    assert parallel["mpi_ranks"] == 2
    assert abs(parallel["materials"]["inclusion"]["E"] - result["materials"]["inclusion"]["E"]) < 1e-4 * ratio * 10
    # the optimum made exact on the start's factors (MaterialSurrogate.refine), on 2 ranks as on 1
    assert parallel["factorizations"] == result["factorizations"] == 1, (result["factorizations"], parallel["factorizations"])


def test_patients_meshed_around_an_atlas_share_its_nodes(tmp_path):
    """A patient meshed around the atlas's bladder and rectum has exactly the atlas
    nodes as loaded nodes; they sit where the organ's own shape change takes them;
    numbering round-trips; a patient meshed on its own is refused."""
    from fenics_elasto.mesh.atlas import atlas_nodes, atlas_order, atlas_surfaces, from_atlas, to_atlas
    from fenics_elasto.mesh.builtin import phantom_organs

    build_scene("prostate-phantom", tmp_path / "atlas", size=1.6)
    atlas = atlas_surfaces(tmp_path / "atlas" / "phantom.msh")
    source = build_scene("prostate-phantom", tmp_path / "p", size=1.6, seed=5, atlas=atlas)
    patient = InverseProblem(load_scene(source), target=False)
    order = atlas_order(patient, atlas)
    coords = patient.loaded.gather(patient.loaded.coords)
    assert len(order) == len(coords) == len(atlas_nodes(atlas, 2))

    # The bladder is an ellipsoid: its atlas nodes should land near their images under
    # the affine map between the two ellipsoids (spacing on the organs is ~0.56 cm).
    a, b = phantom_organs(0)["bladder"], phantom_organs(5)["bladder"]
    points, triangles = atlas["bladder"]
    vertices = points[np.unique(triangles[:, :3])]  # the first atlas nodes
    expected = np.add(b["center"], (vertices - a["center"]) * np.divide(b["radii"], a["radii"]))
    placed = coords[order[: len(vertices)]]
    assert np.linalg.norm(placed - expected, axis=1).max() < 0.12
    assert np.linalg.norm(placed - vertices, axis=1).max() > 0.1  # the patient really differs
    # Every bladder node, midpoints included, lies on the patient's true ellipsoid (curved mesh).
    bladder = coords[order[: len(atlas_nodes({"bladder": atlas["bladder"]}, 2))]]
    assert np.abs(np.sum(((bladder - b["center"]) / b["radii"]) ** 2, axis=1) - 1).max() < 1e-6

    field = np.random.default_rng(0).normal(size=(coords.size, 3))
    assert np.array_equal(from_atlas(to_atlas(field, order), order), field)
    assert np.array_equal(to_atlas(coords.ravel(), order).reshape(-1, 3), coords[order])

    alone = InverseProblem(load_scene(build_scene("prostate-phantom", tmp_path / "q", size=1.6, seed=5)),
                           target=False)
    with pytest.raises(UserError, match="not built around this atlas"):
        atlas_order(alone, atlas)


@pytest.mark.slow
def test_held_out_patient_with_bases_from_others(tmp_path, capsys):
    """Bases trained from the command line on patients 1-3 (meshed around patient 0's
    organs) fit a patient they never saw and recover its E through `estimate` with a
    [reduction] table (coarse P2 phantom: the bound is loose, see docs/validation.md)."""
    from fenics_elasto.app.cli import main
    from fenics_elasto.app.study import simulate_examples, simulate_targets

    build_scene("prostate-phantom", tmp_path / "atlas", size=1.6)
    atlas = tmp_path / "atlas" / "phantom.msh"
    train = ["train", "--atlas", str(atlas), "--rank", "12", "--out", str(tmp_path / "bases.npz")]
    for seed in (1, 2, 3):
        source = build_scene("prostate-phantom", tmp_path / f"p{seed}", size=1.6, seed=seed, atlas=read_atlas(atlas))
        examples = simulate_examples(source, tmp_path / f"p{seed}" / "examples", 5, seed=10 + seed, patient=seed)
        train += ["--patient", str(source), *map(str, examples)]
    assert main(train) == 0
    assert "patient 3/3" in capsys.readouterr().out

    held = build_scene("prostate-phantom", tmp_path / "held", size=1.6, seed=7, atlas=read_atlas(atlas))
    surfaces = simulate_targets(tmp_path / "held_target", (50.0,), 1.3, patient=7)[50.0].surfaces
    target = "target.surfaces={" + ", ".join(f"{g}='{p}'" for g, p in surfaces.items()) + "}"
    reduction = f"reduction={{bases='{tmp_path / 'bases.npz'}'}}"
    assert main(["estimate", str(held), "--out", str(tmp_path / "result"), "--set", target, "--set", reduction]) == 0
    result = json.loads((tmp_path / "result" / "result.json").read_text())
    with capsys.disabled():
        print("held-out patient:", result["materials"]["prostate"]["E"], result["surface_distance"], result["objective"])
    assert result["rank"] == 12
    assert result["surface_distance"]["rms"] < 0.005  # measured 0.001 cm: the organs moved onto the target
    assert abs(result["materials"]["prostate"]["E"] - 50.0) / 50.0 < 0.12  # measured 8 % (rank 12, 15 examples)

    # The same bases on a patient meshed on its own (not around the atlas) are refused.
    alone = build_scene("prostate-phantom", tmp_path / "alone", size=1.6, seed=7)
    assert main(["estimate", str(alone), "--out", str(tmp_path / "r2"), "--set", target, "--set", reduction]) == 2
    assert "not built around this atlas" in capsys.readouterr().err


def read_atlas(msh):
    from fenics_elasto.mesh.atlas import atlas_surfaces

    return atlas_surfaces(msh)
