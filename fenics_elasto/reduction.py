"""Reduced force bases (method.md §5): PCA of example boundary displacements.

Training matches the source's matched nodes to each example target surface
(iterative surface matching), keeps the loaded nodes' displacements, and takes the
principal directions of those examples: W (force_dofs x r, orthonormal columns).
In the estimate the loaded boundary moves by d = W q, so the r generalised forces
W^T F are the inner unknowns and the matched displacement is J q (objective.response).

The examples are not centred: the span of W must contain the examples themselves
(their mean included), since d = W q has no offset term.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scipy.spatial import cKDTree

from fenics_elasto.errors import UserError, require
from fenics_elasto.io import surface as facet_surface
from fenics_elasto.matching import match_surface
from fenics_elasto.objective import InverseProblem
from fenics_elasto.surface import Surface, Target, read_surface


@dataclass
class Bases:
    W: np.ndarray  # (force_dofs, r) orthonormal columns
    variance: np.ndarray  # explained variance ratio of each column
    loaded_coords: np.ndarray  # (n_loaded, gdim) the loaded nodes they belong to
    examples: int

    def truncated(self, rank: int) -> "Bases":
        require(1 <= rank <= self.W.shape[1], f"rank {rank} outside 1..{self.W.shape[1]} (the trained bases)")
        return Bases(self.W[:, :rank], self.variance[:rank], self.loaded_coords, self.examples)

    def save(self, path: Path) -> None:
        np.savez(path, W=self.W, variance=self.variance, loaded_coords=self.loaded_coords, examples=self.examples)


def pca(examples: np.ndarray, rank: int) -> tuple[np.ndarray, np.ndarray]:
    """(W, explained variance ratio) of example columns, uncentred, first ``rank``."""
    U, s, _ = np.linalg.svd(examples, full_matrices=False)
    energy = s**2 / max(np.sum(s**2), 1e-300)
    return U[:, :rank], energy[:rank]


def example_target(problem: InverseProblem, path: Path) -> Target:
    """A training target: one surface file, or a folder of surface_<group>.vtp files."""
    scene = problem.scene
    if path.is_dir():
        files = [path / f"surface_{g}.vtp" for g in scene.matched]
        missing = [str(f) for f in files if not f.is_file()]
        require(not missing, f"{path}: example folder lacks {', '.join(missing)}")
        return Target([read_surface(f, scene.gdim) for f in files], problem.matched_groups())
    return Target([read_surface(path, scene.gdim)], np.zeros(problem.matched.total, int))


def example_displacements(problem: InverseProblem, targets, say=print) -> np.ndarray:
    """(force_dofs, n) loaded-node displacements that surface matching finds per example."""
    columns = []
    for i, target in enumerate(targets, 1):
        u = match_surface(problem.matched_coords, problem.matched_groups(), target)
        columns.append(problem.on_loaded(problem.load(u, problem.matched)))
        say(f"  example {i}/{len(targets)} matched: max |u| on the loaded nodes {np.abs(columns[-1]).max():.3g}")
    return np.stack(columns, axis=1)


def train_bases(problem: InverseProblem, example_paths, rank: int, say=print) -> Bases:
    require(len(example_paths) > 0, "train: give at least one --examples file or folder")
    require(rank >= 1, f"--rank must be >= 1, got {rank}")
    rank = min(rank, len(example_paths), problem.force_dofs)
    targets = [example_target(problem, Path(p)) for p in example_paths]
    data = example_displacements(problem, targets, say)
    W, variance = pca(data, rank)
    coords = problem.loaded.gather(problem.loaded.coords)
    return Bases(W, variance, coords, len(example_paths))


def load_bases(path: Path, problem: InverseProblem, rank: int | None) -> Bases:
    """Bases from ``train``, checked against this scene's loaded nodes."""
    require(path.is_file(), f"{path}: no such bases file")
    try:
        data = np.load(path)
        bases = Bases(data["W"], data["variance"], data["loaded_coords"], int(data["examples"]))
    except (OSError, KeyError, ValueError) as err:
        raise UserError(f"{path}: not a bases file from `fenics-elasto train` ({err})") from None
    coords = problem.loaded.gather(problem.loaded.coords)
    same = bases.loaded_coords.shape == coords.shape and np.allclose(bases.loaded_coords, coords, atol=1e-9)
    require(same, f"{path}: the bases were trained on other loaded nodes ({len(bases.loaded_coords)} nodes) "
                  f"than this scene's ({len(coords)}); train them on this mesh")
    return bases.truncated(rank or bases.W.shape[1])


# --------------------------------------------------------------------------- atlas


def interpolate_nodes(values: np.ndarray, source: np.ndarray, points: np.ndarray, k: int = 4) -> np.ndarray:
    """Per-node rows (n_source, ...) carried to ``points`` by inverse-distance weights of
    the k nearest source nodes (exact where a point coincides with a node)."""
    dist, idx = cKDTree(source).query(points, k)
    weights = 1.0 / np.maximum(dist, 1e-12) ** 2
    weights /= weights.sum(axis=1, keepdims=True)
    return np.einsum("pk,pk...->p...", weights, values[idx])


@dataclass
class AtlasFit:
    """The atlas's loaded nodes placed on one patient's loaded surfaces (paper §3.3.3).

    ``positions`` are the fitted atlas nodes; per-node fields move between the
    patient's own loaded nodes and the atlas numbering through them.
    """

    positions: np.ndarray  # (n_atlas, gdim) on the patient
    patient_nodes: np.ndarray  # (n_patient, gdim) the patient's loaded nodes

    def to_atlas(self, field: np.ndarray) -> np.ndarray:
        """A field on the patient's loaded nodes (flat, optionally with columns) in atlas numbering."""
        return _carry(field, self.patient_nodes, self.positions)

    def to_patient(self, field: np.ndarray) -> np.ndarray:
        """An atlas-numbered field (flat, optionally with columns) on the patient's loaded nodes."""
        return _carry(field, self.positions, self.patient_nodes)


def _carry(field: np.ndarray, source: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Flat per-node field (rows node*gdim + component) from ``source`` nodes to ``points``."""
    rows = interpolate_nodes(field.reshape(len(source), -1), source, points)
    return rows.reshape((len(points) * (field.shape[0] // len(source)),) + field.shape[1:])


def fit_atlas(atlas: InverseProblem, patient: InverseProblem) -> AtlasFit:
    """Surface-match the atlas's loaded nodes onto the patient's loaded surfaces."""
    scene = patient.scene
    require(scene.loaded == atlas.scene.loaded, "atlas and patient must name the same loaded groups")
    # The patient's own (undeformed) loaded surfaces, one per group, are the target.
    zero = patient.model.function("zero")
    surfaces = []
    for g in scene.loaded:
        mesh = facet_surface(zero, scene.facet_groups[g], deformed=False)
        mesh = scene.comm.bcast(mesh, root=0)
        pts = np.asarray(mesh.points)[:, : scene.gdim]
        cells = mesh.lines.reshape(-1, 3)[:, 1:] if scene.gdim == 2 else mesh.faces.reshape(-1, 4)[:, 1:]
        surfaces.append(Surface(pts, cells))
    atlas_points = atlas.loaded.gather(atlas.loaded.coords)
    atlas_groups = atlas.loaded_groups()
    target = Target(surfaces, atlas_groups)
    moved = atlas_points + match_surface(atlas_points, atlas_groups, target)
    return AtlasFit(moved, patient.loaded.gather(patient.loaded.coords))


def train_atlas_bases(atlas: InverseProblem, patients, rank: int, say=print) -> Bases:
    """Multi-source training: every patient's example displacements, carried to the
    atlas's loaded nodes through that patient's atlas fit, share one PCA.

    ``patients``: (InverseProblem, example paths) per patient.
    """
    columns = []
    for i, (patient, examples) in enumerate(patients, 1):
        fit = fit_atlas(atlas, patient)
        data = example_displacements(patient, [example_target(patient, Path(p)) for p in examples], lambda *_: None)
        columns.append(fit.to_atlas(data))
        say(f"  patient {i}/{len(patients)}: {len(examples)} examples in atlas numbering")
    data = np.concatenate(columns, axis=1)
    W, variance = pca(data, min(rank, data.shape[1]))
    return Bases(W, variance, atlas.loaded.gather(atlas.loaded.coords), data.shape[1])


def bases_for_patient(atlas: InverseProblem, bases: Bases, patient: InverseProblem) -> np.ndarray:
    """Atlas-numbered bases on a (new) patient's loaded nodes, orthonormalised."""
    W = fit_atlas(atlas, patient).to_patient(bases.W)
    return np.linalg.qr(W)[0]
