"""Headless pictures with pyvista: deformed over undeformed, coloured by |u|."""

from __future__ import annotations

from pathlib import Path

import numpy as np

GROUP_COLOURS = ["#e6550d", "#3182bd", "#31a354", "#756bb1", "#d6616b", "#8c6d31"]


def offscreen_plotter(**options):
    """A pyvista plotter that renders off-screen (default: one 1400 x 1000 view)."""
    import os

    # Straight to the off-screen (EGL/OSMesa) window: no failed X connection first.
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    import pyvista as pv

    pv.OFF_SCREEN = True
    return pv.Plotter(off_screen=True, **{"window_size": (1400, 1000), **options})


def render(
    path: Path,
    groups: dict,  # name -> deformed surface (pyvista, with "|u|")
    reference: dict | None = None,  # name -> undeformed surface
    context=None,  # e.g. the whole body (2D: deformed cells; 3D: exterior surface)
    target=None,
    title: str = "",
    dim: int = 3,
) -> Path:
    """Write a PNG: each group deformed and coloured by |u| over its undeformed outline."""
    plotter = offscreen_plotter()
    bar = {"title": "|u|", "vertical": True, "position_x": 0.88, "position_y": 0.2}
    clim = _shared_range([context] if dim == 2 and context is not None else list(groups.values()))
    if context is not None:
        if dim == 2:
            plotter.add_mesh(context, scalars="|u|", cmap="viridis", clim=clim, show_edges=True,
                             edge_color="#555555", line_width=0.5, scalar_bar_args=bar)
        else:
            plotter.add_mesh(context, color="#d9d9d9", opacity=0.12, show_scalar_bar=False)
    for i, (name, mesh) in enumerate(groups.items()):
        if dim == 2:
            plotter.add_mesh(mesh, color=GROUP_COLOURS[i % len(GROUP_COLOURS)], line_width=3, label=name)
        else:
            plotter.add_mesh(mesh, scalars="|u|", cmap="viridis", clim=clim, show_edges=True,
                             edge_color=GROUP_COLOURS[i % len(GROUP_COLOURS)], line_width=0.6,
                             scalar_bar_args=bar if i == 0 else None, show_scalar_bar=i == 0, label=name)
    for mesh in (reference or {}).values():
        plotter.add_mesh(mesh, color="black", style="wireframe", opacity=0.35, line_width=1)
    if target is not None:
        plotter.add_mesh(target, color="red", style="wireframe" if dim == 3 else "surface",
                         opacity=0.5, line_width=2, label="target")
    legend = [[name, GROUP_COLOURS[i % len(GROUP_COLOURS)]] for i, name in enumerate(groups)]
    legend += [["target", "red"]] if target is not None else []
    if legend:
        plotter.add_legend(legend, bcolor="white", face="rectangle", size=(0.2, 0.2), loc="upper left")
    if title:
        plotter.add_text(title, font_size=12, position="upper_edge")
    if dim == 2:
        plotter.view_xy()
    else:
        plotter.view_vector((1.0, -1.6, 0.7), viewup=(0.0, 0.0, 1.0))
    plotter.reset_camera()
    plotter.screenshot(str(path))
    plotter.close()
    return path


def _shared_range(meshes) -> tuple[float, float]:
    values = [m.point_data["|u|"] for m in meshes if m is not None and m.n_points]
    top = max((float(np.max(v)) for v in values), default=1.0)
    return (0.0, top if top > 0 else 1.0)


def read_result_folder(folder: Path) -> dict:
    """The saved surfaces of a result folder (``surface_<group>.vtp``, ``target.vtp``) as
    ``render`` arguments; a folder without them, or with unreadable ones: one line."""
    from fenics_elasto.errors import require
    from fenics_elasto.surface import read_polydata

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
    return {"groups": groups, "target": target, "title": folder.name, "dim": dim}


def render_folder(folder: Path, out: Path) -> Path:
    """Re-draw a result folder from its saved surfaces."""
    return render(Path(out), **read_result_folder(folder))


def target_polydata(problem):
    """The target as a pyvista mesh: its surfaces padded to 3D, and its landmarks as
    vertices (observed positions)."""
    import pyvista as pv

    from fenics_elasto.misfit import PointTerm, SurfaceTerm

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
