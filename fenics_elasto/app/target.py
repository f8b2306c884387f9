"""``Target``: what an estimate compares the deformed scene with, from files or memory.

A surface may be a file (anything pyvista/meshio reads), a pyvista mesh, or arrays
``(points, cells)``; landmarks a CSV file or a pair of (n, d) arrays. Files are read,
and surfaces turned into the misfit's form, only when the scene's dimension is known
(``data``); shapes and types are checked at once.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from fenics_elasto.config.problem import IN_MEMORY
from fenics_elasto.files.readers import (check_landmark_dim, landmark_arrays, read_landmarks, surface_from_arrays,
                                         surface_of)
from fenics_elasto.geometry.surface import Surface
from fenics_elasto.inverse.displacement_field import DisplacementField
from fenics_elasto.inverse.misfit import TargetData, label_map_targets, smooth_if_rough, target_surface
from fenics_elasto.util.errors import require

type SurfaceLike = str | os.PathLike[str] | Any | tuple[Any, Any]  # a file, a pyvista mesh, (points, cells)
type LandmarksLike = str | os.PathLike[str] | tuple[Any, Any]  # a CSV file, (source, observed) arrays


def _is_path(entry: object) -> bool:
    return isinstance(entry, (str, os.PathLike))


def _is_pair(entry: object) -> bool:
    return isinstance(entry, (tuple, list)) and len(entry) == 2


def _check_surface(entry: object, name: str) -> object:
    """A surface entry of a known kind (a path made absolute: it names a file of the
    caller's working directory)."""
    import pyvista as pv

    if _is_path(entry):
        return Path(entry).resolve()  # type: ignore[arg-type]
    require(isinstance(entry, pv.DataSet) or _is_pair(entry),
            f"{name}: expected a file, a pyvista mesh or (points, cells) arrays, got {type(entry).__name__}")
    return entry


def _file_or_pair(entry: object, name: str, expected: str) -> Path | tuple[np.ndarray, np.ndarray]:
    """A CSV/field file (made absolute: it names a file of the caller's working directory)
    or a pair of (n, d) arrays of the same shape, checked."""
    require(_is_path(entry) or _is_pair(entry), f"{name}: expected {expected}, got {type(entry).__name__}")
    if _is_path(entry):
        return Path(entry).resolve()  # type: ignore[arg-type]
    return landmark_arrays(*entry, name=name)  # type: ignore[misc]


def _labels_table(labels: object) -> dict[str, Any]:
    """[target.labels] from a mapping, checked and normalised by the problem file's own
    schema (config.schema.LabelTargets); its image made absolute (a file of the caller's
    working directory)."""
    from fenics_elasto.config.schema import LabelTargets, Where

    require(isinstance(labels, Mapping) and _is_path(labels.get("image")),
            "Target.labels: expected {\"image\": label-map file, group: label or [labels], ...}, "
            f"got {labels!r}")
    assert isinstance(labels, Mapping)
    table = {**{str(g): v for g, v in labels.items()}, "image": str(Path(labels["image"]).resolve())}
    return LabelTargets().check(table, Where("Target.labels"))


class Target:
    """What the estimate compares the deformed scene with.

    ``surfaces``: one surface for all matched groups together, or ``{group: surface}``
    with one per matched group; a surface is a file path, a pyvista mesh, or
    ``(points, cells)`` arrays (2D: segments; 3D: triangles). ``landmarks``: a CSV file
    of ``source point, observed point`` rows or a ``(source_points, observed_points)``
    pair of (n, d) arrays. ``noise``: the target's noise std if known (else estimated
    from the residual), ``landmark_noise``: the landmarks' localisation std (their
    weight beside the surfaces by maximum likelihood), ``landmark_weight``: a landmark
    row's weight instead (default 1),
    ``smooth``: "auto" smooths rough 3D surfaces before matching, "off" keeps them.
    ``displacement``: a displacement field observed inside the body -- a file (points
    with one vector array, or a vector image) or ``(points, vectors)`` arrays --
    with its noise std ``displacement_noise`` and correlation length
    ``displacement_correlation`` (one observation per cell of that size; default the
    mesh's cell size); ``displacement_frame = "itk"`` for a NIfTI field whose vectors
    ITK, SimpleITK, ANTs or elastix wrote in ITK's LPS frame (files/displacements.py).
    ``labels``: the deformed state's label map instead of surfaces, as [target.labels]:
    ``{"image": path, group: label or [labels], ...}``. ``measured_force``: the total
    forces measured through loaded groups while this target was observed, as
    [boundary.measured_force]: ``{group: {"value": [...], "noise": std}}`` (with several
    states, that state's). Paths are relative to the working directory.
    """

    def __init__(self, surfaces: SurfaceLike | Mapping[str, SurfaceLike] | None = None,
                 landmarks: LandmarksLike | None = None, noise: float | None = None,
                 landmark_weight: float | None = None, smooth: str = "auto",
                 landmark_noise: float | None = None, displacement: LandmarksLike | None = None,
                 displacement_noise: float | None = None, displacement_correlation: float | None = None,
                 displacement_frame: str = "world", labels: Mapping[str, Any] | None = None,
                 measured_force: Mapping[str, Mapping[str, Any]] | None = None) -> None:
        require(surfaces is not None or landmarks is not None or displacement is not None or labels is not None,
                "Target: give surfaces, labels, landmarks and/or a displacement field")
        require(surfaces is None or labels is None, "Target: give surfaces or labels, not both")
        self.labels = None if labels is None else _labels_table(labels)
        require(measured_force is None or isinstance(measured_force, Mapping),
                "Target.measured_force: expected {group: {\"value\": [...], \"noise\": std}}, "
                f"got {type(measured_force).__name__}")
        for group, force in (measured_force or {}).items():
            require(isinstance(force, Mapping), f"Target.measured_force[{group!r}]: expected {{\"value\": [...], "
                                                f"\"noise\": std}}, got {type(force).__name__} {force!r}")
        self.measured_force = None if measured_force is None else {str(g): dict(f) for g, f in measured_force.items()}
        if isinstance(surfaces, Mapping):
            require(len(surfaces) > 0, "Target.surfaces: an empty mapping; give {group: surface, ...}")
            self.surfaces: object = {str(g): _check_surface(s, f"Target.surfaces[{g!r}]") for g, s in surfaces.items()}
        else:
            self.surfaces = None if surfaces is None else _check_surface(surfaces, "Target.surfaces")
        self.landmarks = None if landmarks is None else _file_or_pair(
            landmarks, "Target.landmarks", "a CSV file or (source_points, observed_points)")
        self.displacement = None if displacement is None else _file_or_pair(
            displacement, "Target.displacement", "a file or (points, vectors)")
        self.noise, self.landmark_weight, self.landmark_noise, self.smooth = noise, landmark_weight, landmark_noise, smooth
        self.displacement_noise, self.displacement_correlation = displacement_noise, displacement_correlation
        for key, value in self.weights.items():
            require(value is None or (isinstance(value, (int, float)) and np.isfinite(value) and value > 0),
                    f"Target.{key}: expected a number > 0 or None, got {value!r}")
        require(smooth in ("auto", "off"), f"Target.smooth: expected \"auto\" or \"off\", got {smooth!r}")
        require(displacement_frame in ("world", "itk"),
                f"Target.displacement_frame: expected \"world\" or \"itk\", got {displacement_frame!r}")
        self.displacement_frame = displacement_frame

    @property
    def weights(self) -> dict[str, float | None]:
        """The [target] numbers this target sets: noises, weight, correlation length."""
        return {"noise": self.noise, "landmark_weight": self.landmark_weight, "landmark_noise": self.landmark_noise,
                "displacement_noise": self.displacement_noise, "displacement_correlation": self.displacement_correlation}

    def spec(self) -> dict:
        """The problem file's [target] table this target stands for (files by their
        absolute paths, what is in memory as "<in memory>")."""
        label = lambda entry: str(entry) if isinstance(entry, Path) else IN_MEMORY  # noqa: E731
        out: dict[str, Any] = {"smooth": self.smooth}
        if isinstance(self.surfaces, dict):
            out["surfaces"] = {g: label(s) for g, s in self.surfaces.items()}
        elif self.surfaces is not None:
            out["surface"] = label(self.surfaces)
        if self.landmarks is not None:
            out["landmarks"] = label(self.landmarks)
        if self.labels is not None:
            out["labels"] = self.labels
        if self.displacement is not None:
            out["displacement"] = label(self.displacement)
            out["displacement_frame"] = self.displacement_frame
        out.update({k: v for k, v in self.weights.items() if v is not None})
        return out

    def data(self, gdim: int, scene=None) -> TargetData:
        """The target read and checked for a ``gdim``-dimensional scene (``scene``: for
        label maps, whose surfaces are cut for its matched groups)."""
        if self.labels is not None:
            require(scene is not None, "Target.labels: read for a scene (estimate does)")
            data = TargetData(surfaces=label_map_targets(scene, self.labels, "Target.labels"), source="Target")
        elif isinstance(self.surfaces, dict):
            surfaces = {g: self._surface(s, gdim, f"Target.surfaces[{g!r}]") for g, s in self.surfaces.items()}
            data = TargetData(surfaces=surfaces, source="Target")
        else:
            data = TargetData(surface=None if self.surfaces is None else self._surface(self.surfaces, gdim, "Target.surfaces"),
                              source="Target")
        if isinstance(self.landmarks, Path):
            data.landmarks = read_landmarks(self.landmarks, gdim)
        elif self.landmarks is not None:
            check_landmark_dim(self.landmarks, gdim, "Target.landmarks")
            data.landmarks = self.landmarks
        if isinstance(self.displacement, Path):
            data.displacement = DisplacementField.read(self.displacement, gdim, self.displacement_frame)
        elif self.displacement is not None:
            check_landmark_dim(self.displacement, gdim, "Target.displacement")
            data.displacement = DisplacementField(*self.displacement, source="Target.displacement")
        return data

    def _surface(self, entry: object, gdim: int, name: str) -> Surface:
        if isinstance(entry, Path):
            return target_surface(entry, gdim, self.smooth)
        if isinstance(entry, (tuple, list)):
            points, cells = entry
            return smooth_if_rough(surface_from_arrays(points, cells, gdim, name), name, self.smooth)
        return smooth_if_rough(surface_of(entry, gdim, name), name, self.smooth)

    def __repr__(self) -> str:
        return f"Target({self.spec()})"
