"""Scenes from organ surface files (or a label-map image, labelmaps.py): the ``scene`` command.

A segmentation gives closed surfaces: the body's outer boundary (or we put a box or an
ellipsoid around the organs), regions (organs with a material of their own) and
cavities (hollow organs, whose wall carries the load). ``build_scene_from_spec`` turns a
spec naming them into a gmsh scene and a ready ``problem.toml``:

1. ``read_spec`` checks every key of the spec (one line per error, did-you-mean for typos).
2. ``anatomy_repair.closed_shells`` reads each file and repairs what is safe, one printed
   line per repair, or refuses with one line (see that module).
3. ``nest`` decides which shell lies in which: organs may neither intersect nor touch,
   every organ lies in the body, nothing lies in a cavity and no cavity in a region.
4. ``mesh_shells`` meshes body minus cavities, with every region its own volume
   (conforming interfaces). The input triangulations are reparametrised by gmsh
   (``classifySurfaces`` + ``createGeometry``), so gmsh remeshes them at the sizes asked
   for -- ``organ_size`` at regions and cavities, growing to ``size`` in the body (a
   Distance + Threshold field). The quadratic elements' boundary midpoints go onto the
   input surfaces (curved geometry); an element that this folds over is untangled by
   gmsh's high-order optimisation (boundary nodes fixed), and one still folded keeps
   straight edges (checked with gmsh's Jacobian, counted in the output).
5. ``problem_toml`` writes every group, a default material per region and ready
   ``[boundary]`` lists.

Lengths in the spec are in the files' unit (``units``: mm, cm or m), which is kept and
recorded in problem.toml; nothing is rescaled (E ratios do not depend on it).

Patches (``[patches.NAME] side = {point, normal}``) are the outer-boundary facets whose
centroid c has (c - point) . normal > 0. The outer surface is cut along each patch
plane before meshing and the cut lines are kept as curves, so every mesh facet lies
wholly on one side and a patch is a set of gmsh surfaces (a physical group).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fenics_elasto.geometry.surface import Surface
from fenics_elasto.mesh.labelmaps import coarsen, label_shells
from fenics_elasto.mesh.repair import Shell, closed_shells, cut_by_planes, enclosed_volume, sharp_edges, triangle_areas
from fenics_elasto.util.budget import CELLS_PER_VOLUME, check_mesh_cost
from fenics_elasto.config.scene_spec import read_scene_spec
from fenics_elasto.util.errors import UserError, require
from fenics_elasto.mesh.gmsh_models import fresh_gmsh_model, node_positions, untangle
from fenics_elasto.util.logs import log
from fenics_elasto.mesh.meshcheck import check_mesh
from fenics_elasto.files.readers import quiet_vtk

ORGAN_SIZE_RATIO = 3.0  # default organ_size = size / 3
BODY_ELEMENTS = 15.0  # default size = body diameter (bounding-box diagonal) / 15
TOUCH_RATIO = 0.1  # organs closer than organ_size / 10 touch (gmsh would squeeze flat elements in)
GROWTH = 0.5  # the element size grows by at most half the distance from the organs
# A surface file of over FINE_TRIANGLES triangles, and over FINE_SURFACE times those edges of
# organ_size / 2 take, is decimated to them: gmsh meshes every input triangle's patch (a
# 10^5-triangle export took minutes), while a few thousand triangles carry the organ's shape
# at organ_size (an icosphere of 5k decimated to 300 moved a test's wall motion by 2 %).
FINE_TRIANGLES = 50_000
FINE_SURFACE = 4.0

# Default materials of the written problem.toml: the body is the reference.
TISSUE_E, TISSUE_NU = 10.0, 0.4
INFLATION = 0.05  # the example [boundary.displacement] of every cavity: 5 % inflation
PUSH = 0.03  # ... and of every loaded patch: pushed in along its normal by 3 % of the body's size


# --------------------------------------------------------------------------- the spec


def read_spec(path: Path) -> dict:
    """The scene spec, checked and normalised by the one schema (config.py): every key
    present (None where not given), region surfaces as lists of file names."""
    return read_scene_spec(Path(path))


# --------------------------------------------------------------------------- shells


def _organ_shells(spec: dict, folder: Path) -> list[Shell]:
    shells = []
    files = [("region", name, f) for name, r in spec["regions"].items() for f in r["surface"]]
    files += [("cavity", name, c["surface"]) for name, c in spec["cavities"].items()]
    for role, name, file in files:
        label = f"{'regions' if role == 'region' else 'cavities'}.{name} ({file})"
        pieces = closed_shells(folder / file, label, role, name)
        _describe(pieces, label, spec["units"])
        shells += pieces
    return shells


def _describe(pieces: list[Shell], label: str, units: str) -> None:
    """One line per surface: what was kept, and its extent (a wrong unit shows here)."""
    low = np.min([p.bounds[0] for p in pieces], axis=0)
    high = np.max([p.bounds[1] for p in pieces], axis=0)
    extent = " x ".join(f"{v:.3g}" for v in high - low)
    count = sum(len(p.triangles) for p in pieces)
    log.info(f"{label}: {len(pieces)} closed piece(s), {count} triangles, {extent} {units}")


def _outward(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    return triangles if enclosed_volume(points, triangles) > 0 else triangles[:, [0, 2, 1]]


def box_shell(low, high, material: str) -> Shell:
    """A triangulated box; its edges are kept as curves (the faces stay flat)."""
    import pyvista as pv

    box = pv.Box(bounds=(low[0], high[0], low[1], high[1], low[2], high[2]), level=3, quads=False).clean()
    points = np.asarray(box.points, dtype=float)
    triangles = _outward(points, box.faces.reshape(-1, 4)[:, 1:].astype(np.int64))
    return Shell("body", material, "body.box", points, triangles, sharp_edges(points, triangles))


def ellipsoid_shell(organs: list[Shell], margin: float, material: str) -> Shell:
    """The ellipsoid, axis-aligned and shaped like the organs' bounding box grown by
    ``margin``, scaled until every organ point is at least ``margin`` inside it."""
    import igl
    import pyvista as pv
    from scipy.spatial import ConvexHull

    inner = np.vstack([s.points for s in organs])
    low, high = inner.min(axis=0), inner.max(axis=0)
    centre, axes = (low + high) / 2, (high - low) / 2 + margin
    # the distance to a convex surface is concave inside it: least at a hull vertex
    inner = inner[ConvexHull(inner).vertices]
    sphere = pv.Icosphere(radius=1.0, nsub=4)
    unit = np.asarray(sphere.points, dtype=float)
    triangles = _outward(unit, sphere.faces.reshape(-1, 4)[:, 1:].astype(np.int64))
    scale = max(1.0, np.sqrt((((inner - centre) / axes) ** 2).sum(axis=1)).max())
    for _ in range(50):
        points = centre + scale * axes * unit
        gap = np.sqrt(igl.point_mesh_squared_distance(inner, points, triangles)[0].min())
        if gap >= 0.999 * margin:
            return Shell("body", material, "body.ellipsoid", points, triangles)
        scale *= 1 + (margin - gap) / (scale * axes.min())
    raise RuntimeError("ellipsoid body: no scale keeps the margin")  # cannot happen: the gap grows with scale


def _input_shells(spec: dict, folder: Path) -> tuple[Shell, list[Shell], np.ndarray | None]:
    """The body's and the organs' shells, from surface files or a label-map image, and
    the image's voxel edges (None from surface files)."""
    if spec["labels"]:
        body, organs, voxels = label_shells(spec, folder)
        return body or _body_shell(spec, folder, organs), organs, voxels
    organs = _organ_shells(spec, folder)
    return _body_shell(spec, folder, organs), organs, None


def _body_shell(spec: dict, folder: Path, organs: list[Shell]) -> Shell:
    body = spec["body"]
    material = body["material"]
    if body["surface"]:
        label = f"body ({body['surface']})"
        pieces = closed_shells(folder / body["surface"], label, "body", material)
        require(len(pieces) == 1, f"{label}: {len(pieces)} separate closed pieces; the body must be one")
        _describe(pieces, label, spec["units"])
        return pieces[0]
    inner = np.vstack([s.points for s in organs])
    if body["box"]:
        margin = body["box"]["margin"]
        shell = box_shell(inner.min(axis=0) - margin, inner.max(axis=0) + margin, material)
    else:
        shell = ellipsoid_shell(organs, body["ellipsoid"]["margin"], material)
    extent = " x ".join(f"{v:.3g}" for v in np.ptp(shell.points, axis=0))
    log.info(f"{shell.label}: {extent} {spec['units']} around the organs")
    return shell


# --------------------------------------------------------------------------- nesting


def _gap(a: Shell, b: Shell, enough: float) -> float:
    """Smallest distance between the two surfaces (vertex to triangle, both ways), or
    any distance above ``enough`` if they are further apart."""
    import igl
    from scipy.spatial import cKDTree

    between_vertices = cKDTree(a.points).query(b.points)[0].min()
    longest = max(_longest_edge(a), _longest_edge(b))
    if between_vertices - longest > enough:  # a closest point is within an edge of a vertex
        return between_vertices
    ab = igl.point_mesh_squared_distance(a.points, b.points, b.triangles)[0].min()
    ba = igl.point_mesh_squared_distance(b.points, a.points, a.triangles)[0].min()
    return float(np.sqrt(min(ab, ba)))


def _longest_edge(shell: Shell) -> float:
    corners = shell.points[shell.triangles]
    return float(np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).max())


def _contact(a: Shell, b: Shell, how: str) -> str:
    if a.role == "body" or b.role == "body":
        organ, body = (b, a) if a.role == "body" else (a, b)
        if how == "intersect":
            return f"{organ.label} leaks out of the body: its surface and the body's ({body.label}) intersect"
        return f"{organ.label} and the body's surface ({body.label}) {how}"
    if a.label == b.label:
        return f"{a.label}: two of its pieces {how}"
    return f"{a.label} and {b.label} {how}"


def _check_apart(shells: list[Shell], gap: float) -> None:
    """No two surfaces intersect or come closer than ``gap``."""
    import pyvista as pv

    polys = [pv.PolyData.from_regular_faces(s.points, s.triangles) for s in shells]
    for i, a in enumerate(shells):
        for j in range(i + 1, len(shells)):
            b = shells[j]
            if (a.bounds[0] > b.bounds[1] + gap).any() or (b.bounds[0] > a.bounds[1] + gap).any():
                continue
            with quiet_vtk(raise_errors=True):
                _, contacts = polys[i].collision(polys[j], contact_mode=1)
            require(contacts == 0, _contact(a, b, "intersect"))
            distance = _gap(a, b, gap)
            require(distance >= gap, _contact(a, b, f"touch ({distance:.3g} apart, under organ_size / 10 = {gap:.3g})"))


def nest(shells: list[Shell], gap: float) -> list[int | None]:
    """The parent of every shell (the smallest shell around it; None for the body),
    after checking that they are apart and nest as a scene must."""
    import igl

    _check_apart(shells, gap)
    probes = np.array([s.points[0] for s in shells])
    inside = np.array([igl.fast_winding_number(s.points, s.triangles, probes) > 0.5 for s in shells]).T
    np.fill_diagonal(inside, False)
    volume = np.array([s.volume for s in shells])
    parents = [int(np.argmin(np.where(row, volume, np.inf))) if row.any() else None for row in inside]
    for shell, parent in zip(shells, parents):
        outer = shells[parent] if parent is not None else None
        if shell.role == "body":
            require(outer is None, f"the body ({shell.label}) lies inside {outer.label if outer else ''}")
            continue
        require(outer is not None, f"{shell.label} lies outside the {shells[0].label}")
        assert outer is not None
        require(outer.role != "cavity", f"{shell.label} lies inside {outer.label}: nothing can be inside a cavity")
        require(not (shell.role == "cavity" and outer.role == "region"),
                f"{shell.label} lies inside {outer.label}: a cavity must be surrounded by the body's material")
    return parents


# --------------------------------------------------------------------------- gmsh


@dataclass
class Patch:
    name: str
    point: np.ndarray
    normal: np.ndarray


# A patch plane cutting a triangle this close to one of its corners, in the triangle's
# longest edge, leaves a strip the mesher cannot resolve: a user's planes at 4e-5 and 7e-5
# of an edge from a block's bottom face kept gmsh at 100 % CPU past ten minutes, deaf to
# Ctrl-C; a label map's staircase cut at 2.6e-4 meshes.
SLIVER_SHARE = 1e-4
# Where a plane crosses the surface and passes that close to a corner by chance (a label
# map's smoothed staircase: 1 voxel grid in 10 of a user's), it is moved along its normal
# by steps of this share of that triangle's longest edge, up to NUDGE_STEPS of them, to
# where it clears every corner by NUDGE_CLEAR of an edge (ten times what is refused; a
# clearance of a whole step was not found within ten steps on a body of 36k triangles);
# never where the surface it nears lies along the plane (within NUDGE_PARALLEL of its
# normal: a face the user meant to cut at).
NUDGE_SHARE, NUDGE_STEPS, NUDGE_CLEAR, NUDGE_PARALLEL = 0.01, 10, 10 * SLIVER_SHARE, 0.95


def _closest_corner(body: Shell, point: np.ndarray, normal: np.ndarray) -> tuple[float, float, float, int]:
    """(the least gap / longest edge over the triangles the plane cuts, that gap, that
    triangle's longest edge, its row in body.triangles); a share of inf where it cuts none."""
    d = ((body.points - point) @ normal)[body.triangles]
    cut = np.flatnonzero((d.min(axis=1) < 0) & (d.max(axis=1) > 0))
    if not len(cut):
        return np.inf, np.inf, np.inf, -1
    corners = body.points[body.triangles[cut]]
    longest = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).max(axis=1)
    gap = np.where(d[cut] != 0, np.abs(d[cut]), np.inf).min(axis=1)
    worst = int(np.argmin(gap / longest))
    return float(gap[worst] / longest[worst]), float(gap[worst]), float(longest[worst]), int(cut[worst])


def _clear_of_slivers(body: Shell, patch: Patch, where: str, units: str) -> Patch:
    """``patch``, or its plane moved a little along its normal where it passes a hair
    from a corner of a triangle it cuts (NUDGE_SHARE, said in one line); one line refusing
    it where no small move clears every corner, or where the surface there lies along it."""
    normal = patch.normal / np.linalg.norm(patch.normal)
    share, gap, longest, row = _closest_corner(body, patch.point, normal)
    if share >= SLIVER_SHARE:
        return patch
    refusal = (f"{where}: its plane passes {gap:.3g} {units} from the body's surface points it cuts between (edges of "
               f"{longest:.3g}): the strip it cuts off is too thin to mesh; move the plane at least "
               f"{0.1 * longest:.3g} {units} from them")
    require(not _along_the_plane(body, row, normal), refusal)
    for step in (k * sign for k in range(1, NUDGE_STEPS + 1) for sign in (1, -1)):
        moved = patch.point + step * NUDGE_SHARE * longest * normal
        if _closest_corner(body, moved, normal)[0] >= NUDGE_CLEAR:
            log.info(f"note: {where}: its plane passed {gap:.3g} {units} from a surface point it cuts past (edges of "
                     f"{longest:.3g}), too close to mesh; moved {step * NUDGE_SHARE * longest:+.3g} {units} along its "
                     "normal, clear of every point")
            return Patch(patch.name, moved, patch.normal)
    raise UserError(refusal)


# A patch's facet turned further than this from its plane's normal is side wall (a box's
# walls: 90 degrees; a cap cut off a sphere of radius 12 at depth 4 has its rim at 48)
WALL_COSINE = np.cos(np.radians(70.0))


def _describe_patch(body: Shell, on: np.ndarray, patch: Patch, units: str) -> None:
    """One line: the patch's area, and the share of it that is wall across its plane
    (a plane 2 mm inside a box's face takes 2 mm strips of the side walls too, which a
    user's truth had left free: +2-11 % on their gland's E)."""
    unit = patch.normal / np.linalg.norm(patch.normal)  # the spec's normal need not be a unit vector
    corners = body.points[body.triangles[on]]
    normals = Surface(body.points, body.triangles[on]).area_normals  # twice each facet's area
    area = 0.5 * np.linalg.norm(normals, axis=1)
    wall = np.abs(normals @ unit) < WALL_COSINE * 2.0 * np.maximum(area, 1e-300)
    line = f"patches.{patch.name}: {area.sum():.4g} {units}^2"
    if area[wall].sum() > 0.01 * area.sum():
        depth = float(((corners[wall] - patch.point) @ unit).max())
        line += (f", {area[wall].sum() / area.sum():.0%} of it side walls reaching {depth:.3g} {units} past its plane "
                 "(a patch takes all of the boundary past its plane, not only a face)")
    log.info(line)


def _along_the_plane(body: Shell, row: int, normal: np.ndarray) -> bool:
    """Whether a triangle sharing a corner with triangle ``row`` lies along the plane:
    the plane nears a face there, and moving it would cut a band along that face."""
    corners = body.triangles[row]
    near = np.flatnonzero(np.isin(body.triangles, corners).any(axis=1))
    a, b, c = (body.points[body.triangles[near, i]] for i in range(3))
    n = np.cross(b - a, c - a)
    cosine = np.abs(n @ normal) / np.maximum(np.linalg.norm(n, axis=1), 1e-300)
    return bool((cosine > NUDGE_PARALLEL).any())


def _patch_bits(points: np.ndarray, triangles: np.ndarray, patches: list[Patch]) -> np.ndarray:
    """Bit p of each triangle: is its centroid c on patch p's side, (c - point) . normal > 0?"""
    centroid = points[triangles].mean(axis=1)
    bits = np.zeros(len(triangles), np.int64)
    for p, patch in enumerate(patches):
        bits |= ((centroid - patch.point) @ patch.normal > 0).astype(np.int64) << p
    return bits


def _add_triangulations(gmsh, shells: list[Shell]) -> np.ndarray:
    """Each shell as a discrete surface (its points numbered from starts[k]); the
    feature edges (box edges, patch cuts) as one discrete curve, kept by classification."""
    starts, lines, first = [], [], 1
    for k, shell in enumerate(shells, 1):
        tags = np.arange(first, first + len(shell.points))
        gmsh.model.addDiscreteEntity(2, k)
        gmsh.model.mesh.addNodes(2, k, tags, shell.points.ravel())
        gmsh.model.mesh.addElementsByType(k, 2, [], tags[shell.triangles].ravel())
        lines.append(tags[shell.features])
        starts.append(first)
        first += len(shell.points)
    features = np.vstack(lines)
    if len(features):
        gmsh.model.addDiscreteEntity(1, 1)
        gmsh.model.mesh.addElementsByType(1, 1, [], features.ravel())
    return np.array(starts)


def _reparametrise(gmsh, shells: list[Shell], starts: np.ndarray, patches: list[Patch]):
    """gmsh geometry from the triangulations: surfaces split only where we said (no
    angle threshold: organ surfaces are smooth, noisy ones would shatter) and where a
    single map needs it. Returns, per shell, its surfaces, and per surface its patch bits."""
    gmsh.model.mesh.classifySurfaces(math.pi, True, True, math.pi)
    gmsh.model.mesh.createGeometry()
    owned: list[list[int]] = [[] for _ in shells]
    bits: dict[int, int] = {}
    for _, tag in gmsh.model.getEntities(2):
        nodes = gmsh.model.mesh.getElementsByType(2, tag)[1].astype(np.int64).reshape(-1, 3)
        k = int(np.searchsorted(starts, nodes[0, 0], side="right")) - 1
        owned[k].append(tag)
        if shells[k].role == "body" and patches:
            local = nodes - starts[k]
            side = np.unique(_patch_bits(shells[k].points, local, patches))
            assert len(side) == 1, "a reparametrised surface straddles a patch boundary"
            bits[tag] = int(side[0])
    return owned, bits


def _add_volumes(gmsh, shells: list[Shell], parents: list, owned: list) -> list[int | None]:
    """Every shell but a cavity bounds a volume: its inside minus the shells in it."""
    geo = gmsh.model.geo
    loops = [geo.addSurfaceLoop(tags) for tags in owned]
    volumes = []
    for k, shell in enumerate(shells):
        children = [loops[c] for c, parent in enumerate(parents) if parent == k]
        volumes.append(None if shell.role == "cavity" else geo.addVolume([loops[k], *children]))
    geo.synchronize()
    return volumes


def _add_groups(gmsh, shells: list[Shell], volumes: list, owned: list, bits: dict, patches: list[Patch]) -> None:
    cells: dict[str, list[int]] = {}
    facets = {"outer": list(owned[0])}
    for shell, volume, tags in zip(shells, volumes, owned):
        if shell.role != "cavity":
            cells.setdefault(shell.name, []).append(volume)
        if shell.role != "body":
            facets.setdefault(shell.name + ("_surface" if shell.role == "region" else ""), []).extend(tags)
    for p, patch in enumerate(patches):
        facets[patch.name] = [tag for tag in owned[0] if bits[tag] >> p & 1]
    for name, tags in cells.items():
        gmsh.model.addPhysicalGroup(3, tags, name=name)
    for name, tags in facets.items():
        gmsh.model.addPhysicalGroup(2, tags, name=name)


def _size_field(gmsh, shells: list[Shell], owned: list, size: float, organ_size: float) -> None:
    """organ_size within organ_size of every region and cavity, growing linearly
    (slope GROWTH) to size in the body."""
    gmsh.option.setNumber("Mesh.MeshSizeMax", size)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
    organs = [tag for shell, tags in zip(shells, owned) if shell.role != "body" for tag in tags]
    if not organs:
        return
    field = gmsh.model.mesh.field
    distance = field.add("Distance")
    field.setNumbers(distance, "SurfacesList", organs)
    # sample points every organ_size / 2 or so (per direction, per surface)
    extent = max(np.linalg.norm(np.ptp(s.points, axis=0)) for s in shells[1:])
    field.setNumber(distance, "Sampling", int(min(400, max(20, 2 * extent / organ_size))))
    threshold = field.add("Threshold")
    field.setNumber(threshold, "InField", distance)
    field.setNumber(threshold, "SizeMin", organ_size)
    field.setNumber(threshold, "SizeMax", size)
    field.setNumber(threshold, "DistMin", organ_size)
    field.setNumber(threshold, "DistMax", organ_size + (size - organ_size) / GROWTH)
    field.setAsBackgroundMesh(threshold)


def _surface_labels(message: str, shells: list[Shell], owned: list) -> str:
    """The files behind the gmsh surface numbers a gmsh error names."""
    label_of = {tag: shells[k].label for k, tags in enumerate(owned) for tag in tags}
    tags = [int(t) for t in re.findall(r"[Ss]urface[s]? (\d+)", message)]
    labels = sorted({label_of[t] for t in tags if t in label_of})
    return f" near {' and '.join(labels)}" if labels else ""


def _generate(gmsh, shells: list[Shell], owned: list) -> None:
    """Mesh the volumes; a failure (an exception, or errors logged and no tetrahedra)
    is one line with gmsh's last error and the files behind the surfaces it names."""
    gmsh.logger.start()
    try:
        gmsh.model.mesh.generate(3)
        failed = not len(gmsh.model.mesh.getElementsByType(4)[0])
    except Exception:  # gmsh raises a bare Exception carrying its last error
        failed = True
    errors = [line for line in gmsh.logger.get() if line.startswith("Error")]
    gmsh.logger.stop()
    if failed:
        message = errors[-1].removeprefix("Error: ") if errors else "no tetrahedra"
        raise UserError(f"gmsh could not mesh the scene{_surface_labels(' '.join(errors), shells, owned)} "
                        f"({message}); surfaces too close for organ_size? try a smaller one")


MIDPOINTS = ((0, 1), (1, 2), (2, 0))  # gmsh's 6-node triangle: corner pairs of nodes 3, 4, 5


def _curve(gmsh, shells: list[Shell], owned: list) -> int:
    """Quadratic elements whose boundary-edge midpoints lie on the input surfaces: the
    straight midpoint moved to the closest point of the shell's triangulation (gmsh's
    own placement, the midpoint in the surface's parameter plane, lands far off where
    the harmonic map stretches and inverts elements). Elements this folds over are
    untangled (gmsh_models.untangle). Returns how many were kept straight."""
    import igl

    gmsh.option.setNumber("Mesh.SecondOrderLinear", 1)
    gmsh.model.mesh.setOrder(2)
    position = node_positions(gmsh)
    for shell, tags in zip(shells, owned):
        nodes = np.vstack([gmsh.model.mesh.getElementsByType(9, tag)[1].reshape(-1, 6) for tag in tags]).astype(np.int64)
        middle, first = np.unique(nodes[:, 3:].ravel(), return_index=True)
        ends = np.array(MIDPOINTS)[first % 3]
        rows = nodes[first // 3]
        straight = (position[rows[np.arange(len(rows)), ends[:, 0]]] + position[rows[np.arange(len(rows)), ends[:, 1]]]) / 2
        closest = igl.point_mesh_squared_distance(straight, shell.points, shell.triangles)[2]
        for node, point in zip(middle, closest):
            gmsh.model.mesh.setNode(int(node), point, [])
        if len(shell.features):
            _curve_features(gmsh, shell, tags, position)
    return untangle(gmsh)


def _curve_features(gmsh, shell: Shell, surfaces: list[int], position: np.ndarray) -> None:
    """Midpoints of mesh edges along a feature (a patch cut, a box edge) onto the
    feature's polyline: the closest point of the surface would leave the cut plane."""
    import igl

    curves = {abs(tag) for _, tag in gmsh.model.getBoundary([(2, t) for t in surfaces], combined=False, oriented=False)}
    per_curve = [gmsh.model.mesh.getElementsByType(8, c)[1].reshape(-1, 3) for c in curves]
    lines = np.vstack(per_curve).astype(np.int64) if per_curve else np.empty((0, 3), np.int64)
    corners = position[lines[:, :2]].reshape(-1, 3)
    gap = np.sqrt(igl.point_mesh_squared_distance(corners, shell.points, shell.features)[0]).reshape(-1, 2)
    on_feature = (gap < 1e-9 * np.linalg.norm(np.ptp(shell.points, axis=0))).all(axis=1)
    straight = position[lines[on_feature, :2]].mean(axis=1)
    closest = igl.point_mesh_squared_distance(straight, shell.points, shell.features)[2]
    for node, point in zip(lines[on_feature, 2], closest):
        gmsh.model.mesh.setNode(int(node), point, [])


def mesh_shells(shells: list[Shell], parents: list, patches: list[Patch], size: float, organ_size: float,
                msh: Path) -> dict:
    """Write the scene's gmsh mesh (4.1, physical groups); returns its counts."""
    gmsh = fresh_gmsh_model("scene")
    try:
        starts = _add_triangulations(gmsh, shells)
        owned, bits = _reparametrise(gmsh, shells, starts, patches)
        volumes = _add_volumes(gmsh, shells, parents, owned)
        _add_groups(gmsh, shells, volumes, owned, bits, patches)
        _size_field(gmsh, shells, owned, size, organ_size)
        gmsh.option.setNumber("Mesh.RandomSeed", 1)
        _generate(gmsh, shells, owned)
        straight = _curve(gmsh, shells, owned)
        msh.parent.mkdir(parents=True, exist_ok=True)
        gmsh.option.setNumber("Mesh.MshFileVersion", 4.1)
        gmsh.option.setNumber("Mesh.SaveAll", 0)
        check_mesh(gmsh, f"{msh.name} as meshed", 3)
        gmsh.write(str(msh))
        return {"tetrahedra": len(gmsh.model.mesh.getElementsByType(11)[0]),
                "nodes": len(gmsh.model.mesh.getNodes()[0]), "kept_straight": straight}
    finally:
        gmsh.clear()


# --------------------------------------------------------------------------- problem.toml


def _toml_list(names) -> str:
    return "[" + ", ".join(f'"{n}"' for n in names) + "]"


def problem_toml(spec: dict, shells: list[Shell], msh_name: str, voxels: np.ndarray | None = None) -> str:
    """A ready problem.toml: every group listed, every region estimated against the body;
    ``voxels``: the label map's voxel edges (columns), where the scene was segmented from one."""
    body = spec["body"]["material"]
    regions, cavities = list(spec["regions"]), list(spec["cavities"])
    held = [name for name, patch in spec["patches"].items() if not patch["loaded"]]
    pressed = [name for name, patch in spec["patches"].items() if patch["loaded"]]
    fixed = held or ["outer"]
    # a pressed patch moves the body's free outer surface most: observed, as in elastography
    # (not where no patch holds the body: then the rest of `outer` is clamped)
    matched = cavities + [f"{r}_surface" for r in regions] + (["outer"] if pressed and held else []) or ["outer"]
    lines = [
        f"# Scene built by `fenics-elasto scene` from surface files; lengths in {spec['units']} (the files' unit).",
        f'mesh = "{msh_name}"',
        f'units = "{spec["units"]}"',
        "degree = 2",
        "",
        "# Young's moduli in any unit (kPa, for one): with unknown boundary forces only the ratios",
        "# of E are identifiable, so one material (the body's) stays fixed as the reference.",
        f"# Poisson's ratio {TISSUE_NU:g}: a compressible start for soft tissue (0.45-0.49 where it is nearly",
        "# incompressible); set what your tissue is.",
    ]
    for region in regions:
        lines += ["", f"[materials.{region}]",
                  f"E  = {{ estimate = true, initial = {3 * TISSUE_E:g}, bounds = [{TISSUE_E / 5:g}, {TISSUE_E * 50:g}] }}",
                  f"nu = {TISSUE_NU:g}"]
    lines += ["", f"[materials.{body}]", f"E  = {TISSUE_E:g}             # the reference", f"nu = {TISSUE_NU:g}", ""]
    lines += _boundary_lines(spec, shells, fixed, cavities + pressed, matched)
    lines += ["", "# The observed (deformed) surfaces, one per matched group; or `surface = ...` or `landmarks = ...`.",
              "[target.surfaces]"]
    lines += [f'{group} = "target_{group}.stl"' for group in matched]
    if voxels is not None:
        rows = ", ".join("[" + ", ".join(f"{v:.6g}" for v in edge) + "]" for edge in np.asarray(voxels).T)
        lines += ["", "# The label map's voxels, as edges in world coordinates: how far its segmentation may be off,",
                  "# a part of sigma (\"voxels\").", "[uncertainty]", f"source_voxels = [{rows}]"]
    return "\n".join(lines) + "\n"


def _boundary_lines(spec: dict, shells: list[Shell], fixed: list[str], loaded: list[str], matched: list[str]) -> list[str]:
    """problem.toml's [boundary] and the example motions ``simulate`` uses: each cavity
    inflated, each loaded patch pushed in along its normal."""
    lines = ["[boundary]"]
    if not spec["patches"]:
        lines += ["# No [patches] in the spec: the whole outer boundary is clamped. Clamp only where the",
                  "# body is held (bones, a table) by giving patches and listing them here."]
    else:
        lines += ["# Patches are clamped unless the spec says `loaded = true` (a probe, a plate pressed on the body):",
                  "# move a patch between fixed and loaded here, and to matched if its deformed place is observed."]
    if not loaded:
        lines += ["# Nothing loaded: nothing carries the unknown forces yet; list the facet groups that do."]
    lines += [f"fixed   = {_toml_list(fixed)}",
              f"loaded  = {_toml_list(loaded)}" + ("      # unknown forces on these walls" if loaded else ""),
              f"matched = {_toml_list(matched)}",
              'match_nodes = "auto"']
    for name in loaded:
        lines += [""] + _example_motion(spec, shells, name)
    return lines


def _example_motion(spec: dict, shells: list[Shell], name: str) -> list[str]:
    if name in spec["cavities"]:
        centre = np.mean([s.points.mean(axis=0) for s in shells if s.role == "cavity" and s.name == name], axis=0)
        return [f"# Used by `simulate` (a synthetic target): {name} inflated by {INFLATION:.0%} about its centre.",
                f"[boundary.displacement.{name}]", f"scale  = {INFLATION:g}",
                "center = [" + ", ".join(f"{c:.6g}" for c in centre) + "]"]
    normal = np.asarray(spec["patches"][name]["side"]["normal"], float)
    push = -PUSH * float(np.linalg.norm(np.ptp(shells[0].points, axis=0))) * normal / np.linalg.norm(normal) + 0.0  # no -0
    return [f"# Used by `simulate` (a synthetic target): {name} pushed in along its normal by {PUSH:.0%} of the body's size.",
            f"[boundary.displacement.{name}]", "value = [" + ", ".join(f"{c:.6g}" for c in push) + "]"]


# --------------------------------------------------------------------------- the command


def _note_coarse_organs(organs: list[Shell], organ_size: float, units: str) -> None:
    """A note (not an error: gmsh copes) where an organ is under three elements thick."""
    for organ in organs:
        thickness = np.ptp(organ.points, axis=0).min()
        if organ_size > thickness / 3:
            log.info(f"note: organ_size {organ_size:.3g} {units} is coarse for {organ.label} "
                f"({thickness:.3g} {units} thick); its shape will be rough")


def _expected_cells(body: Shell, organs: list[Shell], size: float, organ_size: float) -> float:
    """About how many tetrahedra gmsh will make (budget.py): the body's volume at
    ``size``, plus a layer on each organ surface (both sides of a region's) where the
    size grows from ``organ_size`` with slope GROWTH -- the integral of 1 / size^3 across
    it, per unit area. Within ~15 % on the pelvis of the tests."""
    volume = body.volume - sum(o.volume for o in organs if o.role == "cavity")
    layer = 1 / organ_size**2 + (1 / organ_size**2 - 1 / size**2) / (2 * GROWTH)
    area = sum(triangle_areas(o.points, o.triangles).sum() * (2 if o.role == "region" else 1) for o in organs)
    return CELLS_PER_VOLUME[3] * (volume / size**3 + area * layer)


def _sizes(spec: dict, body: Shell, size: float | None) -> tuple[float, float]:
    require(size is None or (math.isfinite(size) and size > 0), f"--size must be > 0, got {size}")
    size = size or spec["size"] or np.linalg.norm(np.ptp(body.points, axis=0)) / BODY_ELEMENTS
    organ_size = spec["organ_size"] or size / ORGAN_SIZE_RATIO
    require(organ_size <= size, f"organ_size {organ_size:g} is larger than size {size:g}; organs need the finer mesh")
    return float(size), float(organ_size)


def _span(shell) -> str:
    """The shell's bounding box, for a message: [x0, x1] x [y0, y1] x [z0, z1]."""
    low, high = shell.points.min(axis=0), shell.points.max(axis=0)
    return " x ".join(f"[{a:.4g}, {b:.4g}]" for a, b in zip(low, high))


def _frame_hint(spec: dict) -> str:
    """Where a label map is not NIfTI: its world frame is ITK's (LPS), x and y negated
    beside a NIfTI copy's (RAS), which a patch's point may have been read from."""
    image = (spec.get("labels") or {}).get("image")
    if image is None or str(image).lower().endswith((".nii", ".nii.gz")):
        return ""
    return "; a MetaImage or NRRD label map is in ITK's LPS frame, x and y negated beside a NIfTI copy's RAS"


def _thinned(shells: list[Shell], organ_size: float) -> list[Shell]:
    """Surfaces of over FINE_TRIANGLES triangles decimated (coarsen, beyond FINE_SURFACE):
    a body exported at 0.5 mm (327k triangles) took gmsh 56 s and another mesh than the
    same body at 5k triangles (3 s)."""
    return [coarsen([s], organ_size, beyond=FINE_SURFACE)[0] if len(s.triangles) > FINE_TRIANGLES else s
            for s in shells]


def build_scene_from_spec(spec_path, out, size: float | None = None) -> Path:
    """Read the spec and its surface files, repair and check them, and write
    ``out/scene.msh`` and ``out/problem.toml``; returns the problem.toml path."""
    spec_path, out = Path(spec_path), Path(out)
    spec = read_spec(spec_path)
    body, organs, voxels = _input_shells(spec, spec_path.parent)
    size, organ_size = _sizes(spec, body, size)
    if spec["labels"]:  # voxel surfaces: about one vertex per boundary voxel, often far finer than organ_size
        organs = coarsen(organs, organ_size)
        body = coarsen([body], organ_size)[0] if spec["body"]["label"] else body
    else:  # exported surfaces of 10^5-10^6 triangles: gmsh would mesh every one of them
        organs, body = _thinned(organs, organ_size), _thinned([body], organ_size)[0]
    check_mesh_cost(f"{spec_path.name}: size {size:g}, organ_size {organ_size:g}",
                    _expected_cells(body, organs, size, organ_size), 3, size)
    shells = [body, *organs]
    parents = nest(shells, TOUCH_RATIO * organ_size)
    patches = [Patch(name, np.array(p["side"]["point"]), np.array(p["side"]["normal"])) for name, p in spec["patches"].items()]
    if patches:
        patches = [_clear_of_slivers(body, patch, f"{spec_path}: patches.{patch.name}", spec["units"]) for patch in patches]
        shells[0] = cut_by_planes(body, [(p.point, p.normal) for p in patches])
        sides = shells[0].patches
        assert sides is not None  # cut_by_planes marks them
        for p, patch in enumerate(patches):
            on = sides >> p & 1
            require(on.any() and not on.all(),
                    f"{spec_path}: patches.{patch.name}: {'every' if on.any() else 'no'} part of the outer boundary "
                    f"has (c - point) . normal > 0 (the body spans {_span(body)}{_frame_hint(spec)})")
            _describe_patch(shells[0], on.astype(bool), patch, spec["units"])
    units = spec["units"]
    _note_coarse_organs(organs, organ_size, units)
    log.info(f"meshing: element size {size:.3g} {units} in the body, {organ_size:.3g} {units} at the organs")
    counts = mesh_shells(shells, parents, patches, size, organ_size, out / "scene.msh")
    straight = f", {counts['kept_straight']} kept straight-sided" if counts["kept_straight"] else ""
    log.info(f"{counts['tetrahedra']} quadratic tetrahedra (curved to the surfaces{straight}), "
        f"{counts['nodes']} nodes -> {out / 'scene.msh'}")
    problem = out / "problem.toml"
    problem.write_text(problem_toml(spec, shells, "scene.msh", voxels))
    return problem
