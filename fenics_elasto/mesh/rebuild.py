"""Surfaces that cannot be repaired in place -> rebuilt from what they enclose.

Exports of segmentation tools are often not closed 2-manifolds: edges shared by three
or more triangles, pieces that touch or pass through themselves, holes wider than the
small-hole fill takes. What such a surface means is still clear: the region it
encloses. ``rebuilt`` recovers that region and makes its boundary again:

1. the generalized winding number of the triangles (libigl's fast winding number, Barnes-
   Hut; defined for any triangle soup, near 1 inside and 0 outside even across holes and
   non-manifold edges) on a voxel grid of REBUILD_VOXELS across the surface's extent,
   the triangles first oriented alike per piece where they can be;
2. the level set |winding number| = 0.5 of that field by VTK's contour filter (flying
   edges: a manifold surface, closed where the grid's margin keeps it off the border;
   across a hole the level set spans it like a soap film), then checked and oriented
   like any surface file (repair.shells_of). Voxel masks and SurfaceNets were tried first:
   a hole's rim leaves voxels touching by an edge, whose surface is not manifold.

One line reports what changed: the enclosed volume before (the input's signed volume,
holes and all) and after, and the Hausdorff distance between the input and the rebuilt surface
(libigl), in the scene's units. Refused: what encloses nothing (an open sheet, whose
winding number stays below 0.5), and a rebuild with a point further than FAITHFUL of
the input's size from it (a bowl closed across its rim: the solid would be a guess; a
fin dropped is far from the rebuild, not the other way round, and is fine).
"""

from __future__ import annotations

import numpy as np

from fenics_elasto.mesh.repair import enclosed_volume
from fenics_elasto.util.errors import require
from fenics_elasto.util.logs import log

FAITHFUL = 0.2  # a rebuilt surface further than this share of the input's size from it is refused
REBUILD_VOXELS = 80  # across the surface's largest extent: 1.3 mm on a kidney, 0.5 mm on a prostate


def oriented_alike(triangles: np.ndarray) -> np.ndarray:
    """Triangles ordered alike per edge-connected piece where libigl's BFS can (a
    non-manifold soup keeps what it cannot orient)."""
    import igl

    try:
        faces, _ = igl.bfs_orient(np.ascontiguousarray(triangles, dtype=np.int64))
        return np.asarray(faces, dtype=np.int64)
    except (RuntimeError, ValueError):
        return triangles


def rebuilt(points: np.ndarray, triangles: np.ndarray, label: str, why: str) -> tuple[np.ndarray, np.ndarray]:
    """The boundary of the region the triangles enclose, remade (module docstring);
    ``why`` says what made the input unusable as it is."""
    import igl
    import pyvista as pv

    points = np.ascontiguousarray(points, dtype=np.float64)
    triangles = oriented_alike(triangles)
    low, high = points.min(axis=0), points.max(axis=0)
    voxel = float(np.max(high - low)) / REBUILD_VOXELS
    counts = np.ceil((high - low) / voxel).astype(int) + 5  # two voxels of margin each side
    origin = low - 2.5 * voxel
    grid = pv.ImageData(dimensions=counts, spacing=(voxel,) * 3, origin=origin + 0.5 * voxel)
    centres = np.asarray(grid.points)
    winding = np.abs(igl.fast_winding_number(points, triangles, centres))
    require((winding >= 0.5).any(), f"{label}: {why}, and it encloses no volume (its winding number stays below "
                                    "0.5: an open sheet?); cannot make it a solid")
    grid.point_data["winding"] = winding
    surface = grid.contour([0.5], scalars="winding").triangulate().clean()
    new_points, new_triangles = np.asarray(surface.points, float), surface.regular_faces.astype(np.int64)
    before = abs(enclosed_volume(points, triangles))  # the input's own (its signed volume, holes and all)
    after = abs(enclosed_volume(new_points, new_triangles))
    distance = float(igl.hausdorff(points, triangles, new_points, new_triangles))
    invented = float(np.sqrt(igl.point_mesh_squared_distance(new_points, points, triangles)[0].max()))
    size = float(np.linalg.norm(high - low))
    require(invented <= FAITHFUL * size, f"{label}: {why}; rebuilt from what it encloses, it would lie up to "
            f"{invented:.3g} from the input ({100 * invented / size:.0f} % of its size): what the surface encloses "
            "is a guess there -- close it before (e.g. in the segmentation tool)")
    log.info(f"{label}: {why}: rebuilt from what it encloses ({' x '.join(map(str, counts))} voxels of {voxel:.3g}): "
             f"{len(triangles)} -> {len(new_triangles)} triangles, volume {before:.4g} -> {after:.4g} "
             f"({100 * (after / before - 1):+.1f} %), Hausdorff distance to the input {distance:.3g}")
    return new_points, new_triangles

