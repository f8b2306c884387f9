"""What a solve leaves behind in its result folder: fields, surfaces and the picture."""

from __future__ import annotations

import numpy as np

import dolfinx
from dolfinx import fem

from fenics_elasto.app.render import render
from fenics_elasto.files.writers import polydata, write_displacement, write_matched_surfaces
from fenics_elasto.geometry.tessellate import gather_entities


def write_solution(folder, scene, u: fem.Function, target=None, title: str = "") -> None:
    """Everything a solve leaves behind, into an ``outputs.OutputFolder`` (inside its
    ``writing()``): displacement.bp, surface.vtp and surface_<group>.vtp (deformed,
    usable as targets), screenshot.png. Collective."""
    write_displacement(u, folder.path_for("displacement.bp"))
    matched = write_matched_surfaces(folder.path, scene, u, place=folder.path_for)
    drawn = picture_arguments(scene, u, matched, have_matched=True)
    if drawn is not None:
        render(folder.path_for("screenshot.png"), target=target, title=title, **drawn)


def picture_arguments(scene, u: fem.Function, matched: dict | None = None, have_matched: bool = False) -> dict | None:
    """What ``render.picture`` draws of a solution u, on rank 0 (None elsewhere):
    every named group deformed and undeformed, the body (2D: its cells; 3D: its outer
    surface), the dimension, the clamped groups and the units. ``have_matched``: the
    matched groups' surfaces were gathered already (``matched``, as write_matched_surfaces
    returns them: on rank 0), else they are gathered here. Collective."""
    tdim = scene.mesh.topology.dim
    shown = list(dict.fromkeys(scene.matched + scene.loaded + list(scene.displacement) + scene.fixed))
    data = {g: gather_entities(u, tdim - 1, scene.facet_groups[g]) for g in shown
            if not (have_matched and g in scene.matched)}
    if tdim == 2:
        context = gather_entities(u, tdim, np.arange(scene.mesh.topology.index_map(tdim).size_local, dtype=np.int32))
    else:  # a faint backdrop: the body's boundary, flat facets
        scene.mesh.topology.create_connectivity(tdim - 1, tdim)
        context = gather_entities(u, tdim - 1, dolfinx.mesh.exterior_facet_indices(scene.mesh.topology), pieces=1)
    if scene.comm.rank != 0:
        return None
    assert context is not None  # gathered on rank 0
    data = {g: (matched or {}).get(g, data.get(g)) for g in shown}
    return {"groups": {g: polydata(*d) for g, d in data.items() if d is not None},
            "reference": {g: polydata(*d, deformed=False) for g, d in data.items() if d is not None},
            "context": polydata(*context), "dim": scene.gdim, "fixed": scene.fixed,
            "units": scene.config.get("units") or "", "matched": list(scene.matched)}
