"""Reduced force bases (docs/method.md §6): PCA of example boundary displacements.

Training matches the source's matched nodes to each example target surface
(iterative surface matching), keeps the loaded nodes' displacements, and takes the
principal directions of those examples: W (force_dofs x r, orthonormal columns).
In the estimate the loaded boundary moves by d = W q, so the r generalised forces
W^T F are the inner unknowns and the matched displacement is J q (objective.response).

The examples are not centred: the span of W must contain the examples themselves
(their mean included), since d = W q has no offset term.
"""

from __future__ import annotations

import os
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np


from fenics_elasto.mesh.atlas import atlas_nodes, atlas_order, from_atlas, to_atlas
from fenics_elasto.model.responses import response_block
from fenics_elasto.util.errors import UserError, require
from fenics_elasto.util.logs import log
from fenics_elasto.geometry.matching import match_surface
from fenics_elasto.inverse.objective import InverseProblem
from fenics_elasto.geometry.targets import SurfaceTerm
from fenics_elasto.files.readers import read_surface


@dataclass
class Bases:
    """Reduced force bases from ``train``: ``W`` (force dofs x rank, orthonormal
    columns) on the loaded nodes ``loaded_coords``, the share of the examples' energy
    each column explains (``variance``), and the share of held-out examples' energy they
    keep (``held_out``). ``save(path)`` writes an .npz that ``Bases.load`` reads back."""

    W: np.ndarray  # (force_dofs, r) orthonormal columns
    variance: np.ndarray  # explained variance ratio of each column
    loaded_coords: np.ndarray  # (n_loaded, gdim) the loaded nodes they belong to (atlas nodes if atlas)
    examples: int
    atlas: dict | None = None  # group -> (points, triangles): W is in atlas numbering
    held_out: float | None = None  # share of left-out examples' energy the bases keep (held_out_energy)

    @property
    def rank(self) -> int:
        """The number of bases (columns of W)."""
        return int(self.W.shape[1])

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> Bases:
        """Bases from a file ``save`` or ``fenics-elasto train`` wrote (checked: one line
        if it is not one)."""
        return cls.read(Path(path))

    def truncated(self, rank: int) -> Bases:
        require(1 <= rank <= self.W.shape[1], f"rank {rank} outside 1..{self.W.shape[1]} (the trained bases)")
        return Bases(self.W[:, :rank], self.variance[:rank], self.loaded_coords, self.examples, self.atlas)

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the bases to ``path`` (.npz)."""
        surfaces = {}
        for g, (points, triangles) in (self.atlas or {}).items():
            surfaces[f"atlas_points_{g}"], surfaces[f"atlas_triangles_{g}"] = points, triangles
        np.savez(path, W=self.W, variance=self.variance, loaded_coords=self.loaded_coords, examples=self.examples,
                 held_out=np.nan if self.held_out is None else self.held_out,
                 atlas_groups=np.array(list(self.atlas or {}), dtype=str), **surfaces)

    @staticmethod
    def read(path: Path) -> Bases:
        require(path.is_file(), f"{path}: no such bases file")
        require(zipfile.is_zipfile(path), f"{path}: not a bases file from `fenics-elasto train` (not an .npz archive)")
        try:
            data = np.load(path, allow_pickle=False)
            groups = data["atlas_groups"].tolist() if "atlas_groups" in data else []
            atlas = {g: (data[f"atlas_points_{g}"], data[f"atlas_triangles_{g}"]) for g in groups}
            held_out = float(data["held_out"]) if "held_out" in data else np.nan
            bases = Bases(data["W"], data["variance"], data["loaded_coords"], int(data["examples"]), atlas or None,
                          None if np.isnan(held_out) else held_out)
        except (OSError, KeyError, ValueError, TypeError, EOFError) as err:
            raise UserError(f"{path}: not a bases file from `fenics-elasto train` ({err})") from None
        bases.check(path)
        return bases

    def check(self, path: Path) -> None:
        """Shapes that fit together, finite numbers, orthonormal columns: or one line."""
        W, coords = self.W, self.loaded_coords
        require(W.ndim == 2 and W.shape[1] >= 1 and coords.ndim == 2 and W.shape[0] == coords.size,
                f"{path}: W {W.shape} does not fit its {coords.shape[0]} loaded nodes; train the bases again")
        require(np.isfinite(W).all() and np.isfinite(coords).all(),
                f"{path}: W holds NaN or infinite values; train the bases again")
        gram = W.T @ W
        require(np.abs(gram - np.eye(len(gram))).max() < 1e-6, f"{path}: W's columns are not orthonormal; train the bases again")

    def on(self, problem: InverseProblem) -> np.ndarray:
        """W on this problem's loaded nodes: the atlas numbering undone (the patient's
        mesh must be built around the atlas), or the same nodes checked."""
        if self.atlas is not None:
            return from_atlas(self.W, atlas_order(problem, self.atlas))
        coords = problem.loaded.gather(problem.loaded.coords)
        if self.loaded_coords.shape == coords.shape and np.allclose(self.loaded_coords, coords, atol=1e-9):
            return self.W
        order, gap = _same_nodes_moved(self.loaded_coords, coords)
        where = f"{len(self.loaded_coords)} nodes, here {len(coords)}" if self.loaded_coords.shape != coords.shape \
            else f"{len(coords)} nodes as here, but as sets up to {gap:.3g} apart"
        require(order is not None, f"the bases were trained on other loaded nodes than {problem.scene.path.name}'s "
                f"({where}); train them on this mesh or around an atlas")
        log.info(f"bases: the loaded nodes matched by position, each nearer its own than any other (up to {gap:.3g} "
                 "apart: the same mesh curved otherwise)")
        gdim = coords.shape[1]
        return self.W.reshape(len(coords), gdim, -1)[order].reshape(self.W.shape)


def _same_nodes_moved(trained: np.ndarray, here: np.ndarray) -> tuple[np.ndarray | None, float]:
    """(for each node here, its trained node; or None, and how far apart the two sets are):
    the same nodes moved a little or numbered otherwise -- the same mesh curved on load or
    not, whose edge midpoints move by up to a quarter of their edge and change the order
    -- each nearer its own trained node than half that node's distance to the next."""
    from scipy.spatial import cKDTree

    tree = cKDTree(trained)
    gap, order = tree.query(here)
    if trained.shape != here.shape:
        return None, float(gap.max(initial=0.0))
    spacing = tree.query(trained, k=2)[0][:, 1]
    unique = len(np.unique(order)) == len(order)
    return (order if unique and (gap <= 0.5 * spacing[order]).all() else None), float(gap.max(initial=0.0))


def pca(examples: np.ndarray, rank: int, first: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(W, explained variance ratio) of example columns, uncentred, first ``rank``.

    ``first``: orthonormal columns kept in the span before anything else (as many as
    ``rank`` allows); the principal directions of what they leave unexplained follow.
    """
    total = max(float(np.sum(examples**2)), 1e-300)
    kept = np.zeros((len(examples), 0)) if first is None else first[:, :rank]
    rest = examples - kept @ (kept.T @ examples)
    U, _, _ = np.linalg.svd(rest, full_matrices=False)
    W = np.hstack([kept, U[:, : rank - kept.shape[1]]])
    return W, np.sum((W.T @ examples) ** 2, axis=1) / total


def example_target(problem: InverseProblem, path: Path) -> SurfaceTerm:
    """A training target: one surface file, or a folder of surface_<group>.vtp files;
    refused if it does not lie on the matched surface."""
    scene = problem.scene
    if path.is_dir():
        files = [path / f"surface_{g}.vtp" for g in scene.matched]
        missing = [str(f) for f in files if not f.is_file()]
        require(not missing, f"{path}: example folder lacks {', '.join(missing)}")
        term = SurfaceTerm([read_surface(f, scene.gdim) for f in files], problem.node_groups())
    else:
        term = SurfaceTerm([read_surface(path, scene.gdim)], np.zeros(len(problem.matched_coords), int))
    _check_overlap(problem, term, path)
    return term


OVERLAP = 0.25  # an example further from the matched surface than this x its size is elsewhere (as estimate's target)


def _check_overlap(problem: InverseProblem, term: SurfaceTerm, path: Path) -> None:
    """The example must deform the matched surface, not lie beside it: the same rule
    as for estimate's target (rms distance under a quarter of the matched size)."""
    y = problem.matched_coords
    distance = float(np.sqrt(np.mean(np.sum(term.residual(y) ** 2, axis=1)))) if len(y) else 0.0
    size = float(np.linalg.norm(np.ptp(y, axis=0))) if len(y) else 0.0
    require(distance < OVERLAP * size, f"{path}: the example does not overlap the matched surface (rms distance "
                                       f"{distance:.3g} vs matched size {size:.3g}); is it in the same units and frame?")


def example_displacements(problem: InverseProblem, targets) -> np.ndarray:
    """(force_dofs, n) loaded-node displacements that surface matching finds per example."""
    columns = []
    for i, target in enumerate(targets, 1):
        u = match_surface(problem.matched_coords, problem.node_groups(), target)
        columns.append(problem.forward.on_loaded(problem.observation.node_field(u)))
        log.info(f"  example {i}/{len(targets)} matched: max |u| on the loaded nodes {np.abs(columns[-1]).max():.3g}")
    return np.stack(columns, axis=1)


def train_bases(problem: InverseProblem, example_paths, rank: int, generator=None) -> Bases:
    """PCA of the loaded-wall displacements of example targets (surface-matched) and/or
    of synthetic examples (synthetic.Generator)."""
    require(len(example_paths) > 0 or generator is not None, "train: give --examples or --synthetic N")
    require(rank >= 1, f"the rank (--rank) must be >= 1, got {rank}")
    columns = []
    if example_paths:
        columns.append(example_displacements(problem, [example_target(problem, Path(p)) for p in example_paths]))
    first = None
    if generator is not None:
        from fenics_elasto.inverse.reduction.synthetic import affine_basis, synthetic_examples

        columns.append(synthetic_examples(problem, generator))
        first = affine_basis(problem)
    data = np.concatenate(columns, axis=1)
    require(np.isfinite(data).all(), "train: an example's displacement is not finite")
    limit = data.shape[1] + (0 if first is None else first.shape[1])
    used = min(rank, limit, problem.force_dofs)
    if used < rank:
        affine = "" if first is None else f" and {first.shape[1]} affine motions"
        log.warning(f"train: rank {used}, not {rank}: {data.shape[1]} examples{affine} on {problem.force_dofs} force "
                    "dofs span no more; give more examples (--synthetic N) for a higher rank")
    W, variance = pca(data, used, first)
    coords = problem.loaded.gather(problem.loaded.coords)
    return Bases(W, variance, coords, data.shape[1], held_out=held_out_energy(data, W.shape[1], first))


def held_out_energy(data: np.ndarray, rank: int, first=None, folds: int = 5) -> float | None:
    """The share of the energy of examples left out of the training that rank-``rank``
    bases keep (5-fold cross-validation): the bases' reach beyond their own examples.
    (On its own examples a rank equal to their number keeps 100 %, always.)"""
    n = data.shape[1]
    if n < 2:
        return None
    kept = total = 0.0
    for fold in np.array_split(np.random.default_rng(0).permutation(n), min(folds, n)):
        rest = np.setdiff1d(np.arange(n), fold)
        W, _ = pca(data[:, rest], min(rank, len(rest) + (0 if first is None else first.shape[1])), first)
        left = data[:, fold]
        kept += float(np.sum((W.T @ left) ** 2))
        total += float(np.sum(left**2))
    return kept / total if total > 0 else None


def bases_fit(W: np.ndarray | None, d0: np.ndarray) -> dict | None:
    """How much of the wall motion surface matching found (d0) the bases can represent:
    |W W^T d0|^2 / |d0|^2 (1: all of it); None without bases. Blind where it matters
    most: the affine part dominates |d0|, so bases that miss a ripple still score 0.99
    (missing_wall_motion asks the question that decides E)."""
    if W is None:
        return None
    kept = W @ (W.T @ d0)  # d0: one column per state, or one state's vector
    total = float(np.sum(d0**2))
    return {"wall_motion_explained": float(np.sum(kept**2)) / total if total > 0 else 1.0}


# missing_wall_motion's one response: a first-order measure reported to 2 digits needs
# the field to ~1e-4, not the estimate's 1e-8 (the phantom at E 25 / 75: CG steps 4 / 9
# -> 2 / 3, 0.25 / 0.47 s -> 0.17 / 0.19 s, the shift the same to 3 digits; 1e-3 moved it 8-14 %).
DIAGNOSTIC_RTOL = 1e-4


def with_matched_motion(W: np.ndarray, motions: list[np.ndarray]) -> np.ndarray:
    """The bases with each state's surface-matched wall motion (estimator.smooth_matched_motions)
    put before their columns, orthonormal: the wall motion the data show, one direction
    per state, whatever the training's examples spanned. First, so that the bases cut to
    half their rank keep them. A motion the columns already span adds nothing.
    (The pelvis phantom at rank 80: the emptied state alone E 85 -> 44 for a truth of 50,
    its interval then holding it; the two states 55.3 -> 49.5.)"""
    extra: list[np.ndarray] = []
    for d in motions:
        size, spanned = float(np.linalg.norm(d)), np.column_stack(extra + [W])
        for _ in range(2):  # twice: one pass of Gram-Schmidt loses orthogonality to round-off
            d = d - spanned @ (spanned.T @ d)
        if float(np.linalg.norm(d)) > 1e-6 * size:
            extra.append(d / float(np.linalg.norm(d)))
    return np.column_stack(extra + [W]) if extra else W


def missing_wall_motion(problem: InverseProblem, W: np.ndarray, theta, evaluation, lin) -> dict:
    """How far the estimate would move if the bases held the wall motion they miss.

    At the reduced optimum the matched wall (loaded) nodes still sit r from their target;
    moving them by -r (its normal part: the closest-point curvature weights it) less the
    part W already spans is the motion the bases miss, d_miss. As one more boundary mode
    its response costs one back-solve on the factorization at theta. One Gauss-Newton step
    of the fit in (q, t, s) from the optimum -- where only t's gradient is not zero --
    gives the shift of s = (log E, nu) that bases holding d_miss would bring: a first-
    order measure of the bias the bases put in the answer (the posterior's interval
    cannot see it: it is not noise).
    """
    n = problem.observation.node_count
    walls = problem.matched_on_loaded()
    needs, directions = [], []
    for residual in problem.states.split(evaluation.residual):  # each state's walls, one more mode each
        need = np.zeros((n, problem.gdim))
        need[walls] = -residual[:n][walls]
        d = problem.forward.on_loaded(problem.observation.node_field(need))
        d -= W @ (W.T @ d)
        size = float(np.linalg.norm(d))
        needs.append(need[walls])
        directions.append(d / size if size > 0 else d)
    rms = float(np.sqrt(np.mean(np.sum(np.concatenate(needs) ** 2, axis=1)))) if walls.any() else 0.0
    shift = np.zeros(lin.A_s.shape[1])
    if any(np.any(d) for d in directions):
        J = np.concatenate([_state_column(problem, theta, d, s) for s, d in enumerate(directions)], axis=2)
        rows = problem.misfit.statistical_rows(evaluation.y, evaluation.residual)  # as the linearisation's
        a = np.einsum("lkd,ldr->lkr", rows, J).reshape(len(lin.residual), -1)
        A = np.hstack([lin.A_q, a, lin.A_s])
        extra = a.shape[1]
        p = lin.A_q.shape[1] + extra
        H = A.T @ A + np.diag(np.r_[np.full(p, lin.prior), np.zeros(lin.A_s.shape[1])])
        g = np.zeros(len(H))
        g[p - extra:p] = a.T @ lin.residual
        shift = -np.linalg.lstsq(H, g, rcond=None)[0][p:]
    return {"missing_wall_rms": rms, "shift_s": shift, "direction": directions[0]}


def _state_column(problem: InverseProblem, theta, d: np.ndarray, state: int) -> np.ndarray:
    """(S n, gdim, 1): the observed response to one more wall mode of one state's, zero
    on the other states' rows."""
    rows = problem.observation.rows(response_block(problem.forward, theta, d[:, None], DIAGNOSTIC_RTOL))
    out = np.zeros((problem.states.count * len(rows),) + rows.shape[1:])
    out[state * len(rows):(state + 1) * len(rows)] = rows
    return out


def load_bases(path: Path, problem: InverseProblem, rank: int | None) -> tuple[np.ndarray, float | None]:
    """W of bases from ``train`` on this scene's loaded nodes (refused if they do not fit),
    and the share of held-out examples' energy they kept at their trained rank (None if
    unknown; a lower ``rank`` keeps less)."""
    bases = Bases.read(path)
    try:
        return bases.truncated(rank or bases.W.shape[1]).on(problem), bases.held_out
    except UserError as err:
        raise UserError(f"{path}: {err}") from None


HELD_OUT_MIN = 0.9  # bases keeping less of unseen examples' energy are too narrow to trust


def reach_warning(held_out: float | None, rank: int) -> str | None:
    """One line when the bases keep under HELD_OUT_MIN of the energy of examples left
    out of their training: a new case's wall motion then lies partly outside them and
    the estimate follows the bases, not the data. (Measured: rank-12 bases keeping 70.6 %
    put a 500k-DOF phantom's E 41 % off, while ``bases_fit`` saw 98 % of the wall motion
    explained -- the affine part dominates that share.)"""
    if held_out is None or held_out >= HELD_OUT_MIN:
        return None
    return (f"the bases keep only {100 * held_out:.0f} % of the energy of examples left out of their training "
            f"(rank {rank} used): a new case's wall motion is likely outside them, so E may follow the bases; "
            "train with more examples and a higher rank (--synthetic N)")


def train_atlas_bases(atlas: dict, patients, rank: int) -> Bases:
    """One PCA of every patient's example displacements, in atlas numbering.

    ``patients``: (InverseProblem on a mesh built around the atlas, example paths) each.
    """
    require(rank >= 1, f"the rank (--rank) must be >= 1, got {rank}")
    columns = []
    for i, (patient, examples) in enumerate(patients, 1):
        order = atlas_order(patient, atlas)
        data = example_displacements(patient, [example_target(patient, Path(p)) for p in examples])
        columns.append(to_atlas(data, order))
        log.info(f"  patient {i}/{len(patients)}: {len(examples)} examples in atlas numbering")
    data = np.concatenate(columns, axis=1)
    W, variance = pca(data, min(rank, data.shape[1]))
    scene = patients[0][0].scene
    loaded = {g: atlas[g] for g in scene.loaded}
    return Bases(W, variance, atlas_nodes(loaded, scene.degree), data.shape[1], loaded)
