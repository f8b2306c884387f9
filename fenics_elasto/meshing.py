"""Built-in scenes: gmsh meshes plus a ready ``problem.toml`` (templates in ``meshes/*.toml``).

The 2D scenes are gmsh ``.geo`` sources in ``meshes/``; the prostate phantom is built
with gmsh's OpenCASCADE kernel here because ``--seed`` varies its organs.
"""

from __future__ import annotations

from pathlib import Path
from string import Template

import numpy as np

from fenics_elasto.atlas import fit_surfaces, mesh_inside, onto_geometry
from fenics_elasto.errors import require
from fenics_elasto.gmsh_models import GmshModel, generate, physical_surfaces, write_msh

GEO_DIR = Path(__file__).parent / "meshes"
SCENES = ("letter-a", "cantilever", "inclusion", "prostate-phantom")


def _mesh_geo(geo: str, path: Path, dim: int, numbers: dict) -> None:
    with GmshModel(path.stem) as gmsh:
        for key, value in numbers.items():
            gmsh.parser.setNumber(key, [float(value)])
        gmsh.merge(str(GEO_DIR / geo))
        write_msh(gmsh, path, dim)







def build_letter_a(out: Path, size: float | None = None) -> Path:
    _mesh_geo("letter_a.geo", out / "letter_a.msh", 2, {"h": size or 0.4})
    return _write_toml(out, "letter_a.toml")


def build_cantilever(out: Path, size: float | None = None, length: float = 8.0, half_height: float = 1.0) -> Path:
    _mesh_geo("cantilever.geo", out / "cantilever.msh", 2, {"h": size or 0.25, "L": length, "c": half_height})
    return _write_toml(out, "cantilever.toml")


def build_inclusion(out: Path, size: float | None = None, radius: float = 2.0) -> Path:
    _mesh_geo("inclusion.geo", out / "inclusion.msh", 2, {"h": size or 0.5, "r": radius})
    return _write_toml(out, "inclusion.toml")


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


def _graded_size(field, faces: list[int], size_min: float, size_max: float) -> int:
    """A gmsh size field: size_min within 0.3 cm of the faces, growing to size_max at 4 cm."""
    dist = field.add("Distance")
    field.setNumbers(dist, "SurfacesList", faces)
    thr = field.add("Threshold")
    field.setNumber(thr, "InField", dist)
    field.setNumber(thr, "SizeMin", size_min)
    field.setNumber(thr, "SizeMax", size_max)
    field.setNumber(thr, "DistMin", 0.3)
    field.setNumber(thr, "DistMax", 4.0)
    return thr


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
    """
    h = size or 1.0
    organs = phantom_organs(seed)
    half = (6.0, 5.0, 5.0)
    with GmshModel("phantom") as gmsh:
        occ = gmsh.model.occ

        def ellipsoid(organ):
            tag = occ.addSphere(*organ["center"], 1.0)
            occ.dilate([(3, tag)], *organ["center"], *organ["radii"])
            return tag

        body = occ.addBox(-half[0], -half[1], -half[2], 2 * half[0], 2 * half[1], 2 * half[2])
        bladder = ellipsoid(organs["bladder"])
        r = organs["rectum"]
        rectum = occ.addCylinder(*r["center"], 0, 0, r["length"], r["radius"])
        bones = [
            occ.addCylinder(*organs[b]["center"], organs[b]["length"], 0, 0, organs[b]["radius"])
            for b in ("pubis", "sacrum")
        ]
        boxes = {}
        occ.synchronize()
        for name, tag in (("bladder", bladder), ("rectum", rectum), ("pubis", bones[0]), ("sacrum", bones[1])):
            boxes[name] = gmsh.model.getBoundingBox(3, tag)
        tissue, _ = occ.cut([(3, body)], [(3, bladder), (3, rectum)] + [(3, b) for b in bones])
        prostate = ellipsoid(organs["prostate"])
        occ.fragment(tissue, [(3, prostate)])
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
            if _inside(box, boxes["bladder"]):
                faces["bladder"].append(face)
            elif _inside(box, boxes["rectum"]):
                faces["rectum"].append(face)
            elif _inside(box, boxes["pubis"]) or _inside(box, boxes["sacrum"]):
                faces["bones"].append(face)
            else:
                require(not _inside(box, outer, -1e-3), f"prostate-phantom seed {seed}: unclassified surface {face}")
                faces["skin"].append(face)

        gmsh.model.addPhysicalGroup(3, [tissue_vol], name="tissue")
        gmsh.model.addPhysicalGroup(3, [prostate_vol], name="prostate")
        for name, tags in faces.items():
            gmsh.model.addPhysicalGroup(2, tags, name=name)
        gmsh.model.addPhysicalGroup(2, prostate_faces, name="prostate_surface")

        # Finer near the organs, finest at the prostate (its surface carries the
        # stiffness signal: ~1e-3 cm per 10 % of E), coarser towards the skin.
        field = gmsh.model.mesh.field
        near = field.add("Min")
        field.setNumbers(near, "FieldsList", [
            _graded_size(field, faces["bladder"] + faces["rectum"], organ_size * h, 1.6 * h),
            _graded_size(field, prostate_faces, prostate_size * h, 1.6 * h)])
        field.setAsBackgroundMesh(near)
        gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
        gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
        gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
        gmsh.option.setNumber("Mesh.RandomSeed", 1)
        # Quadratic (curved) elements: nodes on the organs' true surfaces, so the source
        # and a target meshed differently agree on the shape (flat facets would differ
        # by their sag, ~0.03 cm here: enough to bias E).
        gmsh.option.setNumber("Mesh.ElementOrder", 2)
        if atlas is None:
            write_msh(gmsh, out / "phantom.msh", 3)
        else:
            require(set(atlas) <= set(faces), f"atlas surfaces {sorted(atlas)}: the phantom has only {sorted(faces)}")
            generate(gmsh, out / "phantom.msh", 2)
            surfaces = physical_surfaces(gmsh)
            for g, (points, triangles) in fit_surfaces(atlas, {g: surfaces[g] for g in atlas}).items():
                surfaces[g] = (onto_geometry(gmsh, faces[g], points), triangles)
            mesh_inside(gmsh, surfaces, {"tissue": list(faces) + ["prostate_surface"],
                                          "prostate": ["prostate_surface"]}, out / "phantom.msh")

    c = organs["bladder"]["center"]
    return _write_toml(out, "phantom.toml", inflation=0.1, inflation_percent="10%", cx=f"{c[0]:.4f}", cy=f"{c[1]:.4f}", cz=f"{c[2]:.4f}")


def _write_toml(out: Path, template: str, **values) -> Path:
    """The scene's problem.toml from its template in meshes/ ($name placeholders filled)."""
    path = out / "problem.toml"
    path.write_text(Template((GEO_DIR / template).read_text()).substitute(values))
    return path


def build_scene(name: str, out, size: float | None = None, seed: int = 0, atlas: dict | None = None,
                **detail) -> Path:
    """Write the named built-in scene's mesh and ``problem.toml`` into ``out``
    (``atlas``, ``detail`` = organ_size / prostate_size: see build_prostate_phantom)."""
    require(name in SCENES, f"unknown scene {name!r}; choose one of {', '.join(SCENES)}")
    require(size is None or size > 0, f"--size must be > 0, got {size}")
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
    return build_prostate_phantom(out, size, seed, atlas, **detail)
