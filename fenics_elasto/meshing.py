"""Built-in scenes: gmsh meshes plus a ready ``problem.toml``.

The 2D scenes are gmsh ``.geo`` sources in ``meshes/``; the prostate phantom is built
with gmsh's OpenCASCADE kernel here because ``--seed`` varies its organs.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from fenics_elasto.budget import CELLS_PER_VOLUME, check_mesh_cost
from fenics_elasto.errors import UserError, require
from fenics_elasto.matching import fit_surfaces
from fenics_elasto.meshcheck import check_mesh, gmsh_errors, read_msh_file
from fenics_elasto.scene import fresh_gmsh_model, gmsh_facet_groups
from fenics_elasto.surface import quadratic_edges

GEO_DIR = Path(__file__).parent / "meshes"
SCENES = ("letter-a", "cantilever", "inclusion", "prostate-phantom")
PHANTOM_LOADED = ("bladder", "rectum")  # the phantom's loaded groups (see PHANTOM_TOML)


class GmshModel:
    """A fresh gmsh model with default options (they are global and would leak
    from one scene to the next), cleared again on exit."""

    def __init__(self, name: str):
        self.name = name

    def __enter__(self):
        return fresh_gmsh_model(self.name)

    def __exit__(self, *exc):
        import gmsh

        gmsh.clear()


def _generate(gmsh, path: Path, dim: int) -> None:
    """Mesh up to ``dim``. gmsh may log an error and leave a dimension empty (a surface
    mesh that overlaps itself: no tetrahedra) without raising: that is a failure too,
    named by the group of the surface gmsh blames."""
    with gmsh_errors() as errors:
        gmsh.model.mesh.generate(dim)
    if errors or not sum(len(t) for t in gmsh.model.mesh.getElements(dim)[1]):
        cause = (errors or ["no elements"])[-1]
        groups = _blamed(gmsh, cause)
        raise MeshingFailed(f"gmsh could not mesh {path.name} at this size ({cause}"
                            f"{': ' + ', '.join(groups) if groups else ''}); try another --size", groups)


class MeshingFailed(UserError):
    """gmsh failed; ``groups``: the physical groups of the surfaces it blames."""

    def __init__(self, message: str, groups: list[str]):
        super().__init__(message)
        self.groups = groups


def _blamed(gmsh, message: str) -> list[str]:
    """The physical groups of the surfaces or curves a gmsh message names."""
    names = set()
    for word, dim in (("surface", 2), ("curve", 1)):
        for tag in map(int, re.findall(rf"{word} (\d+)", message, flags=re.IGNORECASE)):
            names |= {gmsh.model.getPhysicalName(dim, g) for g in gmsh.model.getPhysicalGroupsForEntity(dim, tag)}
    return sorted(names - {""})


def _write_msh(gmsh, path: Path, dim: int) -> None:
    _generate(gmsh, path, dim)
    _save(gmsh, path)


def _save(gmsh, path: Path) -> None:
    """Check the mesh as a scene reader will (meshcheck.py), then write it."""
    check_mesh(gmsh, f"{path.name} as meshed", max(d for d, _ in gmsh.model.getPhysicalGroups()))
    path.parent.mkdir(parents=True, exist_ok=True)
    gmsh.option.setNumber("Mesh.MshFileVersion", 4.1)
    gmsh.option.setNumber("Mesh.SaveAll", 0)
    gmsh.write(str(path))


def _node_positions(gmsh) -> np.ndarray:
    """Coordinates of every node of the current gmsh mesh, indexed by node tag."""
    tags, coords, _ = gmsh.model.mesh.getNodes()
    position = np.zeros((int(tags.max()) + 1, 3))
    position[tags] = coords.reshape(-1, 3)
    return position


def physical_surfaces(gmsh) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Every facet group of the current 3D gmsh mesh as (points, triangles), the
    points numbered per group in node-tag order."""
    position = _node_positions(gmsh)
    surfaces = {}
    for name, rows in gmsh_facet_groups(gmsh, 3).items():
        used, local = np.unique(rows + 1, return_inverse=True)
        surfaces[name] = (position[used], local.reshape(rows.shape))
    return surfaces


def read_surfaces(msh: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The facet groups of a 3D .msh file as (points, triangles); a file that is not a
    sound 3D mesh (meshcheck.py): one line."""
    with GmshModel("surfaces") as gmsh:
        read_msh_file(gmsh, msh)
        require(gmsh.model.getPhysicalGroups(3), f"{msh}: not a 3D mesh with physical groups")
        check_mesh(gmsh, str(msh), 3)
        return physical_surfaces(gmsh)


def atlas_surfaces(msh: Path, groups=PHANTOM_LOADED) -> dict:
    """An atlas for ``build_prostate_phantom(atlas=...)``: a mesh's loaded surfaces."""
    surfaces = read_surfaces(msh)
    missing = [g for g in groups if g not in surfaces]
    require(not missing, f"{msh}: no facet group(s) {', '.join(missing)} to serve as the atlas")
    return {g: surfaces[g] for g in groups}


def _onto_geometry(gmsh, faces: list[int], points: np.ndarray) -> np.ndarray:
    """Each point moved to the closest point of the CAD faces (not of their mesh, whose
    facets cut inside curved organs: a node there would be a fake displacement)."""
    candidates = np.stack([np.reshape(gmsh.model.getClosestPoint(2, f, points.ravel())[0], (-1, 3)) for f in faces])
    nearest = np.argmin(np.linalg.norm(candidates - points, axis=2), axis=0)
    return candidates[nearest, np.arange(len(points))]


def _mesh_inside(gmsh, surfaces: dict, volumes: dict, path: Path) -> None:
    """Tetrahedralise the volumes bounded by given triangulated surfaces, keeping those
    triangles -- vertices, and the midpoint nodes of 6-node triangles -- exactly: a
    new model of discrete surfaces, meshed inside, then made quadratic.

    ``volumes``: name -> the surface groups bounding it (outer and inner shells).
    The vertices get consecutive node tags in the order of each group's points.
    """
    gmsh.model.add("around-surfaces")
    first, corners, edge_keys, edge_points = 1, [], [], []
    for tag, (name, (points, triangles)) in enumerate(surfaces.items(), 1):
        vertices = np.unique(triangles[:, :3])
        node_tag = np.zeros(len(points), np.int64)
        node_tag[vertices] = np.arange(first, first + len(vertices))
        gmsh.model.addDiscreteEntity(2, tag)
        gmsh.model.mesh.addNodes(2, tag, node_tag[vertices], points[vertices].ravel())
        gmsh.model.mesh.addElementsByType(tag, 2, [], node_tag[triangles[:, :3]].ravel())
        gmsh.model.addPhysicalGroup(2, [tag], name=name)
        corners.append(points[vertices])
        if triangles.shape[1] == 6:
            pairs, middle = quadratic_edges(triangles)
            edge_keys.append(_edge_key(node_tag[pairs] - 1))
            edge_points.append(points[middle])
        first += len(vertices)
    tag_of = {name: tag for tag, name in enumerate(surfaces, 1)}
    volume = {name: gmsh.model.geo.addVolume([gmsh.model.geo.addSurfaceLoop([tag_of[s] for s in shells])])
              for name, shells in volumes.items()}
    gmsh.model.geo.synchronize()
    for name, tag in volume.items():
        gmsh.model.addPhysicalGroup(3, [tag], name=name)
    # The surfaces carry the sizes; the volume grades between them.
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 1)
    gmsh.option.setNumber("Mesh.ElementOrder", 1)
    _generate(gmsh, path, 3)
    if edge_keys:
        _curve_surfaces(gmsh, np.concatenate(corners), np.concatenate(edge_keys), np.concatenate(edge_points))
    _save(gmsh, path)


def _edge_key(pairs: np.ndarray) -> np.ndarray:
    """One integer per edge of (sorted) node-tag pairs."""
    return pairs[:, 0] * (1 << 31) + pairs[:, 1]


def _curve_surfaces(gmsh, corners: np.ndarray, keys: np.ndarray, midpoints: np.ndarray) -> None:
    """Quadratic elements whose surface edges (``keys`` of pairs of rows of ``corners``)
    have the given midpoint nodes. setOrder renumbers nodes, so corners are found by
    position."""
    gmsh.option.setNumber("Mesh.SecondOrderLinear", 1)  # straight first; the surface ones are moved below
    gmsh.model.mesh.setOrder(2)
    keys, first = np.unique(keys, return_index=True)
    midpoints = midpoints[first]
    position = _node_positions(gmsh)
    tree = cKDTree(corners)
    for _, tag in gmsh.model.getEntities(2):
        nodes = gmsh.model.mesh.getElementsByType(9, tag)[1].reshape(-1, 6).astype(np.int64)
        gap, corner = tree.query(position[nodes[:, :3]])
        pairs, middle = quadratic_edges(np.c_[corner, nodes[:, 3:]])
        at = np.searchsorted(keys, _edge_key(pairs))
        found = (keys[np.minimum(at, len(keys) - 1)] == _edge_key(pairs)) & np.repeat(gap.max(axis=1) < 1e-9, 3)
        for node, point in zip(middle[found], midpoints[at[found]]):
            gmsh.model.mesh.setNode(int(node), point, [])


def _mesh_geo(geo: str, path: Path, numbers: dict, default_size: float) -> None:
    """Mesh a 2D scene from its .geo source (``numbers``: its parameters, ``h`` the
    element size), after checking what the mesh will cost: the area comes from a mesh
    at the scene's default size."""
    with GmshModel(path.stem) as gmsh:
        _merge_geo(gmsh, geo, {**numbers, "h": default_size})
        _generate(gmsh, path, 2)
        area = _mesh_area(gmsh)
        gmsh.clear()
        h = numbers["h"]
        check_mesh_cost(f"{path.stem.replace('_', '-')} --size {h:g}", area / h**2 * CELLS_PER_VOLUME[2], 2, h)
        _merge_geo(gmsh, geo, numbers)
        _write_msh(gmsh, path, 2)


def _merge_geo(gmsh, geo: str, numbers: dict) -> None:
    for key, value in numbers.items():
        gmsh.parser.setNumber(key, [float(value)])
    gmsh.merge(str(GEO_DIR / geo))


def _mesh_area(gmsh) -> float:
    """The area of the current 2D mesh (its triangles' corners)."""
    position = _node_positions(gmsh)
    area = 0.0
    for etype, nodes in zip(*gmsh.model.mesh.getElements(2)[::2]):
        corners = position[nodes.reshape(-1, gmsh.model.mesh.getElementProperties(etype)[3])[:, :3]]
        area += 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1).sum()
    return float(area)


LETTER_A_TOML = """\
# The paper's 2D experiment: letter A, feet clamped, top loaded, outline matched.
mesh = "letter_a.msh"
plane = "strain"
degree = 2            # P2 is accurate; degree = 1 is the paper's setting (locks as nu -> 0.5)

[materials.letter]
E  = 10.0             # with unknown forces only nu is identifiable for one material
nu = {{ estimate = true, initial = 0.3, bounds = [0.0, 0.499] }}

[boundary]
fixed   = ["feet"]
loaded  = ["top"]
matched = ["outline"]

# Used by `simulate` to make a synthetic target: the top is pushed down and sideways.
[boundary.displacement.top]
value = [0.4, -0.8]

[target]
surface = "target.vtp"   # e.g. the surface.vtp written by `simulate`
"""

CANTILEVER_TOML = """\
# Plane-stress cantilever (Timoshenko-Goodier): support clamped, end shear at the tip.
mesh = "cantilever.msh"
plane = "stress"
degree = 2

[materials.beam]
E  = 1000.0
nu = 0.3

[boundary]
fixed   = ["support"]
loaded  = ["tip"]
matched = ["top", "bottom"]

# Used by `simulate`: total force on the tip, spread as a uniform traction.
[boundary.load]
tip = [0.0, -1.0]
"""

INCLUSION_TOML = """\
# A stiff inclusion in a softer plate: recover the E ratio from the outline and the
# inclusion interface. Bottom clamped, top loaded (unknown forces).
mesh = "inclusion.msh"
plane = "strain"
degree = 2

[materials.inclusion]
E  = {{ estimate = true, initial = 30.0, bounds = [1.0, 1000.0] }}
nu = 0.3

[materials.matrix]
E  = 10.0             # the reference
nu = 0.3

[boundary]
fixed   = ["bottom"]
loaded  = ["top"]
matched = ["outline", "interface"]

# Used by `simulate`: the top pressed down and sheared.
[boundary.displacement.top]
value = [0.5, -0.8]

[target]
surfaces = {{ outline = "target_outline.vtp", interface = "target_interface.vtp" }}
"""

PHANTOM_TOML = """\
# Synthetic pelvis: soft tissue with a bladder cavity, a prostate and a rectum tube,
# clamped at the bones. Units: cm and kPa.
mesh = "phantom.msh"
degree = 2

[materials.prostate]
E  = {{ estimate = true, initial = 30.0, bounds = [2.0, 300.0] }}
nu = 0.4

[materials.tissue]
E  = 10.0             # the reference: with unknown forces only E ratios are identifiable
nu = 0.4

# Phi*(E) is smooth and single-welled in log E here: three scan points start it well.
[optimizer]
scan = 3

[boundary]
fixed   = ["bones"]
loaded  = ["bladder", "rectum"]
matched = ["bladder", "prostate_surface", "rectum"]

# Used by `simulate`: the bladder inflated by {inflation:.0%} about its centre.
[boundary.displacement.bladder]
scale  = {inflation}
center = [{cx:.4f}, {cy:.4f}, {cz:.4f}]

[target]
surface = "target.vtp"
"""


def build_letter_a(out: Path, size: float | None = None) -> Path:
    _mesh_geo("letter_a.geo", out / "letter_a.msh", {"h": size or 0.4}, 0.4)
    return _write_toml(out, LETTER_A_TOML.format())


def build_cantilever(out: Path, size: float | None = None, length: float = 8.0, half_height: float = 1.0) -> Path:
    _mesh_geo("cantilever.geo", out / "cantilever.msh", {"h": size or 0.25, "L": length, "c": half_height}, 0.25)
    return _write_toml(out, CANTILEVER_TOML)


def build_inclusion(out: Path, size: float | None = None, radius: float = 2.0) -> Path:
    _mesh_geo("inclusion.geo", out / "inclusion.msh", {"h": size or 0.5, "r": radius}, 0.5)
    return _write_toml(out, INCLUSION_TOML.format())


def phantom_organs(seed: int) -> dict:
    """Organ sizes and positions (cm); seed 0 is the nominal patient, others vary it.

    The jitter (radii +-8 %, centres +-0.15 cm) keeps every gap between organs open.
    """
    nominal = {
        "bladder": {"center": [0.0, -0.3, 2.6], "radii": [2.3, 1.9, 1.5]},
        "prostate": {"center": [0.0, 0.0, -0.8], "radii": [1.6, 1.3, 1.1]},
        "rectum": {"center": [0.0, 2.9, -4.0], "radius": 0.9, "length": 5.0},
        "pubis": {"center": [-3.5, -3.0, -1.0], "radius": 0.7, "length": 7.0},
        "sacrum": {"center": [-3.0, 4.2, 2.5], "radius": 0.5, "length": 6.0},
    }
    if seed == 0:
        return nominal
    rng = np.random.default_rng(seed)
    organs = {}
    for name, organ in nominal.items():
        organs[name] = dict(organ)
        organs[name]["center"] = list(np.add(organ["center"], rng.uniform(-0.15, 0.15, 3)))
        if "radii" in organ:
            organs[name]["radii"] = list(np.multiply(organ["radii"], rng.uniform(0.92, 1.08, 3)))
        else:
            organs[name]["radius"] = organ["radius"] * rng.uniform(0.92, 1.08)
    return organs


# Element sizes near the organs, relative to --size. The prostate's stiffness shows as
# ~1e-3 cm of surface motion per 10 % of E, carried to it through the tissue from the
# moving bladder and rectum walls, so the estimate's accuracy is set by both: against
# a converged target E = 50 comes out +4.6 % (these defaults), +2.1 % (organs 0.25),
# +0.7 % (organs 0.2) at h = 1.6 (benchmarks/convergence.py).
ORGAN_SIZE = 0.35
PROSTATE_SIZE = 0.22
FAR_SIZE = 1.6  # the element size away from the organs, relative to --size
GRADING = (0.3, 4.0)  # cm from the organ walls: the organ's size up to the first, FAR_SIZE from the second
BONE_SIZE = 2.0  # x the bone's radius: the bones' element size when gmsh fails on them at the size of their place
PHANTOM_HALF = (6.0, 5.0, 5.0)  # cm: the box of tissue
PHANTOM_BONES = ("pubis", "sacrum")


def _graded_size(field, faces: list[int], size_min: float, size_max: float) -> int:
    """A gmsh size field: size_min within GRADING[0] of the faces, growing to size_max at GRADING[1]."""
    dist = field.add("Distance")
    field.setNumbers(dist, "SurfacesList", faces)
    thr = field.add("Threshold")
    field.setNumber(thr, "InField", dist)
    field.setNumber(thr, "SizeMin", size_min)
    field.setNumber(thr, "SizeMax", size_max)
    field.setNumber(thr, "DistMin", GRADING[0])
    field.setNumber(thr, "DistMax", GRADING[1])
    return thr


def _check_phantom_sizes(organs: dict, h: float, organ_size: float, prostate_size: float) -> None:
    """Refuse element sizes that cannot resolve the organs: a wall needs elements no
    larger than the organ's smallest radius (6 or more around it)."""
    label = f"prostate-phantom --size {h:g}"
    walls = min(organs["rectum"]["radius"], *organs["bladder"]["radii"])
    require(organ_size * h <= walls, f"{label}: elements of {organ_size * h:.3g} cm at the bladder and rectum walls "
                                     f"do not resolve them (radius {walls:.3g} cm): use --size <= {walls / organ_size:.3g} "
                                     "or a smaller --organ-size")
    prostate = min(organs["prostate"]["radii"])
    require(prostate_size * h <= prostate, f"{label}: elements of {prostate_size * h:.3g} cm do not resolve the prostate "
                                           f"(radius {prostate:.3g} cm): use --size <= {prostate / prostate_size:.3g} "
                                           "or a smaller --prostate-size")


def _phantom_cells(organs: dict, half, h: float, organ_size: float, prostate_size: float, spacing: float = 0.2) -> float:
    """The tetrahedra gmsh will make, about: the size field integrated over a grid of
    the meshed volume (the box without bladder, rectum and bones)."""
    axes = [np.arange(-a + spacing / 2, a, spacing) for a in half]
    x = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    x = x[~_inside_cut_organs(x, organs)]
    walls = np.minimum(_ellipsoid_distance(x, organs["bladder"]), _cylinder_distance(x, organs["rectum"], 2))
    sizes = np.minimum(np.interp(walls, GRADING, [organ_size * h, FAR_SIZE * h]),
                       np.interp(_ellipsoid_distance(x, organs["prostate"]), GRADING, [prostate_size * h, FAR_SIZE * h]))
    return float(np.sum(spacing**3 / sizes**3)) * CELLS_PER_VOLUME[3]


def _inside_cut_organs(x: np.ndarray, organs: dict) -> np.ndarray:
    """Points inside the bladder, the rectum (a cylinder along z) or a bone (along x)."""
    inside = np.sum(((x - organs["bladder"]["center"]) / organs["bladder"]["radii"]) ** 2, axis=1) < 1
    for name, axis in (("rectum", 2), ("pubis", 0), ("sacrum", 0)):
        inside |= _cylinder_distance(x, organs[name], axis, signed=True) < 0
    return inside


def _ellipsoid_distance(x: np.ndarray, organ: dict) -> np.ndarray:
    """Distance to an ellipsoid's surface, to first order (|q - 1| / |grad q| for
    q = |(x - c) / r|): exact on the surface, within ~20 % at the distances a size
    field grades over."""
    scaled = (x - organ["center"]) / organ["radii"]
    q = np.linalg.norm(scaled, axis=1)
    gradient = np.linalg.norm(scaled / organ["radii"], axis=1) / np.maximum(q, 1e-12)
    return np.abs(q - 1) / np.maximum(gradient, 1e-12)


def _cylinder_distance(x: np.ndarray, organ: dict, axis: int, signed: bool = False) -> np.ndarray:
    """Distance to a cylinder along ``axis`` from its ``center`` over its ``length``
    (gmsh's addCylinder); negative inside if ``signed``."""
    d = x - organ["center"]
    radial = np.linalg.norm(np.delete(d, axis, axis=1), axis=1) - organ["radius"]
    along = np.maximum(-d[:, axis], d[:, axis] - organ["length"])
    outside = np.hypot(np.maximum(radial, 0), np.maximum(along, 0))
    inside = np.maximum(radial, along)
    return np.where(inside < 0, inside if signed else -inside, outside)


def _inside(box, outer, tol=1e-6) -> bool:
    return all(box[i] >= outer[i] - tol and box[i + 3] <= outer[i + 3] + tol for i in range(3))


def build_prostate_phantom(out: Path, size: float | None = None, seed: int = 0, atlas: dict | None = None,
                           organ_size: float = ORGAN_SIZE, prostate_size: float = PROSTATE_SIZE) -> Path:
    """The pelvis phantom of patient ``seed``; element size ``size`` (cm) away from the
    organs, ``organ_size`` and ``prostate_size`` times it at their surfaces.

    With ``atlas`` (group -> (points, triangles), e.g. another phantom's bladder and
    rectum from ``read_surfaces``) those surfaces are not meshed afresh: the atlas
    triangles are fitted onto this patient's organs and the volume is meshed around
    them, so every patient built on one atlas has the same loaded nodes, in the same
    order (paper §3.3.3).

    The bones get the size of wherever they are, which for some patients and sizes is
    too coarse for gmsh (their surface mesh overlaps itself; 2 of 31 patients at
    h = 1.6): then they are meshed again at BONE_SIZE times their radius.
    """
    h = size or 1.0
    organs = phantom_organs(seed)
    _check_phantom_sizes(organs, h, organ_size, prostate_size)
    check_mesh_cost(f"prostate-phantom --size {h:g}", _phantom_cells(organs, PHANTOM_HALF, h, organ_size, prostate_size), 3, h)
    bone = BONE_SIZE * min(organs[b]["radius"] for b in PHANTOM_BONES)
    for bone_size in (None, bone):
        with GmshModel("phantom") as gmsh:
            faces = _phantom_geometry(gmsh, organs, seed)
            _phantom_sizes(gmsh, faces, h, organ_size, prostate_size, bone_size)
            try:
                _mesh_phantom(gmsh, faces, atlas, out / "phantom.msh")
                break
            except MeshingFailed as err:
                if bone_size is not None or err.groups != ["bones"]:
                    raise
    c = organs["bladder"]["center"]
    return _write_toml(out, PHANTOM_TOML.format(inflation=0.1, cx=c[0], cy=c[1], cz=c[2]))


def _phantom_geometry(gmsh, organs: dict, seed: int) -> dict[str, list[int]]:
    """The phantom in gmsh's OpenCASCADE kernel: tissue (box minus bladder, rectum and
    bones) around the prostate, as physical groups; returns the faces of each facet group."""
    occ = gmsh.model.occ
    half = PHANTOM_HALF

    def ellipsoid(organ):
        tag = occ.addSphere(*organ["center"], 1.0)
        occ.dilate([(3, tag)], *organ["center"], *organ["radii"])
        return tag

    body = occ.addBox(-half[0], -half[1], -half[2], 2 * half[0], 2 * half[1], 2 * half[2])
    r = organs["rectum"]
    cut = {"bladder": ellipsoid(organs["bladder"]), "rectum": occ.addCylinder(*r["center"], 0, 0, r["length"], r["radius"])}
    for b in PHANTOM_BONES:
        cut[b] = occ.addCylinder(*organs[b]["center"], organs[b]["length"], 0, 0, organs[b]["radius"])
    occ.synchronize()
    boxes = {name: gmsh.model.getBoundingBox(3, tag) for name, tag in cut.items()}
    tissue, _ = occ.cut([(3, body)], [(3, tag) for tag in cut.values()])
    occ.fragment(tissue, [(3, ellipsoid(organs["prostate"]))])
    occ.synchronize()

    volumes = sorted((occ.getMass(3, t), t) for _, t in gmsh.model.getEntities(3))
    prostate_vol, tissue_vol = volumes[0][1], volumes[-1][1]
    prostate_faces = [t for _, t in gmsh.model.getBoundary([(3, prostate_vol)], oriented=False)]
    outer = (-half[0], -half[1], -half[2], half[0], half[1], half[2])
    faces = {"bladder": [], "rectum": [], "bones": [], "skin": []}
    for _, face in gmsh.model.getBoundary([(3, tissue_vol)], oriented=False):
        if face in prostate_faces:
            continue
        box = gmsh.model.getBoundingBox(2, face)
        owner = next((name for name in boxes if _inside(box, boxes[name])), None)
        if owner is None:
            require(not _inside(box, outer, -1e-3), f"prostate-phantom seed {seed}: unclassified surface {face}")
        faces["bones" if owner in PHANTOM_BONES else owner or "skin"].append(face)

    gmsh.model.addPhysicalGroup(3, [tissue_vol], name="tissue")
    gmsh.model.addPhysicalGroup(3, [prostate_vol], name="prostate")
    for name, tags in faces.items():
        gmsh.model.addPhysicalGroup(2, tags, name=name)
    gmsh.model.addPhysicalGroup(2, prostate_faces, name="prostate_surface")
    return {**faces, "prostate_surface": prostate_faces}


def _phantom_sizes(gmsh, faces: dict, h: float, organ_size: float, prostate_size: float, bone_size=None) -> None:
    """Finer near the organs, finest at the prostate (its surface carries the stiffness
    signal: ~1e-3 cm per 10 % of E), coarser towards the skin; the bones at most
    ``bone_size`` if given. Quadratic (curved) elements: nodes on the organs' true
    surfaces, so the source and a target meshed differently agree on the shape (flat
    facets would differ by their sag, ~0.03 cm here: enough to bias E)."""
    field = gmsh.model.mesh.field
    sizes = [_graded_size(field, faces["bladder"] + faces["rectum"], organ_size * h, FAR_SIZE * h),
             _graded_size(field, faces["prostate_surface"], prostate_size * h, FAR_SIZE * h)]
    if bone_size is not None:
        sizes.append(field.add("Constant"))
        field.setNumbers(sizes[-1], "SurfacesList", faces["bones"])
        field.setNumber(sizes[-1], "VIn", bone_size)
        field.setNumber(sizes[-1], "VOut", 1e22)
    near = field.add("Min")
    field.setNumbers(near, "FieldsList", sizes)
    field.setAsBackgroundMesh(near)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
    gmsh.option.setNumber("Mesh.RandomSeed", 1)
    gmsh.option.setNumber("Mesh.ElementOrder", 2)


def _mesh_phantom(gmsh, faces: dict, atlas: dict | None, path: Path) -> None:
    """Mesh and write the phantom; around the atlas's loaded surfaces if given."""
    if atlas is None:
        _write_msh(gmsh, path, 3)
        return
    require(set(atlas) <= set(faces), f"atlas surfaces {sorted(atlas)}: the phantom has only {sorted(faces)}")
    _generate(gmsh, path, 2)
    surfaces = physical_surfaces(gmsh)
    for g, (points, triangles) in fit_surfaces(atlas, {g: surfaces[g] for g in atlas}).items():
        surfaces[g] = (_onto_geometry(gmsh, faces[g], points), triangles)
    shells = [g for g in faces if g != "prostate_surface"] + ["prostate_surface"]
    _mesh_inside(gmsh, surfaces, {"tissue": shells, "prostate": ["prostate_surface"]}, path)


def _write_toml(out: Path, text: str) -> Path:
    path = out / "problem.toml"
    path.write_text(text)
    return path


def build_scene(name: str, out, size: float | None = None, seed: int | None = None, atlas: dict | None = None,
                **detail) -> Path:
    """Write the named built-in scene's mesh and ``problem.toml`` into ``out``
    (``seed``, ``atlas``, ``detail`` = organ_size / prostate_size: see build_prostate_phantom)."""
    require(name in SCENES, f"unknown scene {name!r}; choose one of {', '.join(SCENES)}")
    require(size is None or (np.isfinite(size) and size > 0), f"--size must be a number > 0, got {size}")
    require(seed is None or name == "prostate-phantom", "--seed: only prostate-phantom varies with a seed")
    require(seed is None or seed >= 0, f"--seed must be >= 0 (0 is the nominal patient), got {seed}")
    detail = {k: v for k, v in detail.items() if v is not None}
    flags = {key: "--" + key.replace("_", "-") for key in detail}
    require(not detail or name == "prostate-phantom", f"{', '.join(flags.values())}: only prostate-phantom takes these")
    for key, value in detail.items():
        require(0 < value <= 1, f"{flags[key]} must be in (0, 1] (relative to --size), got {value}")
    out = Path(out)
    if name == "letter-a":
        return build_letter_a(out, size)
    if name == "cantilever":
        return build_cantilever(out, size)
    if name == "inclusion":
        return build_inclusion(out, size)
    return build_prostate_phantom(out, size, seed or 0, atlas, **detail)
