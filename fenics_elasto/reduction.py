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

from fenics_elasto.errors import UserError, require
from fenics_elasto.matching import match_surface
from fenics_elasto.objective import InverseProblem
from fenics_elasto.surface import Target, read_surface


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
