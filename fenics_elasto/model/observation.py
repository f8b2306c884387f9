"""Where the model is observed: matched surface nodes and points inside the body.

The observed positions are linear in the displacement, y = y0 + O u:
- a matched node's row picks its nodal value (on a straight-sided P2 mesh only the
  vertices are on the geometry the mesh stands for; see ``matched_vertices_only``);
- a landmark (an implanted fiducial, any point inside the body) interpolates the
  finite-element displacement at its source point: sum_i phi_i(x) u_i over the DOFs of
  the cell holding x;
- a displacement field's observation is the mean of its samples' displacements, so its
  row is the mean of the model at those same samples (``Samples``), not the model at
  their mean point, which differs wherever u curves within the cube.

Rows: the matched nodes first (canonical order, the same under any number of MPI
ranks), then the points inside (in the order given). Every rank holds all rows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from mpi4py import MPI

import basix
import dolfinx
import dolfinx.geometry as geo
from dolfinx import la

from scipy.spatial import cKDTree

from fenics_elasto.config.problem import IN_MEMORY
from fenics_elasto.model.elasticity import ElasticModel
from fenics_elasto.model.dofs import NodeSet
from fenics_elasto.util.errors import UserError, require


def matched_vertices_only(scene, model: ElasticModel) -> bool:
    """``match_nodes``: "vertices", "all", or "auto" -- all nodes only where every node
    lies on the geometry: P1, or P2 on a curved (order-2 geometry) mesh. On a
    straight-sided mesh a P2 edge midpoint sits on the chord of a curved boundary, up
    to its sag inside the surface a target describes: a fake displacement."""
    rule = scene.match_nodes
    if rule == "auto":
        return scene.degree > scene.mesh.geometry.cmaps[0].degree
    return rule == "vertices"


def elementwise_min(comm, values: np.ndarray) -> np.ndarray:
    """The minimum over the ranks of each entry. (mpi4py's lower-case allreduce with
    MPI.MIN compares whole arrays with Python's min, which numpy refuses.)"""
    values = np.ascontiguousarray(values)
    out = np.empty_like(values)
    comm.Allreduce(values, out, op=MPI.MIN)
    return out


def closest_cells(mesh, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(cell, distance) of each point's closest owned cell on this rank (-1, inf: none).
    A point inside a cell (or on its boundary) takes the first cell it collides with,
    through the bounding-box tree; the closest-entity search runs for the others only
    (the default phantom's 5,522 matched nodes: 0.24 s instead of 2.2 s)."""
    distance = np.full(len(points), np.inf)
    search = _owned_tree(mesh, points)
    if search is None:
        return np.full(len(points), -1, np.int32), distance
    tree, owned, xyz = search
    tdim = mesh.topology.dim
    cells = _colliding_cell(mesh, tree, xyz)
    outside = np.flatnonzero(cells < 0)
    if len(outside):
        cells[outside] = geo.compute_closest_entity(tree, geo.create_midpoint_tree(mesh, tdim, owned), mesh,
                                                    xyz[outside])
    distance[cells >= 0] = 0.0
    found = outside[cells[outside] >= 0]
    distance[found] = np.sqrt(geo.squared_distance(mesh, tdim, cells[found], xyz[found]))
    return cells, distance


def distances_to_body(mesh, points: np.ndarray) -> np.ndarray:
    """Each point's distance to the body (0 inside), on every rank. Inside first, by the
    bounding-box tree's collisions (cheap); the closest cell only for points inside no
    rank's cells (1.5e5 samples of a 2D field: 8.3 s by closest cells alone)."""
    outside = _in_no_rank(mesh, points)
    distance = np.zeros(len(points))
    distance[outside] = elementwise_min(mesh.comm, closest_cells(mesh, points[outside])[1])
    return distance


def farther_than(mesh, distance: float, points: np.ndarray) -> np.ndarray:
    """Whether each point lies farther than ``distance`` from the body, on every rank: as
    ``distances_to_body(...) > distance``, but a point certainly farther, by its distance
    to the boundary's straight facets less their curved faces' bulge
    (``_below_boundary_distance``), is not measured by the closest-cell search (~0.2 ms a
    point: 50,000 points around the pelvis took 8 s, and an image's voxels in the air
    around the body are most of its 10^5-10^6)."""
    beyond = _in_no_rank(mesh, points)
    rest = np.flatnonzero(beyond)
    near = rest[elementwise_min(mesh.comm, _below_boundary_distance(mesh, points[rest])) <= distance]
    beyond[near] = elementwise_min(mesh.comm, closest_cells(mesh, points[near])[1]) > distance
    return beyond


def _in_no_rank(mesh, points: np.ndarray) -> np.ndarray:
    """Whether each point lies in no rank's cells (on every rank)."""
    return elementwise_min(mesh.comm, (~_inside_owned(mesh, points)).astype(np.int8)).astype(bool)


def _below_boundary_distance(mesh, points: np.ndarray) -> np.ndarray:
    """A lower bound of each point's distance to this rank's boundary facets (inf where it
    has none): the distance to the facets made straight between their vertices (libigl's
    tree), less twice the largest offset of a facet's node from where its straight facet
    puts it (a vertex, or the midpoint of two: a quadratic face strays from its straight
    facet at most 4/3 of its midpoints' offsets). The closest point of the body to a point
    outside it lies on some rank's boundary facet."""
    tdim, gdim = mesh.topology.dim, mesh.geometry.dim
    for entities in ((tdim - 1, tdim), (tdim - 1, 0), (0, tdim)):  # on every rank, before any return
        mesh.topology.create_connectivity(*entities)
    facets = dolfinx.mesh.exterior_facet_indices(mesh.topology)  # collective
    if not len(facets) or not len(points):
        return np.full(len(points), np.inf)
    import igl

    vertices = mesh.topology.connectivity(tdim - 1, 0).array.reshape(-1, tdim)[facets]
    corners = dolfinx.mesh.entities_to_geometry(mesh, 0, vertices.ravel()).reshape(vertices.shape)
    x = np.ascontiguousarray(mesh.geometry.x[:, :gdim])
    nodes = x[dolfinx.mesh.entities_to_geometry(mesh, tdim - 1, facets)]  # (facets, k, gdim)
    ends = x[corners]  # (facets, tdim, gdim)
    first, second = np.triu_indices(tdim, 1)
    straight = np.concatenate([ends, (ends[:, first] + ends[:, second]) / 2], axis=1)  # vertices, midpoints
    bulge = float(np.linalg.norm(nodes[:, :, None] - straight[:, None], axis=3).min(axis=2).max())
    return np.sqrt(igl.point_mesh_squared_distance(np.ascontiguousarray(points, float), x, corners)[0]) - 2.0 * bulge


def _inside_owned(mesh, points: np.ndarray) -> np.ndarray:
    """Whether each point lies in one of this rank's owned cells."""
    search = _owned_tree(mesh, points)
    return np.zeros(len(points), bool) if search is None else _colliding_cell(mesh, search[0], search[2]) >= 0


def _owned_tree(mesh, points: np.ndarray):
    """(the bounding-box tree of this rank's owned cells, those cells, the points padded to
    3D); None where this rank owns no cells or there are no points."""
    tdim, gdim = mesh.topology.dim, mesh.geometry.dim
    owned = np.arange(mesh.topology.index_map(tdim).size_local, dtype=np.int32)
    if len(owned) == 0 or len(points) == 0:
        return None
    xyz = np.zeros((len(points), 3))
    xyz[:, :gdim] = points
    return geo.bb_tree(mesh, tdim, entities=owned), owned, xyz


CHUNK = 20_000  # points located at once (their candidate cells' nodes: ~50 MB)
INSIDE_REFERENCE = 1e-10  # a point this far outside a cell's reference simplex is on it
FAR_FROM_REFERENCE = 1.0  # pull_back_all: a point this far outside its cell's vertex simplex is not in the cell
NOT_SETTLED = 1e6  # ... the reference coordinate of a point whose Newton did not settle: outside every cell


def _colliding_cell(mesh, tree, xyz: np.ndarray) -> np.ndarray:
    """The first cell of ``tree`` each point (padded to 3D) lies in or on; -1 where none.
    The bounding boxes name candidates; each is tested by its pull-back, all at once
    (``pull_back_all``): DOLFINx's compute_colliding_cells took 0.1 ms a point in 3D."""
    cells = np.full(len(xyz), -1, np.int32)
    for start in range(0, len(xyz), CHUNK):
        chunk = xyz[start:start + CHUNK]
        candidates = geo.compute_collisions_points(tree, chunk)
        point = np.repeat(np.arange(len(chunk)), np.diff(candidates.offsets))
        cell = np.asarray(candidates.array, np.int32)
        reference = pull_back_all(mesh, cell, chunk[point, : mesh.geometry.dim])
        inside = np.flatnonzero(_in_reference_cell(reference, INSIDE_REFERENCE))
        found, first = np.unique(point[inside], return_index=True)  # a point on a facet: its first cell
        cells[start + found] = cell[inside[first]]
    return cells


def _in_reference_cell(reference: np.ndarray, margin: float) -> np.ndarray:
    return (reference.min(axis=1) >= -margin) & (reference.sum(axis=1) <= 1 + margin)


def pull_back_all(mesh, cells: np.ndarray, points: np.ndarray, steps: int = 12) -> np.ndarray:
    """(n, tdim) reference coordinates of each point under its cell's map (simplices), all
    at once: from the affine map of the cell's vertices (exact for straight cells), then
    Newton on the curved map. Where Newton has not settled the result lies far outside
    the cell; callers that need the point's own preimage test for that (``_pull_back``)."""
    tdim, gdim = mesh.topology.dim, mesh.geometry.dim
    cmap = mesh.geometry.cmaps[0]
    nodes = mesh.geometry.x[mesh.geometry.dofmaps[0][cells], :gdim]  # (n, nodes, gdim)
    corners = nodes[:, : tdim + 1]
    affine = np.transpose(corners[:, 1:] - corners[:, :1], (0, 2, 1))  # (n, gdim, tdim)
    reference = _solve(affine, points - corners[:, 0])
    if cmap.degree == 1 or not len(cells):
        return reference
    element = basix.create_element(basix.ElementFamily.P, basix.CellType[mesh.topology.cell_type.name],
                                   cmap.degree, basix.LagrangeVariant(cmap.variant))
    tolerance = 1e-13 * max(1.0, float(np.abs(nodes).max()))
    # a curved cell lies close to its vertices' simplex: candidates far outside that are not it
    active = np.flatnonzero(_in_reference_cell(reference, FAR_FROM_REFERENCE))
    for _ in range(steps):
        table = element.tabulate(1, reference[active])[..., 0]  # (1 + tdim, n, nodes)
        residual = points[active] - np.einsum("nk,nkd->nd", table[0], nodes[active])
        moving = np.abs(residual).max(axis=1) > tolerance
        active, residual, table = active[moving], residual[moving], table[:, moving]
        if not len(active):
            break
        jacobian = np.einsum("tnk,nkd->ndt", table[1:], nodes[active])
        reference[active] += _solve(jacobian, residual)
    else:
        reference[active] = NOT_SETTLED  # no preimage found
    return reference


def _solve(matrices: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """Each square system (n, d, d) x = (n, d); a singular one (a cell folded flat) gives
    a point far outside every reference cell."""
    out = np.full(vectors.shape, NOT_SETTLED)
    good = np.abs(np.linalg.det(matrices)) > 0.0
    out[good] = np.linalg.solve(matrices[good], vectors[good][..., None])[..., 0]
    return out


OUTSIDE_REFERENCE = 0.25  # reference coordinates further outside the cell than this: another preimage


def _near_reference_cell(reference: np.ndarray) -> bool:
    """Within OUTSIDE_REFERENCE of the reference simplex (a point a hair outside a
    curved cell lies just outside it)."""
    return bool(_in_reference_cell(reference[None, :], OUTSIDE_REFERENCE)[0])


def _newton(cmap, point: np.ndarray, nodes: np.ndarray, start: np.ndarray, steps: int = 30) -> np.ndarray:
    """Reference coordinates of ``point`` under the cell map (geometry ``nodes``), by
    Newton from ``start`` with a forward-difference Jacobian (the residual is exact, so
    it still converges to rounding)."""
    reference = start.astype(float).copy()
    scale = max(1.0, float(np.abs(nodes).max()))
    for _ in range(steps):
        x = cmap.push_forward(reference[None, :], nodes)[0]
        residual = x - point
        if np.linalg.norm(residual) <= 1e-13 * scale:
            break
        step = 1e-7
        jacobian = np.column_stack([(cmap.push_forward((reference + step * e)[None, :], nodes)[0] - x) / step
                                    for e in np.eye(len(reference))])
        try:
            reference = reference - np.linalg.solve(jacobian, residual)
        except np.linalg.LinAlgError:  # a degenerate map where Newton wandered: keep the last
            break
    return reference


@dataclass
class Samples:
    """Rows observed inside the body, each the weighted mean of the model at its samples:
    ``points`` (n, gdim) the rows' undeformed positions; ``at`` (m, gdim) where the model
    is evaluated, ``row`` (m,) whose row each sample is, ``weight`` (m,) its share of it
    (a row's shares sum to 1). A landmark is a row of one sample at its own point."""

    points: np.ndarray
    at: np.ndarray
    row: np.ndarray
    weight: np.ndarray

    @classmethod
    def single(cls, points: np.ndarray) -> Samples:
        """Each point its own row."""
        return cls(points, points, np.arange(len(points)), np.ones(len(points)))

    @classmethod
    def joined(cls, parts: list[Samples]) -> Samples:
        """The parts' rows one after another."""
        offsets = np.cumsum([0] + [len(p.points) for p in parts])[:-1]
        return cls(np.concatenate([p.points for p in parts]), np.concatenate([p.at for p in parts]),
                   np.concatenate([p.row + o for p, o in zip(parts, offsets)]),
                   np.concatenate([p.weight for p in parts]))

    def mean(self, values: np.ndarray) -> np.ndarray:
        """(n, ...) each row's weighted mean of the samples' ``values`` (m, ...)."""
        out = np.zeros((len(self.points),) + values.shape[1:])
        np.add.at(out, self.row, self.weight.reshape((-1,) + (1,) * (values.ndim - 1)) * values)
        return out

    def spread(self, r: np.ndarray) -> np.ndarray:
        """(m, gdim) the transpose of ``mean``: each sample's share of its row's ``r``."""
        return self.weight[:, None] * r[self.row]


def _inside_source(scene) -> str:
    """What the points inside the body came from, for an error line: the landmarks' or
    the displacement field's file, or the Python Target's argument that held them."""
    target = scene.config.get("target") or {}
    for key in ("landmarks", "displacement"):
        entry = target.get(key)
        if entry == IN_MEMORY:
            return f"Target.{key}"
        if entry:
            return str(scene.path.parent / entry)
    return str(scene.path)


class PointProbe:
    """u at fixed points anywhere in the mesh (each point evaluated on one rank).

    A point a hair outside the mesh (a node of a coarse curved boundary against a
    finer mesh) takes the value of the closest cell's polynomial; ``tolerance`` bounds
    how far outside a point may lie.
    """

    def __init__(self, V, points: np.ndarray, tolerance: float = np.inf):
        mesh = V.mesh
        self.V, self.comm = V, mesh.comm
        self.gdim = mesh.geometry.dim
        self.count = len(points)
        cells, distance = closest_cells(mesh, points)
        best = elementwise_min(self.comm, distance)
        require(np.all(best <= tolerance), f"{int(np.sum(best > tolerance))} point(s) lie outside the body "
                f"(worst {best.max():.3g} from it, tolerance {tolerance:.3g}): the first is "
                f"{np.round(points[np.argmax(best > tolerance)], 6).tolist()}")
        node, at_node = self._nodes_at(points)
        mine = (cells >= 0) & (distance == best)
        claim = elementwise_min(self.comm, np.where(mine, self.comm.rank, self.comm.size))
        node_claim = elementwise_min(self.comm, np.where(at_node, self.comm.rank, self.comm.size))
        claim = np.where(node_claim < self.comm.size, node_claim, claim)
        self.rows = np.flatnonzero(claim == self.comm.rank)
        self.blocks, self.weights = self._weights(mesh, points[self.rows], cells[self.rows])
        snapped = at_node[self.rows]  # a point at a node of V takes that node's value exactly
        self.blocks[snapped] = node[self.rows][snapped, None]
        self.weights[snapped] = 0.0
        self.weights[snapped, 0] = 1.0

    def _nodes_at(self, points):
        """(node, found): the owned node of V at each point, where there is one."""
        owned = self.V.tabulate_dof_coordinates()[: self.V.dofmap.index_map.size_local, : self.gdim]
        if not len(owned) or not len(points):
            return np.zeros(len(points), np.int32), np.zeros(len(points), bool)
        gap, node = cKDTree(owned).query(points)
        scale = max(1.0, float(np.abs(owned).max()))
        return node.astype(np.int32), gap <= 1e-10 * scale

    def _weights(self, mesh, points, cells):
        """(blocks, phi) per point: the cell's DOF blocks and its basis functions at the point."""
        element = self.V.ufl_element().basix_element
        blocks = self.V.dofmap.list[cells] if len(cells) else np.zeros((0, self.V.dofmap.list.shape[1]), np.int32)
        # explicit widths: a rank may hold none of the points (reshape(0, -1) is an error)
        reference = pull_back_all(mesh, cells, points)
        lost = np.flatnonzero(~_in_reference_cell(reference, OUTSIDE_REFERENCE))  # outside, or another preimage
        if len(lost):  # fetched once: each fetch of a geometry dofmap copies it
            cmap, geometry, x = mesh.geometry.cmaps[0], mesh.geometry.dofmaps[0], mesh.geometry.x[:, : self.gdim]
            reference[lost] = [self._pull_back(cmap, points[i], x[geometry[cells[i]]]) for i in lost]
        phi = element.tabulate(0, reference)[0] if len(cells) else np.zeros(blocks.shape)
        return blocks, phi.reshape(blocks.shape)

    def _pull_back(self, cmap, point, nodes) -> np.ndarray:
        """The point's reference coordinates in the cell with geometry ``nodes``: Newton on
        the cell's (curved) map. A quadratic map has other preimages far outside the cell, and DOLFINx's
        Newton can land on one: on the real prostate's source a shared edge's midpoint
        pulled back to (13.1, -12.7, -7.2), where the degree-3 basis weighs ~3e4, and
        that one point made the mesh part of sigma 21.7 for an E of 50. Where it fails or
        lands outside the cell, Newton from the affine map of the cell's vertices
        (``_newton``) -- exact at the vertices, close to the point near the cell."""
        try:
            reference = cmap.pull_back(point[None, :], nodes)[0]
            if _near_reference_cell(reference):
                return reference
        except RuntimeError:
            pass
        corners = nodes[: self.gdim + 1]
        start = np.linalg.solve((corners[1:] - corners[0]).T, point - corners[0])
        return _newton(cmap, point, nodes, start)

    def values(self, array: np.ndarray) -> np.ndarray:
        """(count, gdim) values of a Function's local array (ghosts up to date), all ranks."""
        out = np.zeros((self.count, self.gdim))
        local = array.reshape(-1, self.gdim)
        out[self.rows] = np.einsum("pi,pid->pd", self.weights, local[self.blocks])
        return self.comm.allreduce(out, op=MPI.SUM)

    def add_transpose(self, r: np.ndarray, array: np.ndarray) -> None:
        """array += O^T r on this rank's local entries (ghosts included: scatter them back)."""
        local = array.reshape(-1, self.gdim)
        np.add.at(local, self.blocks.ravel(), (self.weights[:, :, None] * r[self.rows][:, None, :]).reshape(-1, self.gdim))


def probe(u: dolfinx.fem.Function, points: np.ndarray) -> np.ndarray:
    """u at arbitrary points (every rank gets all values)."""
    return PointProbe(u.function_space, points).values(u.x.array)


class Observation:
    """y = y0 + O u at the matched nodes, then at the points inside the body."""

    def __init__(self, model: ElasticModel, scene, inside: Samples | None = None):
        self.model = model
        self.gdim = model.dofs.gdim
        self.vertices_only = matched_vertices_only(scene, model)
        self.nodes: NodeSet = model.dofs.node_set(scene.matched, vertices_only=self.vertices_only)
        self.node_points = self.nodes.gather(self.nodes.coords)
        self.inside = Samples.single(np.zeros((0, self.gdim))) if inside is None else inside
        size = np.ptp(model.dofs.dof_coords, axis=0).max() if len(model.dofs.dof_coords) else 0.0
        size = model.dofs.comm.allreduce(size, op=MPI.MAX)
        try:
            self.probe = PointProbe(model.dofs.V, self.inside.at, tolerance=0.02 * size) if len(self.inside.at) else None
        except UserError as err:
            raise UserError(f"{_inside_source(scene)}: {err}") from None
        self.points = np.concatenate([self.node_points, self.inside.points])

    @property
    def count(self) -> int:
        return len(self.points)

    @property
    def node_count(self) -> int:
        return len(self.node_points)

    def values(self, u: dolfinx.fem.Function) -> np.ndarray:
        """(count, gdim) O u (u's ghosts up to date)."""
        array = u.x.array
        nodal = self.nodes.gather(array.reshape(-1, self.model.dofs.bs)[self.nodes.blocks])
        if self.probe is None:
            return nodal
        return np.concatenate([nodal, self.inside.mean(self.probe.values(array))])

    def on_space(self, V):
        """O for another space V over the same rows (a function of V's local array, ghosts
        up to date): the higher-degree solve of the mesh part is observed so."""
        probe = PointProbe(V, np.concatenate([self.node_points, self.inside.at]))
        n = self.node_count

        def values(array: np.ndarray) -> np.ndarray:
            v = probe.values(array)
            return np.concatenate([v[:n], self.inside.mean(v[n:])])
        return values

    def positions(self, u: dolfinx.fem.Function) -> np.ndarray:
        return self.points + self.values(u)

    def node_field(self, values: np.ndarray) -> dolfinx.fem.Function:
        """A field holding per-node rows (canonical order) at the matched nodes, zero at
        the other nodes -- except, when only vertices are matched, the edge midpoints
        between matched vertices, which follow them linearly (as on the chord)."""
        f = self.model.dofs.function("matched")
        f.x.array.reshape(-1, self.model.dofs.bs)[self.nodes.blocks] = self.nodes.local(values)
        f.x.scatter_forward()
        if not self.vertices_only:
            return f
        mesh = self.model.dofs.V.mesh
        linear = dolfinx.fem.Function(dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (self.gdim,))))
        linear.interpolate(f)  # the vertex values
        out = self.model.dofs.function("matched")
        out.interpolate(linear)  # midpoints: the mean of their edge's vertices
        ends = self._on_matched_facets()
        array = out.x.array.reshape(-1, self.model.dofs.bs)
        array[~ends] = 0.0  # only between matched vertices, as the nodes themselves
        array[self.nodes.blocks] = f.x.array.reshape(-1, self.model.dofs.bs)[self.nodes.blocks]
        return out

    def _on_matched_facets(self) -> np.ndarray:
        """Mask over V's local blocks: every node (midpoints too) of the matched facets."""
        scene = self.model.scene
        blocks = self.model.dofs.boundary_blocks(scene.matched, vertices_only=False)
        mask = np.zeros(len(self.model.dofs.V.tabulate_dof_coordinates()), bool)
        mask[blocks] = True
        return mask

    def transpose(self, r: np.ndarray) -> dolfinx.fem.Function:
        """A Function holding O^T r (owned entries exact): the adjoint load."""
        f = self.model.dofs.function("adjoint_load")
        array = f.x.array.reshape(-1, self.model.dofs.bs)
        array[self.nodes.blocks] = self.nodes.local(r[: self.node_count])
        if self.probe is not None:
            landmark = self.model.dofs.function("landmark_load")
            self.probe.add_transpose(self.inside.spread(r[self.node_count:]), landmark.x.array)
            landmark.x.scatter_reverse(la.InsertMode.add)
            owned = self.model.dofs.n_owned_blocks * self.model.dofs.bs
            f.x.array[:owned] += landmark.x.array[:owned]
        return f

    def rows(self, X: np.ndarray) -> np.ndarray:
        """(count, gdim, k) O X for owned-row DOF columns X."""
        bs = self.model.dofs.bs
        nodal = self.nodes.gather(X[self.nodes.dofs(bs).ravel()].reshape(len(self.nodes), self.gdim, -1))
        if self.probe is None:
            return nodal
        column = self.model.dofs.function("column")
        owned = self.model.dofs.n_owned_blocks * bs
        parts = []
        for k in range(X.shape[1]):  # a handful of modes: each needs its ghost values
            column.x.array[:owned] = X[:, k]
            column.x.scatter_forward()
            parts.append(self.inside.mean(self.probe.values(column.x.array)))
        return np.concatenate([nodal, np.stack(parts, axis=2) if parts else np.zeros((len(self.inside.points), self.gdim, 0))])
