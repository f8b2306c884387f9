"""Headless pictures with pyvista that explain a result at a glance.

3D: the organs (every group that is not clamped) are coloured by the field the colour
bar names -- |u| for a simulation; an estimate gets a second panel coloured by the
distance to the target, with the target's points drawn over it. The body is a faint
translucent shell with its edges, clamped groups (bones) are muted and see-through,
the camera frames the organs, and each organ carries its name; a group around others
(a matched outer surface, a gland around its nodule) is see-through. The title says the
case and the answer (materials, misfit, and +- sigma when the estimate has it); the
legend lists only what is drawn.

2D: the body's cells coloured by |u| with mesh lines, each group's curve in its own
colour, the target in red.
"""

from __future__ import annotations

import os
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    import pyvista as pv

GROUP_COLOURS = ["#e6550d", "#3182bd", "#31a354", "#756bb1", "#d6616b", "#8c6d31"]
FIXED_COLOUR = "#c9b38f"  # clamped groups: bone, muted
BODY_COLOUR = "#9e9e9e"
TARGET_COLOUR = "#29c5f6"  # light blue: seen on every colour of the distance map
ARROW_COLOUR = "#333333"
LEGEND_TEXT = {BODY_COLOUR: "#6b6b6b", FIXED_COLOUR: "#96804f"}  # the pale colours darker, to be read
ARROWS = 150  # about this many displacement arrows on the organs
VIEW_3D = ((1.0, -0.75, 0.45), (0.0, 0.0, 1.0))  # from the side and the front, slightly above; z up
MAX_TARGET_POINTS = 6000  # a denser target is thinned for drawing (every point is still measured)
SHELL_OPACITY = 0.35  # a group around others: see-through


@contextmanager
def _headless_window(off_screen: bool):
    """VTK's off-screen (EGL) window class for the plotters made inside, unless the
    environment names one: straight to EGL, no failed X connection first. The
    environment is as it was afterwards."""
    set_here = off_screen and "VTK_DEFAULT_OPENGL_WINDOW" not in os.environ
    if set_here:
        os.environ["VTK_DEFAULT_OPENGL_WINDOW"] = "vtkEGLRenderWindow"
    try:
        yield
    finally:
        if set_here:
            os.environ.pop("VTK_DEFAULT_OPENGL_WINDOW", None)


def offscreen_plotter(off_screen: bool = True, **options) -> Any:
    """A pyvista plotter (default: one 1400 x 1000 view), off-screen unless told; no
    global setting of pyvista's is changed. (Typed Any: pyvista's own annotations of
    its drawing calls are narrower than what they take.)"""
    import pyvista as pv

    with _headless_window(off_screen):
        return pv.Plotter(off_screen=off_screen, **{"window_size": (1400, 1000), **options})


def render(
    path: Path,
    groups: dict,  # name -> deformed surface (pyvista, with "|u|")
    reference: dict | None = None,  # name -> undeformed surface
    context=None,  # e.g. the whole body (2D: deformed cells; 3D: exterior surface)
    target=None,
    title: str = "",
    dim: int = 3,
    fixed=(),  # names of clamped groups: drawn muted
    units: str = "",
    matched=None,  # names of the groups the target is for (None: every group drawn)
) -> Path:
    """Write a PNG of a solution: 2D or 3D (see the module docstring)."""
    plotter = picture(groups, reference, context, target, title, dim, fixed, units, matched=matched)
    plotter.screenshot(str(path))
    plotter.close()
    return Path(path)


def picture(groups: dict, reference: dict | None = None, context=None, target=None, title: str = "", dim: int = 3,
            fixed=(), units: str = "", off_screen: bool = True, matched=None) -> pv.Plotter:
    """The plotter of a solution's picture, drawn but not shown (``render``'s arguments)."""
    if dim == 2:
        return _picture_2d(groups, reference, context, target, title, off_screen)
    return _picture_3d(groups, context, target, title, fixed, units, off_screen, matched)


# --------------------------------------------------------------------------- 3D


def _picture_3d(groups, context, target, title, fixed, units, off_screen: bool, matched=None) -> pv.Plotter:
    organs = {n: m for n, m in groups.items() if n not in fixed and m is not None and m.n_points}
    muted = [groups[n] for n in fixed if n in groups and groups[n] is not None and groups[n].n_points]
    panels = _panels(organs, target, units, matched)
    shells = _enclosing(organs)  # the same in every panel
    width = 1400 if len(panels) == 1 else 1000 * len(panels)
    plotter = offscreen_plotter(off_screen, shape=(2, len(panels)), row_weights=[1, 9], groups=[(0, np.s_[:])],
                                window_size=(width, 1000), border=False)
    plotter.subplot(0, 0)
    plotter.add_text(title, font_size=13, position="upper_edge")
    for k, (scalars, heading, bar, cmap) in enumerate(panels):
        plotter.subplot(1, k)
        legend = _add_surroundings(plotter, context, muted)
        clim = _shared_range(organs.values(), scalars, 0.98 if scalars == "distance" else 1.0)
        coloured = {n: m for n, m in organs.items() if scalars in m.point_data}
        for i, (name, mesh) in enumerate(coloured.items()):
            plotter.add_mesh(mesh, scalars=scalars, cmap=cmap, clim=clim, smooth_shading=True,
                             opacity=SHELL_OPACITY if name in shells else 1.0,
                             scalar_bar_args=_bar(bar), show_scalar_bar=i == 0)
        legend += _add_unmatched(plotter, [m for m in organs.values() if scalars not in m.point_data])
        legend += _add_motion(plotter, organs) if scalars == "|u|" else []
        legend += _add_target(plotter, target) if target is not None and k == len(panels) - 1 else []
        _add_names(plotter, organs)
        _add_legend(plotter, legend, width / len(panels), "lower left")
        if heading:
            plotter.add_text(heading, font_size=12, position="upper_left")
        _frame(plotter, list(organs.values()) or muted or [context])
    return plotter


def _enclosing(organs: dict) -> set[str]:
    """The groups whose bounding box holds another group's (a matched outer surface around
    the organs, a gland around its nodule): drawn see-through, the inner ones would be
    hidden behind them."""
    boxes = {n: np.reshape(m.bounds, (3, 2)) for n, m in organs.items()}
    return {n for n, a in boxes.items()
            if any((a[:, 0] <= b[:, 0]).all() and (b[:, 1] <= a[:, 1]).all() for k, b in boxes.items() if k != n)}


def _panels(organs: dict, target, units: str, matched=None) -> list[tuple]:
    """(scalars, heading, colour bar title, colour map) per panel: the motion, and with a
    target surface, the distance to it (computed here, onto the organs ``matched`` names;
    None: every organ). An organ with no target of its own is not coloured by the
    distance to another's (a bar's loaded end, moved in its own plane, read 0.25 away)."""
    unit = f" ({units})" if units else ""
    motion = ("|u|", "", f"displacement{unit}", "viridis")  # (scalar bars cannot draw "|" or "‖")
    measured = [m for n, m in organs.items() if matched is None or n in matched]
    if target is None or not _has_faces(target) or not measured:
        return [motion]
    for mesh in measured:
        mesh.point_data["distance"] = distance_to(target, mesh.points)
    return [(*motion[:1], "how it moved", *motion[2:]),
            ("distance", "how well it fits the target", f"distance to target{unit}", "inferno")]


def _add_legend(plotter, entries: list, pixels: float, loc: str) -> None:
    """A legend whose letters are the same size whatever its entries: its box sized
    by the number of lines and the longest one (``pixels``: the view's width)."""
    if not entries:
        return
    longest = max(len(label) for label, _ in entries)
    plotter.add_legend(entries, bcolor="white", face="rectangle", loc=loc,
                       size=(min(0.5, 15.0 * longest / pixels), 0.038 * len(entries)))


def _bar(title: str) -> dict:
    return {"title": title, "vertical": True, "position_x": 0.86, "position_y": 0.25, "height": 0.5,
            "title_font_size": 16, "label_font_size": 14, "fmt": "%.3g"}


def _add_surroundings(plotter, context, muted) -> list:
    """The body as a faint shell with its edges; clamped groups muted. Legend entries."""
    legend = []
    if context is not None and context.n_points:
        surface = context.extract_surface(algorithm=None) if not hasattr(context, "faces") else context
        plotter.add_mesh(surface, color=BODY_COLOUR, opacity=0.06, show_scalar_bar=False)
        # the facets come in any orientation: make the normals consistent before asking for kinks
        oriented = surface.compute_normals(consistent_normals=True, auto_orient_normals=True, split_vertices=False)
        edges = oriented.extract_feature_edges(feature_angle=60, boundary_edges=False, non_manifold_edges=False,
                                              manifold_edges=False)
        if edges.n_cells:
            plotter.add_mesh(edges, color=BODY_COLOUR, line_width=1, opacity=0.5)
        legend.append(["body (translucent)", LEGEND_TEXT[BODY_COLOUR]])
    for mesh in muted:
        plotter.add_mesh(mesh, color=FIXED_COLOUR, opacity=0.3, show_scalar_bar=False)
    if muted:
        legend.append(["clamped (fixed)", LEGEND_TEXT[FIXED_COLOUR]])
    return legend


def _add_unmatched(plotter, meshes: list) -> list:
    """Groups with no target, plain in the distance panel. Legend entries."""
    for mesh in meshes:
        plotter.add_mesh(mesh, color=BODY_COLOUR, opacity=0.5, smooth_shading=True, show_scalar_bar=False)
    return [["no target (not matched)", LEGEND_TEXT[BODY_COLOUR]]] if meshes else []


def _add_motion(plotter, organs: dict) -> list:
    """Arrows of the displacement at a few hundred surface points, the longest drawn at
    a tenth of the organs' size (the scale is in the legend)."""
    import pyvista as pv

    points = np.vstack([m.points for m in organs.values()])
    motion = np.vstack([_displacement(m) for m in organs.values()])
    length = np.linalg.norm(motion, axis=1)
    if not len(points) or length.max() <= 0:
        return []
    chosen = _spread(points, ARROWS)
    size = float(np.linalg.norm(np.ptp(points, axis=0)))
    scale = 0.1 * size / length.max()
    cloud = pv.PolyData(points[chosen])
    cloud["motion"] = motion[chosen] * scale
    arrow = pv.Arrow(tip_length=0.3, tip_radius=0.08, shaft_radius=0.025)
    plotter.add_mesh(cloud.glyph(orient="motion", scale="motion", factor=1.0, geom=arrow), color=ARROW_COLOUR,
                     show_scalar_bar=False)
    return [[f"motion (arrows x {scale:.3g})", ARROW_COLOUR]]


def _displacement(mesh) -> np.ndarray:
    if "displacement" in mesh.point_data:
        return np.asarray(mesh.point_data["displacement"], float)
    return np.zeros((mesh.n_points, 3))


def _spread(points: np.ndarray, count: int) -> np.ndarray:
    """Indices of about ``count`` points spread evenly (one per cell of a grid)."""
    if len(points) <= count:
        return np.arange(len(points))
    low, high = points.min(axis=0), points.max(axis=0)
    cell = (np.prod(np.maximum(high - low, 1e-12)) / count) ** (1 / 3)
    keys = np.floor((points - low) / cell).astype(np.int64)
    return np.unique(keys, axis=0, return_index=True)[1]


def _add_target(plotter, target) -> list:
    """The target's points (thinned for drawing) over the organs."""
    import pyvista as pv

    points = np.asarray(target.points)
    if len(points) > MAX_TARGET_POINTS:
        points = points[np.random.default_rng(0).choice(len(points), MAX_TARGET_POINTS, replace=False)]
    plotter.add_mesh(pv.PolyData(points), color=TARGET_COLOUR, point_size=3, render_points_as_spheres=True)
    return [["target (points)", TARGET_COLOUR]]


def _add_names(plotter, organs: dict) -> None:
    """Each organ's name, just above its top."""
    if not organs:
        return
    tops = []
    for mesh in organs.values():
        low, high = np.array(mesh.bounds).reshape(3, 2).T
        tops.append([(low[0] + high[0]) / 2, (low[1] + high[1]) / 2, high[2]])
    names = [name.removesuffix("_surface") for name in organs]
    plotter.add_point_labels(np.array(tops), names, font_size=16, bold=True, text_color="#222222",
                             shape_color="white", shape_opacity=0.7, show_points=False, always_visible=True)


def _frame(plotter, meshes) -> None:
    """Look at the given meshes (the organs), not the whole body."""
    import pyvista as pv

    plotter.view_vector(*VIEW_3D)
    bounds = pv.merge([m for m in meshes if m is not None]).bounds
    plotter.reset_camera(bounds=bounds)
    plotter.camera.zoom(0.95)


def _has_faces(mesh) -> bool:
    return len(getattr(mesh, "faces", ())) > 0  # PolyData polygons (not only lines or vertices)


def distance_to(target, points: np.ndarray) -> np.ndarray:
    """Unsigned distance from each point to the target's triangles (exact, libigl)."""
    import igl

    triangles = target.triangulate()
    faces = triangles.faces.reshape(-1, 4)[:, 1:]
    squared = igl.point_mesh_squared_distance(np.asarray(points, float), np.asarray(triangles.points, float),
                                              faces.astype(np.int64))[0]
    return np.sqrt(squared)


def _shared_range(meshes, name: str, quantile: float = 1.0) -> tuple[float, float]:
    values = [np.asarray(m.point_data[name]) for m in meshes if m is not None and m.n_points and name in m.point_data]
    top = float(np.quantile(np.concatenate(values), quantile)) if values else 1.0
    return (0.0, top if top > 0 else 1.0)


# --------------------------------------------------------------------------- 2D


def _picture_2d(groups, reference, context, target, title, off_screen: bool) -> pv.Plotter:
    """The body's cells coloured by |u| with mesh lines; the target as a wide red band
    under each group's curve, so both show where they agree."""
    plotter = offscreen_plotter(off_screen)
    bar = {"title": "displacement", "vertical": True, "position_x": 0.88, "position_y": 0.2, "fmt": "%.3g"}
    clim = _shared_range([context] if context is not None else list(groups.values()), "|u|")
    if context is not None:
        plotter.add_mesh(context, scalars="|u|", cmap="viridis", clim=clim, show_edges=True,
                         edge_color="#555555", line_width=0.5, scalar_bar_args=bar)
    for mesh in (reference or {}).values():
        plotter.add_mesh(mesh, color="black", style="wireframe", opacity=0.35, line_width=1)
    lift = 1e-3 * (context.length if context is not None else 1.0)  # coincident lines: draw order by depth
    if target is not None:
        plotter.add_mesh(target.translate((0, 0, lift)), color="#ff9d9d", line_width=10)
    for i, mesh in enumerate(groups.values()):
        plotter.add_mesh(mesh.translate((0, 0, 2 * lift)), color=GROUP_COLOURS[i % len(GROUP_COLOURS)], line_width=2.5)
    legend = [[name, GROUP_COLOURS[i % len(GROUP_COLOURS)]] for i, name in enumerate(groups)]
    legend += [["undeformed", "black"]] if reference else []
    legend += [["target (red band)", "#ff6b6b"]] if target is not None else []
    _add_legend(plotter, legend, 1400, "upper left")
    if title:
        plotter.add_text(title, font_size=12, position="upper_edge")
    plotter.view_xy()
    plotter.reset_camera()
    plotter.camera.zoom(0.9)
    return plotter


# --------------------------------------------------------------------------- titles


def caption(record: dict, case: str = "", units: str = "") -> str:
    """The picture's title from a result.json record: the command and case, then the
    answer -- the estimated constants (E also as a ratio to the reference material,
    their 95 % interval, or +- sigma, when the record has ``uncertainty``) and the misfit, or a simulation's
    materials and largest displacement."""
    unit = f" {units}" if units else ""
    materials = record.get("materials", {})
    estimated = record.get("estimated")
    if estimated is None:
        what = ", ".join(f"{name} E = {m['E']:.4g}" for name, m in materials.items())
        answer = f"{what}; largest displacement {record.get('max_displacement', 0.0):.3g}{unit}"
        return f"simulate{': ' + case if case else ''}\n{answer}"
    parts = [_estimated(label, record) for label in estimated]
    distance = record.get("surface_distance") or {}
    misfit = f"rms distance to target {distance['rms']:.3g}{unit}" if "rms" in distance else ""
    return f"estimate{': ' + case if case else ''}\n" + ", ".join(parts) + (f"; {misfit}" if misfit else "")


def _estimated(label: str, record: dict) -> str:
    material, key = label.split(".")
    value = record["materials"][material][key]
    spread = (record.get("uncertainty") or {}).get(label, {})
    sigma, interval = spread.get("std"), spread.get("ci95")
    text = f"{material} {key} = {value:.4g}"
    if interval is not None:  # the interval, not +- sigma: a one-sided one (0.84-161 about 3.16) is no +- 4.2
        text += f" (95 %: {interval[0]:.4g}-{interval[1]:.4g})"
    elif sigma is not None and np.isfinite(sigma):
        text += f" ± {sigma:.2g}"
    reference = [(n, m["E"]) for n, m in record["materials"].items() if f"{n}.E" not in record["estimated"]]
    if key == "E" and reference:
        name, E = reference[0]
        text += f" ({value / E:.3g} x {name})"
    return text


# --------------------------------------------------------------------------- result folders


def read_result_folder(folder: Path) -> dict:
    """The saved surfaces of a result folder (``surface_<group>.vtp``, ``target.vtp``) and
    the title from its result.json, as ``render`` arguments; a folder without them, or
    with unreadable ones: one line."""
    import json

    from fenics_elasto.util.errors import require
    from fenics_elasto.files.readers import read_polydata

    folder = Path(folder)
    require(folder.is_dir(), f"{folder}: not a folder (a result folder is expected)" if folder.exists()
            else f"{folder}: no such result folder")
    files = sorted(folder.glob("surface_*.vtp"))
    require(bool(files), f"{folder}: no surface_*.vtp files (is it a result folder?)")
    groups = {f.stem.removeprefix("surface_"): read_polydata(f) for f in files}
    target = read_polydata(folder / "target.vtp") if (folder / "target.vtp").is_file() else None
    for mesh in groups.values():
        if "|u|" not in mesh.point_data:
            mesh.point_data["|u|"] = np.zeros(mesh.n_points)
    dim = 2 if all(np.allclose(m.points[:, 2], 0) for m in groups.values()) else 3
    title = folder.resolve().name
    record_file = folder / "result.json"
    if record_file.is_file():
        try:
            title = caption(json.loads(record_file.read_text()), title)
        except (ValueError, KeyError, TypeError, AttributeError):
            pass  # an old or foreign result.json: the folder's name will do
    return {"groups": groups, "target": target, "title": title, "dim": dim}


def render_folder(folder: Path, out: Path) -> Path:
    """Re-draw a result folder from its saved surfaces."""
    return render(Path(out), **read_result_folder(folder))


def target_polydata(problem):
    """The target as a pyvista mesh: its surfaces padded to 3D, and its landmarks as
    vertices (observed positions)."""
    import pyvista as pv

    from fenics_elasto.inverse.misfit import PointTerm
    from fenics_elasto.geometry.targets import SurfaceTerm

    meshes = []
    for term in problem.misfit.terms:
        if isinstance(term, SurfaceTerm):
            for surface in term.surfaces:
                pts = np.zeros((len(surface.points), 3))
                pts[:, : surface.dim] = surface.points
                conn = np.hstack([np.full((len(surface.cells), 1), surface.cells.shape[1]), surface.cells]).ravel()
                meshes.append(pv.PolyData(pts, lines=conn) if surface.cells.shape[1] == 2 else pv.PolyData(pts, faces=conn))
        elif isinstance(term, PointTerm) and len(term.points):
            pts = np.zeros((len(term.points), 3))
            pts[:, : term.points.shape[1]] = term.points
            meshes.append(pv.PolyData(pts))
    return pv.merge(meshes) if len(meshes) > 1 else meshes[0]


# --------------------------------------------------------------------------- plots


def plot_convergence(result: dict, path: Path) -> Path:
    """Phi* and each estimated constant per evaluation (scan, then outer iterations)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    history = result["history"]
    names = result["estimated"]
    fig, axes = plt.subplots(1, 1 + len(names), figsize=(5 * (1 + len(names)), 4))
    steps = np.arange(len(history))
    outer = np.array([h["stage"] == "outer" for h in history])
    phi = np.array([h["phi"] for h in history])
    axes[0].semilogy(steps[~outer], phi[~outer], "o", color="grey", label="initial scan")
    axes[0].semilogy(steps[outer], phi[outer], "o-", color="C0", label="outer iterations")
    axes[0].set(xlabel="evaluation of Phi*", ylabel="Phi*", title="objective")
    axes[0].legend()
    for k, name in enumerate(names):
        values = np.array([h["theta"][k] for h in history])
        axes[k + 1].plot(steps[~outer], values[~outer], "o", color="grey")
        axes[k + 1].plot(steps[outer], values[outer], "o-", color="C1")
        material, key = name.split(".")
        axes[k + 1].axhline(result["materials"][material][key], color="k", lw=0.8, ls="--")
        axes[k + 1].set(xlabel="evaluation of Phi*", ylabel=name, title=name)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_variance(variance: np.ndarray, path: Path) -> Path:
    """Explained variance per principal component and its running sum."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    k = np.arange(1, len(variance) + 1)
    ax.bar(k, variance, color="C0", label="per component")
    ax.plot(k, np.cumsum(variance), "o-", color="C3", label="cumulative")
    ax.set(xlabel="principal component", ylabel="explained variance (fraction)", ylim=(0, 1.05),
           title="force bases: explained variance")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)
