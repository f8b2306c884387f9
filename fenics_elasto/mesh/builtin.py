"""Built-in scenes: gmsh meshes plus a ready ``problem.toml`` (templates in ``meshes/*.toml``).

The 2D scenes are gmsh ``.geo`` sources in ``meshes/``; the prostate phantom is built
with gmsh's OpenCASCADE kernel here because ``--seed`` varies its organs.
"""

from __future__ import annotations

import importlib.resources
from pathlib import Path
from string import Template

import numpy as np

from fenics_elasto.mesh.atlas import fit_surfaces, mesh_inside, onto_geometry
from fenics_elasto.util.budget import CELLS_PER_VOLUME, check_mesh_cost
from fenics_elasto.util.errors import require
from fenics_elasto.mesh.gmsh_models import GmshModel, MeshingFailed, generate, node_positions, physical_surfaces, write_msh



def _scenes_folder() -> Path:
    """The scenes' sources: top-level meshes/, installed as the data package
    fenics_elasto.meshes; in a source tree put on the path by hand (the adjoint
    benchmark's own venv: an editable install's import hook is not read there), that
    folder itself."""
    try:
        return Path(str(importlib.resources.files("fenics_elasto.meshes")))
    except ModuleNotFoundError:
        return Path(__file__).resolve().parents[2] / "meshes"


GEO_DIR = _scenes_folder()
PROSTATE_STL = GEO_DIR / "prostate" / "prostate.stl"  # a real prostate surface (MIT; meshes/prostate/README.md)
SCENES = ("letter-a", "cantilever", "inclusion", "prostate-phantom")


def _mesh_geo(geo: str, path: Path, numbers: dict, default_size: float) -> None:
    """Mesh a 2D scene from its .geo source (``numbers``: its parameters, ``h`` the
    element size), after checking what the mesh will cost: the area comes from a mesh
    at the scene's default size."""
    with GmshModel(path.stem) as gmsh:
        _merge_geo(gmsh, geo, {**numbers, "h": default_size})
        generate(gmsh, path, 2)
        area = _mesh_area(gmsh)
        gmsh.clear()
        h = numbers["h"]
        check_mesh_cost(f"{path.stem.replace('_', '-')} --size {h:g}", area / h**2 * CELLS_PER_VOLUME[2], 2, h)
        _merge_geo(gmsh, geo, numbers)
        write_msh(gmsh, path, 2)


def _merge_geo(gmsh, geo: str, numbers: dict) -> None:
    for key, value in numbers.items():
        gmsh.parser.setNumber(key, [float(value)])
    gmsh.merge(str(GEO_DIR / geo))


def _mesh_area(gmsh) -> float:
    """The area of the current 2D mesh (its triangles' corners)."""
    position = node_positions(gmsh)
    area = 0.0
    for etype, nodes in zip(*gmsh.model.mesh.getElements(2)[::2]):
        corners = position[nodes.reshape(-1, gmsh.model.mesh.getElementProperties(etype)[3])[:, :3]]
        area += 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1).sum()
    return float(area)


def build_letter_a(out: Path, size: float | None = None) -> Path:
    _mesh_geo("letter_a.geo", out / "letter_a.msh", {"h": size or 0.4}, 0.4)
    return _write_toml(out, "letter_a.toml")


def build_cantilever(out: Path, size: float | None = None, length: float = 8.0, half_height: float = 1.0) -> Path:
    _mesh_geo("cantilever.geo", out / "cantilever.msh", {"h": size or 0.25, "L": length, "c": half_height}, 0.25)
    return _write_toml(out, "cantilever.toml")


def build_inclusion(out: Path, size: float | None = None, radius: float = 2.0) -> Path:
    _mesh_geo("inclusion.geo", out / "inclusion.msh", {"h": size or 0.5, "r": radius}, 0.5)
    return _write_toml(out, "inclusion.toml")


def phantom_organs(seed: int) -> dict:
    """Organ sizes and positions (cm); seed 0 is the nominal patient, others vary it.

    The jitter (radii +-8 %, centres +-0.15 cm) keeps every gap between organs open.
    """
    nominal: dict[str, dict] = {
        "bladder": {"center": [0.0, -0.3, 2.6], "radii": [2.3, 1.9, 1.5]},
        "prostate": {"center": [0.0, 0.0, -0.8], "radii": [1.6, 1.3, 1.1]},
        "rectum": {"center": [0.0, 2.9, -4.0], "radius": 0.9, "length": 5.0},
        "pubis": {"center": [-3.5, -3.0, -1.0], "radius": 0.7, "length": 7.0},
        "sacrum": {"center": [-3.0, 4.2, 2.5], "radius": 0.5, "length": 6.0},
    }
    if seed == 0:
        return nominal
    rng = np.random.default_rng(seed)
    organs: dict[str, dict] = {}
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
    return _write_toml(out, "phantom.toml", inflation=0.1, inflation_percent="10%",
                       cx=f"{c[0]:.4f}", cy=f"{c[1]:.4f}", cz=f"{c[2]:.4f}")


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
    faces: dict[str, list[int]] = {"bladder": [], "rectum": [], "bones": [], "skin": []}
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
    # Curving the boundary edges folds a few thin cells at the walls over (26 of 7,138
    # at h = 1.6, their Jacobian changes sign; the mesh check refuses such cells). gmsh
    # untangles them by optimising the high-order nodes of a layer around each, boundary
    # nodes kept on the surfaces: +0.1 s at h = 1.6 (one layer; its elastic variant,
    # HighOrderOptimize = 2, took 4.4 s).
    gmsh.option.setNumber("Mesh.HighOrderOptimize", 1)
    gmsh.option.setNumber("Mesh.HighOrderNumLayers", 1)


def _mesh_phantom(gmsh, faces: dict, atlas: dict | None, path: Path) -> None:
    """Mesh and write the phantom; around the atlas's loaded surfaces if given."""
    if atlas is None:
        write_msh(gmsh, path, 3)
        return
    require(set(atlas) <= set(faces), f"atlas surfaces {sorted(atlas)}: the phantom has only {sorted(faces)}")
    generate(gmsh, path, 2)
    surfaces = physical_surfaces(gmsh)
    for g, (points, triangles) in fit_surfaces(atlas, {g: surfaces[g] for g in atlas}).items():
        surfaces[g] = (onto_geometry(gmsh, faces[g], points), triangles)
    shells = [g for g in faces if g != "prostate_surface"] + ["prostate_surface"]
    mesh_inside(gmsh, surfaces, {"tissue": shells, "prostate": ["prostate_surface"]}, path)


def _write_toml(out: Path, template: str, **values) -> Path:
    """The scene's problem.toml from its template in meshes/ ($name placeholders filled)."""
    path = out / "problem.toml"
    path.write_text(Template((GEO_DIR / template).read_text()).substitute(values))
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
