"""Targets made by an independent FE code, to judge the estimator against.

The toolkit's own tests simulate their targets with the toolkit (DOLFINx) on its own
meshes, so a bias shared by the simulation and the estimate -- the same element, the
same way of putting a curved boundary into a mesh -- cannot show. Here the truth comes
from elsewhere at every step:

- the FE code is scikit-fem: P2 vector Lagrange, linear elasticity (plane strain in
  2D), on quadratic (curved) gmsh meshes read through gmsh's API into MeshTri2 /
  MeshTet2, meshed with other algorithms and much finer than the toolkit's sources;
- the targets are sampled on the exact geometry (polygon edges, the exact circle,
  parametric ellipsoids and cylinders), finely, and moved by the scikit-fem
  displacement; a sample a hair outside the curved mesh gets the polynomial of its
  nearest element (``evaluate``);
- the organ motion of the 3D phantom is not affine (inflation + shift + a ripple).

Cases (each returns the paths of the files it wrote, cached on disk by parameters):
``letter_a`` (nu sweep), ``inclusion`` (E-ratio sweep, with a user-style straight-sided
source scene) and ``phantom`` (prostate E sweep, organ surfaces + fiducials).
File formats are those ``fenics_elasto.surface`` reads: 2D targets are .vtp polylines
in z = 0, 3D targets triangle .vtp, landmarks CSV rows ``x,y,z,X,Y,Z``.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from contextlib import contextmanager
from functools import lru_cache
from pathlib import Path
from typing import NamedTuple
from collections.abc import Callable

import numpy as np
import scipy.sparse.linalg as spla
from scipy.spatial import cKDTree

GEO_DIR = Path(__file__).resolve().parents[1] / "meshes"

# --------------------------------------------------------------------------- gmsh -> scikit-fem

GMSH_QUADRATIC = {2: (9, 8), 3: (11, 9)}  # dim -> (cell, facet) types: 6-node tri + 3-node line, 10-node tet + 6-node tri
NODES_PER_ELEMENT = {8: 3, 9: 6, 11: 10}
# gmsh's 10-node tet lists its edges 01 12 20 30 32 31; scikit-fem's are 01 12 02 03 13 23.
GMSH_TO_SKFEM = {2: [0, 1, 2, 3, 4, 5], 3: [0, 1, 2, 3, 4, 5, 6, 7, 9, 8]}


class FEMesh(NamedTuple):
    """A scikit-fem quadratic mesh with the gmsh physical groups: cell indices per
    region, facet indices per boundary group."""

    mesh: object
    regions: dict
    facets: dict


@contextmanager
def gmsh_model(name: str):
    """A fresh, quiet gmsh model with default options (options are global)."""
    import gmsh

    if not gmsh.isInitialized():
        gmsh.initialize(interruptible=False)
    gmsh.option.setNumber("General.Terminal", 0)
    gmsh.clear()
    gmsh.option.restoreDefaults()
    gmsh.option.setNumber("General.Terminal", 0)
    gmsh.model.add(name)
    try:
        yield gmsh
    finally:
        gmsh.clear()


def _elements(gmsh, etype: int, dim: int, index: np.ndarray) -> dict:
    """Entity tag -> (n, nodes) rows of 0-based node indices of its elements of one type."""
    out = {}
    for _, entity in gmsh.model.getEntities(dim):
        _, nodes = gmsh.model.mesh.getElementsByType(etype, entity)
        out[entity] = index[np.asarray(nodes, np.int64)].reshape(-1, NODES_PER_ELEMENT[etype])
    return out


def _groups(gmsh, dim: int) -> dict:
    """Physical group name -> its entity tags."""
    return {gmsh.model.getPhysicalName(d, t): gmsh.model.getEntitiesForPhysicalGroup(d, t)
            for d, t in gmsh.model.getPhysicalGroups(dim)}


def _facet_keys(vertices: np.ndarray, n: int) -> np.ndarray:
    """One integer per facet from its sorted vertex indices (columns)."""
    v = np.sort(vertices, axis=0).astype(np.int64)
    return v[0] * n * n + v[1] * n + (v[2] if len(v) > 2 else 0)


def quadratic_mesh(gmsh, dim: int) -> FEMesh:
    """The current gmsh model's second-order mesh as a scikit-fem MeshTri2/MeshTet2
    (curved: the edge nodes sit where gmsh put them, on the CAD geometry)."""
    from skfem import MeshTet2, MeshTri2

    tags, coords, _ = gmsh.model.mesh.getNodes()
    index = np.full(int(tags.max()) + 1, -1, np.int64)
    index[tags] = np.arange(len(tags))
    points = coords.reshape(-1, 3)[:, :dim]
    by_entity = _elements(gmsh, GMSH_QUADRATIC[dim][0], dim, index)
    assert sum(len(c) for c in by_entity.values()), "gmsh made no quadratic cells (see its log)"
    order = list(by_entity)
    cells = np.concatenate([by_entity[e] for e in order])[:, GMSH_TO_SKFEM[dim]]
    start = dict(zip(order, np.cumsum([0] + [len(by_entity[e]) for e in order])))
    regions = {name: np.concatenate([np.arange(start[e], start[e] + len(by_entity[e])) for e in ents])
               for name, ents in _groups(gmsh, dim).items()}

    mesh = (MeshTri2 if dim == 2 else MeshTet2)(points.T.copy(), cells.T.copy())
    return FEMesh(mesh, regions, _facet_groups(gmsh, mesh, cells, index))


def _facet_groups(gmsh, mesh, cells: np.ndarray, index: np.ndarray) -> dict:
    """Facet group name -> scikit-fem facet indices, matched by their vertices."""
    dim = mesh.dim()
    vertex_of = np.full(len(index), -1, np.int64)  # scikit-fem numbers the vertices first, in sorted order
    used = np.unique(cells[:, :dim + 1])
    vertex_of[used] = np.arange(len(used))
    n = mesh.nvertices
    mesh_keys = _facet_keys(mesh.facets, n)
    sort = np.argsort(mesh_keys)
    facet_rows = _elements(gmsh, GMSH_QUADRATIC[dim][1], dim - 1, index)
    facets = {}
    for name, ents in _groups(gmsh, dim - 1).items():
        rows = np.concatenate([facet_rows[e][:, :dim] for e in ents])
        keys = _facet_keys(vertex_of[rows].T, n)
        at = sort[np.minimum(np.searchsorted(mesh_keys, keys, sorter=sort), len(sort) - 1)]
        assert (mesh_keys[at] == keys).all(), f"facet group {name}: facets not in the mesh"
        facets[name] = at
    return facets


# --------------------------------------------------------------------------- the FE solve


def lame(E: float, nu: float) -> tuple[float, float]:
    """(lambda, mu); in 2D this is plane strain (the 3D constants, eps_zz = 0)."""
    return E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))


class Elasticity:
    """P2 linear elasticity on an FEMesh: per region the matrices of the mu and the
    lambda terms, assembled once, so that any material assignment is a sum."""

    def __init__(self, fe: FEMesh, intorder: int = 4):
        from skfem import Basis, ElementTetP2, ElementTriP2, ElementVector

        self.fe = fe
        scalar = ElementTetP2() if fe.mesh.dim() == 3 else ElementTriP2()
        self.basis = Basis(fe.mesh, ElementVector(scalar), intorder=intorder)  # curved: J varies in a cell
        _check_orientation(self.basis)
        self.parts = {name: elasticity_parts(Basis(fe.mesh, scalar, intorder=intorder, elements=cells))
                      for name, cells in fe.regions.items()}

    def stiffness(self, materials: dict):
        """K for ``materials``: region -> (E, nu); every region must have one."""
        K = 0
        for name, (mu_part, lambda_part) in self.parts.items():
            lam, mu = lame(*materials[name])
            K = K + mu * mu_part + lam * lambda_part
        return K.tocsr()

    def prescribed(self, motions: dict) -> tuple[np.ndarray, np.ndarray]:
        """(dofs, values) of the boundary groups' displacement: group -> u(points (dim, n))
        -> (dim, n), taken at the P2 nodes (on the curved geometry)."""
        dim = self.fe.mesh.dim()
        values = np.zeros(self.basis.N)
        dofs = []
        for group, motion in motions.items():
            view = self.basis.get_dofs(self.fe.facets[group])
            for c in range(dim):
                rows = view.all(f"u^{c + 1}")
                values[rows] = np.asarray(motion(self.basis.doflocs[:, rows]))[c]
                dofs.append(rows)
        return np.unique(np.concatenate(dofs)), values

    def solve(self, materials: dict, motions: dict, tol: float = 1e-11) -> np.ndarray:
        """The displacement (DOF vector) with the given groups moved, the rest free."""
        from skfem import condense

        dofs, values = self.prescribed(motions)
        A, b, x, free = condense(self.stiffness(materials), np.zeros(self.basis.N), x=values, D=dofs)
        x = x.copy()
        x[free] = _linear_solve(A, b, self.basis.doflocs[:, free], free % self.fe.mesh.dim(), tol)
        return x


def elasticity_parts(scalar_basis) -> tuple:
    """The (mu, lambda) matrices of 2 mu eps(u):eps(v) + lambda div u div v on the vector
    P2 space (DOF dim * node + component, scikit-fem's order), from the scalar
    matrices G_ab = (d_a phi_i, d_b phi_j): block (a, b) is delta_ab sum_c G_cc + G_ba
    for mu and G_ab for lambda. (scikit-fem's vector-valued form gives the same, at
    ~15x the assembly time for 3D P2 on curved cells.)"""
    import scipy.sparse as sp
    from skfem import BilinearForm, asm

    dim = scalar_basis.mesh.dim()
    G = {}
    for a in range(dim):
        for b in range(a, dim):
            G[a, b] = asm(BilinearForm(lambda u, v, w, a=a, b=b: v.grad[a] * u.grad[b]), scalar_basis).tocsr()
            G[b, a] = G[a, b].T.tocsr()
    laplace = sum(G[c, c] for c in range(dim))
    unit = np.eye(dim)
    mu_part = sum(sp.kron(G[b, a] + (laplace if a == b else 0), np.outer(unit[a], unit[b]))
                  for a in range(dim) for b in range(dim))
    lambda_part = sum(sp.kron(G[a, b], np.outer(unit[a], unit[b])) for a in range(dim) for b in range(dim))
    return mu_part.tocsr(), lambda_part.tocsr()


def _check_orientation(basis) -> None:
    """No curved cell folded over itself (scikit-fem integrates |det J|: a folded
    cell would be silently wrong): det J keeps one sign within every cell."""
    det = basis.mapping.detDF(basis.X, tind=basis.tind)
    mixed = (det.min(axis=1) < 0) & (det.max(axis=1) > 0)
    assert not mixed.any(), f"{mixed.sum()} curved cells fold over (det J changes sign)"


def _linear_solve(A, b, points: np.ndarray, component: np.ndarray, tol: float) -> np.ndarray:
    """Direct (SuperLU) in 2D; in 3D, CG preconditioned by smoothed-aggregation AMG with
    the rigid-body modes as near-null space (a direct solve of 3D P2 is slow here).
    ``points``, ``component``: each unknown's location and displacement component."""
    if points.shape[0] == 2:
        return spla.spsolve(A.tocsc(), b)
    import pyamg

    solver = pyamg.smoothed_aggregation_solver(A, B=_rigid_body_modes(points, component), coarse_solver="splu")
    residuals = []
    x = solver.solve(b, tol=tol, accel="cg", maxiter=500, residuals=residuals)
    assert residuals[-1] <= tol * 10 * residuals[0], f"AMG-CG stalled at relative residual {residuals[-1] / residuals[0]:.1e}"
    return x


def _rigid_body_modes(points: np.ndarray, component: np.ndarray) -> np.ndarray:
    """(n, 6) translations and rotations of 3D space at n unknowns: their locations
    (3, n) and displacement components (0, 1, 2)."""
    n = points.shape[1]
    x, y, z = points
    modes = np.zeros((n, 6))
    modes[np.arange(n), component] = 1.0
    rotations = [(-y, x, 0 * x), (0 * x, -z, y), (z, 0 * x, -x)]
    for k, rotation in enumerate(rotations):
        modes[:, 3 + k] = np.choose(component, rotation)
    return modes


# --------------------------------------------------------------------------- evaluation anywhere


def _straight_coordinates(mesh, points: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Reference coordinates (dim, n, 1) of points (dim, n) in the straight-sided
    simplices of the cells' vertices (reference vertex k + 1 at the unit vector e_k)."""
    corners = mesh.p[:, mesh.t[:, cells]]  # (dim, dim + 1, n)
    edges = np.moveaxis(corners[:, 1:] - corners[:, :1], 2, 0)  # (n, dim, dim), columns are edges
    return np.linalg.solve(edges, (points - corners[:, 0]).T[:, :, None])[:, :, 0].T[:, :, None]


def _reference_coordinates(mapping, points: np.ndarray, cells: np.ndarray, X: np.ndarray,
                           iterations: int = 25) -> np.ndarray:
    """Reference coordinates (dim, n, 1) of points (dim, n) in the given (curved) cells,
    by Newton on the isoparametric map from X, not clipped to the cell: outside points
    get coordinates outside the reference simplex."""
    X = X.copy()
    active = np.arange(points.shape[1])
    for _ in range(iterations):
        sub = X[:, active]
        step = np.einsum("ijkl,jkl->ikl", mapping.invDF(sub, cells[active]),
                         points[:, active, None] - mapping.F(sub, cells[active]))
        X[:, active] = np.clip(sub + step, -1.0, 2.0)  # far candidates must not diverge
        active = active[np.abs(step).max(axis=(0, 2)) > 1e-13]
        if not len(active):
            break
    return X


def _barycentric(X: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (dim + 1, n) of reference coordinates (dim, n, 1): the
    weight of reference vertex 0 last, then vertices 1..dim."""
    return np.concatenate([X[:, :, 0], 1.0 - X[:, :, 0].sum(axis=0, keepdims=True)])


def _outside(X: np.ndarray) -> np.ndarray:
    """How far reference coordinates lie outside the simplex (0 inside)."""
    return np.maximum(-_barycentric(X).min(axis=0), 0.0)


def _beyond_boundary(mesh, cells: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Whether the facet a point is most outside of is on the mesh boundary: then no
    cell lies beyond it, and the point is outside the mesh, not in another cell."""
    facets = mesh.refdom.facets
    vertex = np.r_[np.arange(1, mesh.dim() + 1), 0]  # row of _barycentric -> reference vertex
    opposite = np.array([next(f for f, verts in enumerate(facets) if v not in verts) for v in vertex])
    worst = np.argmin(_barycentric(X), axis=0)
    facet = mesh.t2f[opposite[worst], cells]
    return mesh.f2t[1, facet] == -1


def locate(basis, points: np.ndarray, candidates: int = 12, inside: float = 1e-9, hair: float = 1e-2):
    """For points (n, dim): (cell, reference coordinates (dim, n, 1), outside measure).
    The cell contains the point; or, for a point a hair outside the curved mesh, is a
    cell that it is outside of across a boundary facet by less than ``hair`` (in
    reference coordinates): the point gets the polynomial of its own boundary cell;
    failing both, the least outside candidate. Candidates are the cells with the nearest
    centroids (12, then 60 for the points not placed yet), tried nearest first, each
    only for the points not placed yet."""
    mesh = basis.mesh
    tree = cKDTree(mesh.doflocs[:, mesh.t].mean(axis=1).T)
    cell = np.zeros(len(points), np.int64)
    X = np.zeros((points.shape[1], len(points), 1))
    outside = np.full(len(points), np.inf)
    todo = np.arange(len(points))
    for k in (candidates, 5 * candidates):
        near = tree.query(points[todo], k=k)[1]
        for j in range(k):
            trial = _straight_coordinates(mesh, points[todo].T, near[:, j])
            close = _outside(trial) < 0.5  # Newton only where the straight cell is near the point
            trial[:, close] = _reference_coordinates(basis.mapping, points[todo[close]].T, near[close, j],
                                                     trial[:, close])
            measure = _outside(trial)
            better = measure < outside[todo]
            rows = todo[better]
            cell[rows], X[:, rows], outside[rows] = near[better, j], trial[:, better], measure[better]
            placed = (outside[todo] <= inside) | ((outside[todo] < hair) & _beyond_boundary(mesh, cell[todo], X[:, todo]))
            todo, near = todo[~placed], near[~placed]
    return cell, X, outside


def evaluate(basis, u: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The P2 displacement (n, dim) at arbitrary points (n, dim) (see ``locate``)."""
    cells, X, _ = locate(basis, points)
    dim = points.shape[1]
    values = np.zeros((dim, len(points)))
    for k in range(basis.Nbfun):
        phi = np.asarray(basis.elem.gbasis(basis.mapping, X, k, tind=cells)[0])[:, :, 0]  # (dim, n)
        values += phi * u[basis.element_dofs[k, cells]]
    return values.T


# --------------------------------------------------------------------------- exact geometry, sampled


def sample_segment(a, b, spacing: float) -> np.ndarray:
    """Points from a to b (both included), at most ``spacing`` apart."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    n = max(1, int(np.ceil(np.linalg.norm(b - a) / spacing)))
    return a + np.linspace(0.0, 1.0, n + 1)[:, None] * (b - a)


def sample_circle(center, radius: float, spacing: float) -> np.ndarray:
    """Points on the exact circle, at most ``spacing`` apart along it, the first repeated
    at the end (a closed polyline)."""
    n = max(8, int(np.ceil(2 * np.pi * radius / spacing)))
    angle = np.linspace(0.0, 2 * np.pi, n + 1)
    angle[-1] = 0.0
    return np.asarray(center, float) + radius * np.c_[np.cos(angle), np.sin(angle)]


def ellipsoid_surface(center, radii, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """(points, triangles) of an icosphere mapped onto the ellipsoid: every point exactly
    on it, edges at most about ``spacing`` long."""
    import pyvista as pv

    longest = max(radii)
    nsub = int(np.clip(np.round(np.log2(1.05 * longest / spacing)), 1, 8))  # icosahedron edge ~1.05 r, halved per level
    sphere = pv.Icosphere(radius=1.0, nsub=nsub)
    unit = np.asarray(sphere.points, np.float64)
    unit /= np.linalg.norm(unit, axis=1, keepdims=True)  # pyvista's points are float32
    return np.asarray(center) + unit * np.asarray(radii), sphere.faces.reshape(-1, 4)[:, 1:]


def revolution_surface(center, radii: np.ndarray, heights: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """(points, triangles) of a closed surface of revolution about the z axis through
    ``center``: rings (radius, height) from one pole to the other; a ring of radius 0
    is one point. For the rectum cylinder with its flat end caps."""
    n = max(12, int(np.ceil(2 * np.pi * max(radii) / spacing)))
    angle = 2 * np.pi * np.arange(n) / n
    ring_start, points = [], []
    for r, h in zip(radii, heights):
        ring_start.append(sum(len(p) for p in points))
        count = 1 if r == 0 else n
        points.append(np.c_[r * np.cos(angle[:count]), r * np.sin(angle[:count]), np.full(count, h)])
    triangles = []
    j, j1 = np.arange(n), (np.arange(n) + 1) % n
    for k in range(len(radii) - 1):
        a, b = ring_start[k], ring_start[k + 1]
        lower = a + (0 * j if radii[k] == 0 else j)
        lower1 = a + (0 * j if radii[k] == 0 else j1)
        upper = b + (0 * j if radii[k + 1] == 0 else j)
        upper1 = b + (0 * j if radii[k + 1] == 0 else j1)
        if radii[k] != 0:
            triangles.append(np.c_[lower, lower1, upper1])
        if radii[k + 1] != 0:
            triangles.append(np.c_[lower, upper1, upper])
    return np.asarray(center) + np.concatenate(points), np.concatenate(triangles)


def cylinder_surface(base, radius: float, length: float, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """The closed cylinder gmsh's ``addCylinder(*base, 0, 0, length, radius)`` makes:
    side plus two flat caps, every point exactly on it."""
    caps = np.linspace(0.0, radius, max(2, int(np.ceil(radius / spacing)) + 1))
    side = np.linspace(0.0, length, max(2, int(np.ceil(length / spacing)) + 1))
    radii = np.r_[caps, np.full(len(side) - 2, radius), caps[::-1]]
    heights = np.r_[np.zeros(len(caps)), side[1:-1], np.full(len(caps), length)]
    return revolution_surface(base, radii, heights, spacing)


# --------------------------------------------------------------------------- files


def write_polylines(path: Path, polylines: list[np.ndarray]) -> Path:
    """2D polylines (each (n, 2)) as one .vtp of line cells in the z = 0 plane."""
    import pyvista as pv

    points = np.concatenate(polylines)
    starts = np.cumsum([0] + [len(p) for p in polylines[:-1]])
    lines = np.concatenate([np.r_[len(p), s + np.arange(len(p))] for s, p in zip(starts, polylines)])
    pv.PolyData(np.c_[points, np.zeros(len(points))], lines=lines).save(str(path))
    return path


def write_triangles(path: Path, points: np.ndarray, triangles: np.ndarray) -> Path:
    import pyvista as pv

    faces = np.c_[np.full(len(triangles), 3), triangles].ravel()
    pv.PolyData(np.asarray(points, float), faces=faces).save(str(path))
    return path


def write_landmarks(path: Path, source: np.ndarray, target: np.ndarray) -> Path:
    """CSV rows ``x,y,z,X,Y,Z``: a source point and where it moved."""
    dim = source.shape[1]
    header = ",".join([f"x{i}" for i in range(dim)] + [f"X{i}" for i in range(dim)])
    np.savetxt(path, np.c_[source, target], delimiter=",", header=header, comments="", fmt="%.12g")
    return path


def noisy_copy(path: Path, out: Path, std: float, rng) -> Path:
    """A copy of a target file with Gaussian noise of ``std`` on every point, in every
    direction the target has (2D targets stay in the z = 0 plane)."""
    import pyvista as pv

    mesh = pv.read(str(path))
    noise = std * rng.standard_normal(mesh.points.shape)
    if np.allclose(mesh.points[:, 2], 0.0):
        noise[:, 2] = 0.0
    mesh.points = mesh.points + noise
    mesh.save(str(out))
    return Path(out)


def cached(out, case: str, params: dict, make: Callable[[Path], dict]) -> dict:
    """``make(folder)`` -> {name: path} run once per parameter set: the folder
    ``out/case-<hash of params>`` keeps the files and a list of them."""
    key = hashlib.sha1(json.dumps(params, sort_keys=True).encode()).hexdigest()[:12]
    folder = Path(out) / f"{case}-{key}"
    index = folder / "files.json"
    if index.is_file():
        return {name: folder / rel for name, rel in json.loads(index.read_text())["files"].items()}
    folder.mkdir(parents=True, exist_ok=True)
    files = make(folder)
    relative = {name: str(Path(p).relative_to(folder)) for name, p in files.items()}
    index.write_text(json.dumps({"case": case, "params": params, "files": relative}, indent=1))
    return files


# --------------------------------------------------------------------------- case 1: letter A


def _curve_ends(gmsh, curve: int) -> tuple[np.ndarray, np.ndarray]:
    a, b = (np.array(gmsh.model.getValue(0, p, [])) for _, p in gmsh.model.getBoundary([(1, curve)], oriented=True))
    return a[:2], b[:2]


def _refine_towards(gmsh, entities: list, dim: int, size: float, ratio: float = 10.0, reach: float = 1.0) -> int:
    """A size field (its tag, also made the background mesh): ``size / ratio`` at the
    entities (corners, where the stress is singular and P2 converges slowly), growing
    linearly to ``size`` at ``reach``."""
    field = gmsh.model.mesh.field
    dist = field.add("Distance")
    field.setNumbers(dist, "PointsList" if dim == 0 else "CurvesList", entities)
    thr = field.add("Threshold")
    field.setNumber(thr, "InField", dist)
    field.setNumber(thr, "SizeMin", size / ratio)
    field.setNumber(thr, "SizeMax", size)
    field.setNumber(thr, "DistMin", 0.02)
    field.setNumber(thr, "DistMax", reach)
    field.setAsBackgroundMesh(thr)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    return thr


@lru_cache(maxsize=1)
def letter_a_model(size: float):
    """The letter A of ``letter_a.geo`` meshed P2 (Delaunay, not the toolkit's
    Frontal-Delaunay) at ``size``: (Elasticity, outline as a list of straight edges)."""
    with gmsh_model("letter-a-truth") as gmsh:
        gmsh.parser.setNumber("h", [float(size)])
        gmsh.merge(str(GEO_DIR / "letter_a.geo"))
        gmsh.option.setNumber("Mesh.Algorithm", 5)
        gmsh.option.setNumber("Mesh.ElementOrder", 2)
        _refine_towards(gmsh, [t for _, t in gmsh.model.getEntities(0)], dim=0, size=size)
        gmsh.model.mesh.generate(2)
        fe = quadratic_mesh(gmsh, 2)
        outline = _groups(gmsh, 1)["outline"]
        edges = [_curve_ends(gmsh, c) for c in outline]
    return Elasticity(fe), edges


def letter_a(out, nu: float, top=(0.4, -0.8), E: float = 10.0, size: float = 0.16, spacing: float = 0.01) -> dict:
    """The letter A (feet clamped, top moved by ``top``) solved at (E, nu) by scikit-fem;
    ``{"target": .vtp}``: the displaced outline (outer contour and hole), sampled every
    ``spacing`` on the exact straight edges."""
    params = {"nu": nu, "top": list(top), "E": E, "size": size, "spacing": spacing}

    def make(folder):
        model, edges = letter_a_model(size)
        u = model.solve({"letter": (E, nu)}, {"feet": constant_motion((0.0, 0.0)), "top": constant_motion(top)})
        polylines = [sample_segment(a, b, spacing) for a, b in edges]
        moved = [p + evaluate(model.basis, u, p) for p in polylines]
        return {"target": write_polylines(folder / "target.vtp", moved)}

    return cached(out, "letter-a", params, make)


def constant_motion(value) -> Callable:
    """u(x) = value: a group moved rigidly (or clamped)."""
    return lambda x: np.asarray(value, float)[:, None] * np.ones(x.shape[1])


# --------------------------------------------------------------------------- case 2: inclusion, a user's scene

BLOCK = (10.0, 6.0)  # width, height: the block [-5, 5] x [-3, 3]

INCLUSION_PROBLEM = """\
# A user's scene: stiff circular inclusion (r = {radius}) in a 10 x 6 block, meshed
# straight-sided (order-1 geometry) at h = {size}. Bottom clamped, top loaded.
mesh = "source.msh"
plane = "strain"
degree = 2

[materials.inclusion]
E  = {{ estimate = true, initial = 30.0, bounds = [1.0, 1000.0] }}
nu = 0.3

[materials.matrix]
E  = 10.0
nu = 0.3

[boundary]
fixed   = ["bottom"]
loaded  = ["top"]
matched = ["outline", "interface"]

[target]
surfaces = {{ outline = "target_outline.vtp", interface = "target_interface.vtp" }}
"""


# The top's default motion: shifted, stretched 5 %, bent by 0.5 at the corners. (A 10 %
# stretch, (0.25, 0.1, -0.3, -0.02), is a harder case: see benchmarks/independent.py.)
INCLUSION_TOP = (0.3, 0.05, -0.5, -0.02)


def inclusion_top_motion(top=INCLUSION_TOP) -> Callable:
    """The top's prescribed displacement u(x) = (a + b x, c + d x^2) for top = (a, b, c,
    d): smooth, not affine (sheared, stretched by b, bent by d)."""
    a, b, c, d = top
    return lambda x: np.array([a + b * x[0], c + d * x[0] ** 2])


def _inclusion_geometry(gmsh, center, radius: float) -> None:
    """Block with a circular inclusion and the physical groups of a user's scene."""
    occ = gmsh.model.occ
    w, h = BLOCK
    block = occ.addRectangle(-w / 2, -h / 2, 0, w, h)
    disk = occ.addDisk(center[0], center[1], 0, radius, radius)
    occ.fragment([(2, block)], [(2, disk)])
    occ.synchronize()
    inclusion = [t for _, t in gmsh.model.getEntities(2) if abs(occ.getMass(2, t) - np.pi * radius**2) < 1e-6]
    matrix = [t for _, t in gmsh.model.getEntities(2) if t not in inclusion]
    gmsh.model.addPhysicalGroup(2, matrix, name="matrix")
    gmsh.model.addPhysicalGroup(2, inclusion, name="inclusion")
    gmsh.model.addPhysicalGroup(1, [t for _, t in gmsh.model.getBoundary([(2, inclusion[0])], oriented=False)],
                                name="interface")
    sides = {"bottom": [], "top": [], "outline": []}
    for _, curve in gmsh.model.getBoundary([(2, t) for t in matrix + inclusion], oriented=False):
        x0, y0, _, x1, y1, _ = gmsh.model.getBoundingBox(1, curve)
        sides["outline"].append(curve)
        if y1 < -h / 2 + 1e-6:
            sides["bottom"].append(curve)
        elif y0 > h / 2 - 1e-6:
            sides["top"].append(curve)
    for name, curves in sides.items():
        gmsh.model.addPhysicalGroup(1, curves, name=name)


@lru_cache(maxsize=1)
def inclusion_model(center: tuple, radius: float, size: float) -> Elasticity:
    """The inclusion block meshed P2 with curved elements (Delaunay), ``size`` in the
    block, half of it along the interface, a tenth at the corners."""
    with gmsh_model("inclusion-truth") as gmsh:
        _inclusion_geometry(gmsh, center, radius)
        gmsh.option.setNumber("Mesh.Algorithm", 5)
        gmsh.option.setNumber("Mesh.ElementOrder", 2)
        interface = gmsh.model.getEntitiesForPhysicalGroup(1, _physical_tag(gmsh, 1, "interface"))
        corners = _refine_towards(gmsh, _block_corners(gmsh), dim=0, size=size)
        field = gmsh.model.mesh.field
        near = field.add("Distance")
        field.setNumbers(near, "CurvesList", list(interface))
        along = field.add("MathEval")  # size / 2 on the interface, size from 0.5 away
        field.setString(along, "F", f"Min({size}, {size / 2} + F{near} * {size})")
        both = field.add("Min")
        field.setNumbers(both, "FieldsList", [corners, along])
        field.setAsBackgroundMesh(both)
        gmsh.model.mesh.generate(2)
        return Elasticity(quadratic_mesh(gmsh, 2))


def _physical_tag(gmsh, dim: int, name: str) -> int:
    return next(t for d, t in gmsh.model.getPhysicalGroups(dim) if gmsh.model.getPhysicalName(d, t) == name)


def _block_corners(gmsh) -> list[int]:
    w, h = BLOCK
    return [t for _, t in gmsh.model.getEntities(0)
            if np.allclose(np.abs(gmsh.model.getValue(0, t, [])[:2]), (w / 2, h / 2))]


def write_inclusion_source(folder: Path, center, radius: float, size: float = 0.35) -> Path:
    """The user-style source scene: gmsh defaults, straight-sided (order 1) at ``size``,
    plus its problem.toml (inclusion E estimated, targets ``target_outline.vtp`` and
    ``target_interface.vtp`` beside it)."""
    with gmsh_model("inclusion-source") as gmsh:
        _inclusion_geometry(gmsh, center, radius)
        gmsh.option.setNumber("Mesh.MeshSizeMax", size)
        gmsh.option.setNumber("Mesh.MeshSizeMin", size)
        gmsh.model.mesh.generate(2)
        gmsh.option.setNumber("Mesh.MshFileVersion", 4.1)
        gmsh.write(str(folder / "source.msh"))
    path = folder / "problem.toml"
    path.write_text(INCLUSION_PROBLEM.format(radius=radius, size=size))
    return path


def inclusion(out, ratio: float, top=INCLUSION_TOP, center=(0.0, 0.0), radius: float = 1.2,
              nu: float = 0.3, E: float = 10.0, size: float = 0.1, source_size: float = 0.35,
              spacing: float = 0.01) -> dict:
    """The block with an inclusion of E = ``ratio`` x E solved by scikit-fem (bottom
    clamped, top moved by ``inclusion_top_motion(top)``). Files: ``problem`` (the source
    scene, ready to estimate), ``outline`` and ``interface`` (the displaced exact
    rectangle and circle)."""
    params = {"ratio": ratio, "top": list(top), "center": list(center), "radius": radius, "nu": nu, "E": E, "size": size,
              "source_size": source_size, "spacing": spacing}

    def make(folder):
        model = inclusion_model(tuple(center), radius, size)
        materials = {"matrix": (E, nu), "inclusion": (ratio * E, nu)}
        u = model.solve(materials, {"bottom": constant_motion((0.0, 0.0)), "top": inclusion_top_motion(top)})
        w, h = BLOCK
        corners = np.array([[-w / 2, -h / 2], [w / 2, -h / 2], [w / 2, h / 2], [-w / 2, h / 2], [-w / 2, -h / 2]])
        curves = {"outline": np.concatenate([sample_segment(a, b, spacing)[:-1] for a, b in zip(corners, corners[1:])]
                                            + [corners[:1]]),
                  "interface": sample_circle(center, radius, spacing)}
        files = {"problem": write_inclusion_source(folder, center, radius, source_size)}
        for name, points in curves.items():
            files[name] = write_polylines(folder / f"target_{name}.vtp", [points + evaluate(model.basis, u, points)])
        return files

    return cached(out, "inclusion", params, make)


def smooth_error(points: np.ndarray, std: float, seed: int = 0, spread: float = 2.5) -> np.ndarray:
    """A registration's kind of error at ``points``: per component six cosines with random
    wave vectors (normal, ``spread`` per unit length: wavelengths of ~2 pi / spread) and
    phases, scaled to ``std``. Smooth, so sampling it more densely adds no information."""
    rng = np.random.default_rng(seed)
    out = np.zeros_like(points)
    for c in range(points.shape[1]):
        for _ in range(6):
            k = rng.normal(0.0, spread, points.shape[1])
            out[:, c] += np.cos(points @ k + rng.uniform(0, 2 * np.pi))
    return std * out / np.sqrt(3.0)  # six unit cosines: variance 3


@lru_cache(maxsize=4)
def inclusion_solution(ratio: float, top=INCLUSION_TOP, center=(0.0, 0.0), radius: float = 1.2, nu: float = 0.3,
                       E: float = 10.0, size: float = 0.1) -> tuple[Elasticity, np.ndarray, dict]:
    """(model, u, materials) of the inclusion case's scikit-fem solution (as ``inclusion``)."""
    model = inclusion_model(tuple(center), radius, size)
    materials = {"matrix": (E, nu), "inclusion": (ratio * E, nu)}
    u = model.solve(materials, {"bottom": constant_motion((0.0, 0.0)), "top": inclusion_top_motion(tuple(top))})
    return model, u, materials


def inclusion_displacement(points: np.ndarray, ratio: float, top=INCLUSION_TOP, **kw) -> np.ndarray:
    """The independent solution's displacement at ``points`` (n, 2) inside the block."""
    model, u, _ = inclusion_solution(ratio, tuple(top), **kw)
    return evaluate(model.basis, u, points)


def inclusion_force(ratio: float, top=INCLUSION_TOP, group: str = "top", **kw) -> np.ndarray:
    """The total force the independent solution applies to the body through ``group``:
    the sum of the nodal reactions K u over the group's DOFs, per component."""
    model, u, materials = inclusion_solution(ratio, tuple(top), **kw)
    reactions = model.stiffness(materials) @ u
    view = model.basis.get_dofs(model.fe.facets[group])
    return np.array([reactions[view.all(f"u^{c + 1}")].sum() for c in range(2)])


# --------------------------------------------------------------------------- case 3: the prostate phantom

HALF = (6.0, 5.0, 5.0)  # the phantom's box 12 x 10 x 10 cm, centred at the origin (as in fenics_elasto.meshing)


def _ellipsoid(occ, organ) -> int:
    tag = occ.addSphere(*organ["center"], 1.0)
    occ.dilate([(3, tag)], *organ["center"], *organ["radii"])
    return tag


def _within(box, outer, tol=1e-6) -> bool:
    return all(box[i] >= outer[i] - tol and box[i + 3] <= outer[i + 3] + tol for i in range(3))


def _phantom_geometry(gmsh, organs: dict) -> dict:
    """The pelvis phantom's geometry and physical groups (tissue, prostate; bladder,
    rectum, bones, skin, prostate_surface); returns the face tags of each group."""
    occ = gmsh.model.occ
    body = occ.addBox(*(-np.array(HALF)), *(2 * np.array(HALF)))
    r = organs["rectum"]
    cavities = {"bladder": _ellipsoid(occ, organs["bladder"]),
                "rectum": occ.addCylinder(*r["center"], 0, 0, r["length"], r["radius"])}
    for bone in ("pubis", "sacrum"):
        b = organs[bone]
        cavities[bone] = occ.addCylinder(*b["center"], b["length"], 0, 0, b["radius"])
    occ.synchronize()
    boxes = {name: gmsh.model.getBoundingBox(3, tag) for name, tag in cavities.items()}
    tissue, _ = occ.cut([(3, body)], [(3, t) for t in cavities.values()])
    prostate = _ellipsoid(occ, organs["prostate"])
    occ.synchronize()
    prostate_box = gmsh.model.getBoundingBox(3, prostate)
    occ.fragment(tissue, [(3, prostate)])
    occ.synchronize()
    volumes = [t for _, t in gmsh.model.getEntities(3)]
    inner = [t for t in volumes if _within(gmsh.model.getBoundingBox(3, t), prostate_box)]
    outer = [t for t in volumes if t not in inner]
    faces = {"bladder": [], "rectum": [], "bones": [], "skin": [],
             "prostate_surface": [t for _, t in gmsh.model.getBoundary([(3, inner[0])], oriented=False)]}
    for _, face in gmsh.model.getBoundary([(3, t) for t in outer], oriented=False):
        box = gmsh.model.getBoundingBox(2, face)
        group = next((g for g, names in (("bladder", ["bladder"]), ("rectum", ["rectum"]),
                                         ("bones", ["pubis", "sacrum"])) if any(_within(box, boxes[n]) for n in names)),
                     "skin")
        if face not in faces["prostate_surface"]:
            faces[group].append(face)
    gmsh.model.addPhysicalGroup(3, outer, name="tissue")
    gmsh.model.addPhysicalGroup(3, inner, name="prostate")
    for name, tags in faces.items():
        gmsh.model.addPhysicalGroup(2, tags, name=name)
    return faces


def _graded(field, faces: list[int], near: float, far: float) -> int:
    dist = field.add("Distance")
    field.setNumbers(dist, "SurfacesList", faces)
    thr = field.add("Threshold")
    field.setNumber(thr, "InField", dist)
    field.setNumber(thr, "SizeMin", near)
    field.setNumber(thr, "SizeMax", far)
    field.setNumber(thr, "DistMin", 0.2)
    field.setNumber(thr, "DistMax", 3.0)
    return thr


@lru_cache(maxsize=1)
def phantom_model(seed: int, walls: float, prostate: float, far: float) -> Elasticity:
    """The phantom of ``phantom_organs(seed)`` meshed P2, curved, with gmsh's Delaunay
    surfaces and HXT volumes (the toolkit: Frontal-Delaunay and Delaunay), element
    size ``walls`` at the bladder and rectum, ``prostate`` at the prostate, ``far``
    elsewhere."""
    from fenics_elasto.mesh.builtin import phantom_organs

    with gmsh_model("phantom-truth") as gmsh:
        faces = _phantom_geometry(gmsh, phantom_organs(seed))
        field = gmsh.model.mesh.field
        both = field.add("Min")
        field.setNumbers(both, "FieldsList", [_graded(field, faces["bladder"] + faces["rectum"], walls, far),
                                              _graded(field, faces["prostate_surface"], prostate, far)])
        field.setAsBackgroundMesh(both)
        for option, value in (("MeshSizeExtendFromBoundary", 0), ("MeshSizeFromPoints", 0),
                              ("MeshSizeFromCurvature", 0), ("Algorithm", 5), ("Algorithm3D", 10),
                              ("ElementOrder", 2), ("HighOrderOptimize", 2)):  # unfold curved cells
            gmsh.option.setNumber(f"Mesh.{option}", value)
        gmsh.option.setNumber("General.NumThreads", 1)  # the machine is shared
        gmsh.model.mesh.generate(3)
        return Elasticity(quadratic_mesh(gmsh, 3))


def _ripple(d: np.ndarray, amplitude: float, wavelength: float = 6.0) -> np.ndarray:
    """A smooth, low-frequency vector field (3, n) of the offsets d (3, n) from an organ's
    centre: a few mm of motion that no affine map has."""
    k = 2 * np.pi / wavelength
    x, y, z = k * d
    return amplitude * np.array([np.sin(y + 0.3) * np.cos(z), np.sin(z + 0.5) * np.cos(x), np.sin(x + 0.7) * np.cos(y)])


# The walls' motion per state: (bladder inflation, its shift; rectum inflation, its shift).
# "filled": the bladder filled and the rectum distended; "emptied": the bladder emptied
# and sunk, the rectum collapsed and pulled back -- another load on the same body;
# "probe": the bladder at rest, the rectum widened 40 % and pushed towards the prostate,
# as by an endorectal coil's balloon (a load that presses on the prostate itself).
PHANTOM_STATES = {"filled": (0.1, (0.05, 0.0, 0.15), 0.15, (0.0, -0.1, 0.05)),
                  "emptied": (-0.08, (-0.05, 0.05, -0.12), -0.1, (0.02, 0.08, -0.04)),
                  "probe": (0.0, (0.0, 0.0, 0.0), 0.4, (0.0, -0.15, 0.0))}


def phantom_motions(organs: dict, ripple: float = 0.15, state: str = "filled") -> dict:
    """Prescribed wall motions (group -> u(x)): bones fixed; in the "filled" state the
    bladder inflated 10 % about its centre and shifted up, the rectum inflated 15 % about
    its axis (not along it) and pushed forward ("emptied": PHANTOM_STATES); both with a
    ripple of ``ripple`` cm."""
    bladder = np.asarray(organs["bladder"]["center"], float)[:, None]
    axis = np.asarray(organs["rectum"]["center"], float)[:, None]
    grow_b, shift_b, grow_r, shift_r = PHANTOM_STATES[state]

    def bladder_motion(x):
        return grow_b * (x - bladder) + np.array(shift_b)[:, None] + _ripple(x - bladder, ripple)

    def rectum_motion(x):
        radial = (x - axis) * np.array([[1.0], [1.0], [0.0]])
        return grow_r * radial + np.array(shift_r)[:, None] + _ripple(x - axis, ripple)

    return {"bones": constant_motion((0.0, 0.0, 0.0)), "bladder": bladder_motion, "rectum": rectum_motion}


# Fiducials: offsets in units of the prostate's radii, spread out, well inside (|q| < 0.7).
FIDUCIALS = np.array([[0.5, 0.3, 0.2], [-0.5, 0.2, -0.3], [0.1, -0.5, 0.4], [-0.1, -0.25, -0.55]])


def phantom_surfaces(organs: dict, spacing: float) -> dict:
    """The exact organ surfaces: group -> (points, triangles)."""
    r = organs["rectum"]
    return {"bladder": ellipsoid_surface(organs["bladder"]["center"], organs["bladder"]["radii"], spacing),
            "prostate_surface": ellipsoid_surface(organs["prostate"]["center"], organs["prostate"]["radii"], spacing),
            "rectum": cylinder_surface(r["center"], r["radius"], r["length"], spacing)}


def phantom(out, prostate_E: float, seed: int = 0, E: float = 10.0, nu: float = 0.4, prostate_nu: float = 0.4,
            ripple: float = 0.15, walls: float = 0.25, prostate: float = 0.15, far: float = 1.2,
            spacing: float = 0.03, state: str = "filled", field: int = 0) -> dict:
    """The phantom of ``phantom_organs(seed)`` solved by scikit-fem: bones fixed,
    bladder and rectum walls moved by ``phantom_motions``, skin free; tissue (E, nu),
    prostate (prostate_E, prostate_nu). Files: ``bladder``, ``prostate_surface``,
    ``rectum`` (the displaced exact surfaces, triangles about ``spacing`` apart) and
    ``fiducials`` (landmark CSV of 4 points inside the prostate), ``forces`` (JSON: the
    total force through each moved wall) and, with ``field`` > 0, ``field`` (a .vtp of
    that many of the truth mesh's vertices, each with its exact displacement) -- in ``state``
    (PHANTOM_STATES)."""
    from fenics_elasto.mesh.builtin import phantom_organs

    params = {"prostate_E": prostate_E, "seed": seed, "E": E, "nu": nu, "prostate_nu": prostate_nu, "ripple": ripple,
              "walls": walls, "prostate": prostate, "far": far, "spacing": spacing, "state": state, "field": field}

    def make(folder):
        organs = phantom_organs(seed)
        model = phantom_model(seed, walls, prostate, far)
        materials = {"tissue": (E, nu), "prostate": (prostate_E, prostate_nu)}
        u = model.solve(materials, phantom_motions(organs, ripple, state))
        files = {}
        for name, (points, triangles) in phantom_surfaces(organs, spacing).items():
            files[name] = write_triangles(folder / f"target_{name}.vtp", points + evaluate(model.basis, u, points), triangles)
        p = organs["prostate"]
        inside = np.asarray(p["center"]) + FIDUCIALS * np.asarray(p["radii"])
        files["fiducials"] = write_landmarks(folder / "fiducials.csv", inside, inside + evaluate(model.basis, u, inside))
        reactions = model.stiffness(materials) @ u
        forces = {g: [float(reactions[model.basis.get_dofs(model.fe.facets[g]).all(f"u^{c + 1}")].sum()) for c in range(3)]
                  for g in ("bladder", "rectum")}
        files["forces"] = folder / "forces.json"
        files["forces"].write_text(json.dumps(forces))
        if field:
            files["field"] = write_field(folder / "field.vtp", model, u, field)
        return files

    return cached(out, "phantom", params, make)


def write_field(path: Path, model: Elasticity, u: np.ndarray, count: int) -> Path:
    """``count`` vertices of the truth's mesh (random, fixed seed) with their displacement."""
    import pyvista as pv

    nodes = model.basis.doflocs[:, model.basis.nodal_dofs[0]].T  # the mesh vertices
    pick = np.random.default_rng(0).choice(len(nodes), min(count, len(nodes)), replace=False)
    values = np.stack([u[model.basis.nodal_dofs[c]] for c in range(3)], axis=1)
    cloud = pv.PolyData(nodes[pick])
    cloud["displacement"] = values[pick]
    cloud.save(path)
    return path


# --------------------------------------------------------------------------- problem files


def retarget(problem, target: dict, name: str = "problem_independent.toml") -> Path:
    """A copy of ``problem`` (beside it, so its mesh path still holds) whose [target]
    table is replaced by ``target``: key -> a path or a {group: path} table, written
    relative to the new file."""
    problem = Path(problem)
    text = re.sub(r"(?ms)^\[target(\.[^\]]*)?\]\n.*?(?=^\[|\Z)", "", problem.read_text())  # [target] and [target.*]
    lines = ["[target]"]
    for key, value in target.items():
        if isinstance(value, dict):
            table = ", ".join(f'{g} = "{_relative(path, problem.parent)}"' for g, path in value.items())
            lines.append(f"{key} = {{ {table} }}")
        else:
            lines.append(f'{key} = "{_relative(value, problem.parent)}"')
    path = problem.parent / name
    path.write_text(text.rstrip() + "\n\n" + "\n".join(lines) + "\n")
    return path


def _relative(path, base: Path) -> str:
    return os.path.relpath(Path(path).resolve(), base.resolve())


# --------------------------------------------------------------------------- a user's own source mesh

PLAIN_PROBLEM = """\
# The phantom as a user would bring it: meshed by plain gmsh, not by fenics_elasto.
mesh = "source.msh"
degree = 2

[materials.prostate]
E  = {{ estimate = true, initial = 30.0, bounds = [2.0, 300.0] }}
nu = {nu}

[materials.tissue]
E  = {E}
nu = {nu}

[boundary]
fixed   = ["bones"]
loaded  = ["bladder", "rectum"]
matched = ["bladder", "prostate_surface", "rectum"]
"""


def plain_source(out, order: int, seed: int = 0, organs_size: float = 0.45, far: float = 1.5,
                 E: float = 10.0, nu: float = 0.4, optimize: int = 2) -> Path:
    """The phantom of ``phantom_organs(seed)`` meshed the way most users' meshes are
    made: gmsh's default algorithms at ``order`` 1 (straight-sided tetrahedra) or 2
    (curved, untangled by gmsh's high-order optimiser: ``optimize`` is its
    Mesh.HighOrderOptimize), element size ``organs_size`` at the bladder, rectum and
    prostate and ``far`` elsewhere (about 3k vertices at the defaults). Returns the path
    of a problem.toml beside ``source.msh`` (no [target] table: ``retarget`` adds one)."""
    from fenics_elasto.mesh.builtin import phantom_organs

    params = {"order": order, "seed": seed, "organs": organs_size, "far": far, "E": E, "nu": nu}
    if order == 2 and optimize != 2:
        params["optimize"] = optimize

    def make(folder):
        with gmsh_model("plain-source") as gmsh:
            faces = _phantom_geometry(gmsh, phantom_organs(seed))
            field = gmsh.model.mesh.field
            near = faces["bladder"] + faces["rectum"] + faces["prostate_surface"]
            field.setAsBackgroundMesh(_graded(field, near, organs_size, far))
            for option, value in (("MeshSizeExtendFromBoundary", 0), ("MeshSizeFromPoints", 0),
                                  ("MeshSizeFromCurvature", 0), ("ElementOrder", order),
                                  ("HighOrderOptimize", optimize if order == 2 else 0)):
                gmsh.option.setNumber(f"Mesh.{option}", value)
            gmsh.option.setNumber("General.NumThreads", 1)
            gmsh.model.mesh.generate(3)
            gmsh.option.setNumber("Mesh.Binary", 0)
            gmsh.write(str(folder / "source.msh"))
        problem = folder / "problem.toml"
        problem.write_text(PLAIN_PROBLEM.format(E=E, nu=nu))
        return {"problem": problem, "mesh": folder / "source.msh"}

    return cached(out, "plain-source", params, make)["problem"]


# --------------------------------------------------------------------------- case 4: a kidney from label maps

# A kidney-sized ellipsoid (semi-axes in mm, its own frame) holding a ball "tumour", its
# hilum end clamped and one side pressed by a probe; imaged at rest and pressed as label
# maps of anisotropic voxels in a rotated, shifted frame, as a CT's would be.
KIDNEY_AXES = np.array([50.0, 28.0, 24.0])
KIDNEY_TUMOUR = (np.array([8.0, 6.0, 0.0]), 11.0)  # centre, radius
KIDNEY_HILUM, KIDNEY_PROBE = 0.8, 0.8  # the hilum: x < -0.8 a; the probe's face: y > 0.8 b
KIDNEY_VOXELS = np.array([1.0, 1.0, 1.5])
KIDNEY_OFFSET = np.array([-120.0, 40.0, -600.0])  # the world position of the kidney's centre


def kidney_rotation() -> np.ndarray:
    """The kidney's frame in the world: 25 degrees about a tilted axis."""
    axis = np.array([2.0, -1.0, 2.0]) / 3.0
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    angle = np.radians(25.0)
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def kidney_grid(margin: float = 12.0) -> tuple[tuple, np.ndarray, np.ndarray]:
    """(shape, the voxel centres in the kidney's frame (n, 3), the image's affine): voxels
    of KIDNEY_VOXELS covering the kidney and ``margin`` mm around it (room to deform)."""
    corner = -(KIDNEY_AXES + margin)
    shape = tuple(int(n) for n in np.ceil(2 * (KIDNEY_AXES + margin) / KIDNEY_VOXELS) + 1)
    ijk = np.indices(shape).reshape(3, -1).T
    affine = np.eye(4)
    affine[:3, :3] = kidney_rotation() * KIDNEY_VOXELS
    affine[:3, 3] = kidney_rotation() @ corner + KIDNEY_OFFSET
    return shape, ijk * KIDNEY_VOXELS + corner, affine


def kidney_probe_motion(push: float) -> Callable:
    """The probe's face (y > 0.8 b) pressed in by ``push`` mm at its middle and less
    towards its rim (a rounded probe), dragged along the kidney by a tenth of that and
    rippled: motion no affine map has."""
    a, _, c = KIDNEY_AXES

    def motion(x):
        reach = (x[0] / (0.6 * a)) ** 2 + (x[2] / (0.6 * c)) ** 2
        depth = push * (1.0 - 0.4 * reach) + 0.05 * push * np.sin(x[0] / 6.0)
        return np.array([0.1 * push * (1.0 - reach), -depth, 0.05 * push * np.cos(x[2] / 5.0)])

    return motion


def _kidney_geometry(gmsh) -> dict:
    """The kidney, its tumour, and the hilum and probe cut from its surface by planes;
    physical groups kidney, tumour (volumes), hilum, probe, outer, tumour_surface."""
    occ = gmsh.model.occ
    a, b, c = KIDNEY_AXES
    body = _ellipsoid(occ, {"center": (0.0, 0.0, 0.0), "radii": KIDNEY_AXES})
    centre, radius = KIDNEY_TUMOUR
    ball = occ.addSphere(*centre, radius)
    hilum = occ.addBox(-2 * a, -2 * b, -2 * c, (2 - KIDNEY_HILUM) * a, 4 * b, 4 * c)
    probe = occ.addBox(-2 * a, KIDNEY_PROBE * b, -2 * c, 4 * a, 2 * b, 4 * c)
    occ.fragment([(3, body)], [(3, ball), (3, hilum), (3, probe)])
    occ.synchronize()
    inside = lambda tag: ((np.array(occ.getCenterOfMass(3, tag)) / KIDNEY_AXES) ** 2).sum() < 1  # noqa: E731
    outside = [(3, t) for _, t in gmsh.model.getEntities(3) if not inside(t)]
    occ.remove(outside, recursive=True)
    occ.synchronize()
    volumes = [t for _, t in gmsh.model.getEntities(3)]
    tumour = [t for t in volumes if np.linalg.norm(np.array(occ.getCenterOfMass(3, t)) - centre) < 1e-3]
    kidney = [t for t in volumes if t not in tumour]
    faces: dict = {"hilum": [], "probe": [], "outer": [],
                   "tumour_surface": [t for _, t in gmsh.model.getBoundary([(3, tumour[0])], oriented=False)]}
    for _, face in gmsh.model.getBoundary([(3, t) for t in volumes], combined=True, oriented=False):
        x, y, _ = occ.getCenterOfMass(2, face)
        faces["hilum" if x < -KIDNEY_HILUM * a else "probe" if y > KIDNEY_PROBE * b else "outer"].append(face)
    gmsh.model.addPhysicalGroup(3, kidney, name="kidney")
    gmsh.model.addPhysicalGroup(3, tumour, name="tumour")
    for name, tags in faces.items():
        gmsh.model.addPhysicalGroup(2, tags, name=name)
    return faces


def kidney_model(tumour_size: float, far: float) -> Elasticity:
    """The kidney meshed P2, curved (gmsh's Delaunay surfaces and HXT volumes, unfolded),
    element size ``tumour_size`` at the tumour and ``far`` elsewhere."""
    with gmsh_model("kidney-truth") as gmsh:
        faces = _kidney_geometry(gmsh)
        field = gmsh.model.mesh.field
        field.setAsBackgroundMesh(_graded(field, faces["tumour_surface"], tumour_size, far))
        for option, value in (("MeshSizeExtendFromBoundary", 0), ("MeshSizeFromPoints", 0),
                              ("MeshSizeFromCurvature", 0), ("Algorithm", 5), ("Algorithm3D", 10),
                              ("ElementOrder", 2), ("HighOrderOptimize", 2)):
            gmsh.option.setNumber(f"Mesh.{option}", value)
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.model.mesh.generate(3)
        return Elasticity(quadratic_mesh(gmsh, 3))


def _labels_inside(surfaces: list[tuple[np.ndarray, np.ndarray]], points: np.ndarray) -> np.ndarray:
    """Per point, the 1-based index of the last closed surface that encloses it (0: none):
    label 1 inside the first, 2 inside the second (nested in it)."""
    import pyvista as pv

    cloud = pv.PolyData(points)
    labels = np.zeros(len(points), np.int16)
    for label, (vertices, triangles) in enumerate(surfaces, 1):
        surface = pv.PolyData(vertices, np.c_[np.full(len(triangles), 3), triangles].ravel())
        inside = cloud.select_interior_points(surface, method="cell_locator", check_surface=False)["selected_points"]
        labels[np.asarray(inside, bool)] = label
    return labels


def kidney_surfaces(spacing: float = 0.5) -> list[tuple[np.ndarray, np.ndarray]]:
    """The kidney's and the tumour's exact surfaces at rest (its own frame), points about
    ``spacing`` apart."""
    centre, radius = KIDNEY_TUMOUR
    return [ellipsoid_surface((0.0, 0.0, 0.0), KIDNEY_AXES, spacing), ellipsoid_surface(centre, (radius,) * 3, spacing)]


def kidney_labels(surfaces: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """(label map, its affine) of the kidney (1) and the tumour (2) bounded by ``surfaces``
    (its own frame) on ``kidney_grid``'s voxels."""
    shape, voxels, affine = kidney_grid()
    return _labels_inside(surfaces, voxels).reshape(shape), affine


def write_label_image(path: Path, labels: np.ndarray, affine: np.ndarray) -> Path:
    import nibabel as nib

    nib.save(nib.Nifti1Image(labels, affine), str(path))
    return path


def kidney(out, ratio: float, push: float = 6.0, E: float = 10.0, nu: float = 0.4, tumour_size: float = 1.5,
           far: float = 3.0, spacing: float = 0.5) -> dict:
    """The kidney solved by scikit-fem (hilum clamped, the probe's face moved by
    ``kidney_probe_motion(push)``, the rest free; kidney (E, nu), tumour (ratio E, nu)),
    and imaged: ``rest`` and ``deformed`` (NIfTI label maps, kidney 1, tumour 2: a voxel
    takes the label of the exact surfaces -- at rest, or moved by the solution -- that
    enclose its centre), ``outer`` and ``tumour_surface`` (the exact surfaces moved, in
    the world: what a perfect segmentation would give) and ``patches`` (JSON: the hilum's
    and the probe's cutting planes in the world, as a scene spec's [patches] takes them)."""
    params = {"ratio": ratio, "push": push, "E": E, "nu": nu, "tumour": tumour_size, "far": far, "spacing": spacing}

    def make(folder):
        model = kidney_model(tumour_size, far)
        materials = {"kidney": (E, nu), "tumour": (ratio * E, nu)}
        u = model.solve(materials, {"hilum": constant_motion((0.0, 0.0, 0.0)), "probe": kidney_probe_motion(push)})
        surfaces = kidney_surfaces(spacing)
        moved = [(points + evaluate(model.basis, u, points), triangles) for points, triangles in surfaces]
        files = {name: write_label_image(folder / f"{name}.nii.gz", *kidney_labels(s))
                 for name, s in (("rest", surfaces), ("deformed", moved))}
        R, a, b = kidney_rotation(), KIDNEY_AXES[0], KIDNEY_AXES[1]
        for name, (points, triangles) in zip(("outer", "tumour_surface"), moved):
            files[name] = write_triangles(folder / f"target_{name}.vtp", points @ R.T + KIDNEY_OFFSET, triangles)
        planes = {"hilum": (R @ [-KIDNEY_HILUM * a, 0, 0] + KIDNEY_OFFSET, R @ [-1.0, 0, 0]),
                  "probe": (R @ [0, KIDNEY_PROBE * b, 0] + KIDNEY_OFFSET, R @ [0, 1.0, 0])}
        files["patches"] = folder / "patches.json"
        files["patches"].write_text(json.dumps({k: {"point": p.tolist(), "normal": n.tolist()}
                                                for k, (p, n) in planes.items()}))
        return files

    return cached(out, "kidney", params, make)


KIDNEY_BOUNDARY = ["--set", "boundary.fixed=['hilum']", "--set", "boundary.loaded=['probe']",
                   "--set", "boundary.matched=['outer', 'tumour_surface']"]
KIDNEY_TARGETS = {
    "labels": "target={labels={image='../deformed.nii.gz', outer=[1, 2], tumour_surface=2}}",
    "surfaces": "target={surfaces={outer='../target_outer.vtp', tumour_surface='../target_tumour_surface.vtp'}}"}


def kidney_chain(truth: dict, folder: Path, organ_size: float = 3.0, kind: str = "labels") -> dict:
    """What a user runs on ``kidney``'s images, in ``folder``: `scene` of the rest label
    map (the hilum and the probe's face as plane-cut patches), `train --synthetic 60
    --rank 24`, `estimate` of the tumour's E from the pressed state -- its label map
    (``kind`` "labels") or the exact surfaces moved ("surfaces"). Returns result.json."""
    import shutil

    from fenics_elasto.app.cli import main

    folder.mkdir(parents=True, exist_ok=True)
    for name, file in (("rest", "rest.nii.gz"), ("deformed", "deformed.nii.gz"), ("outer", "target_outer.vtp"),
                       ("tumour_surface", "target_tumour_surface.vtp")):
        shutil.copy(truth[name], folder / file)
    import labelmaps

    planes = {name: (p["point"], p["normal"]) for name, p in json.loads(Path(truth["patches"]).read_text()).items()}
    (folder / "spec.toml").write_text(labelmaps.kidney_spec("rest.nii.gz", organ_size, planes))
    assert main(["scene", str(folder / "spec.toml"), "--out", str(folder / "src")]) == 0
    problem = str(folder / "src" / "problem.toml")
    bases = str(folder / "bases.npz")
    assert main(["train", problem, "--synthetic", "60", "--rank", "24", "--out", bases] + KIDNEY_BOUNDARY) == 0
    estimate = folder / f"est_{kind}"
    assert main(["estimate", problem, "--out", str(estimate), "--set", "reduction={bases='../bases.npz'}",
                 "--set", KIDNEY_TARGETS[kind]] + KIDNEY_BOUNDARY) == 0
    return json.loads((estimate / "result.json").read_text())
