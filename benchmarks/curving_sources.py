"""Where a straight-sided source's error comes from: one set of vertices, its surface
midpoints from gmsh's geometry or from the toolkit's curving, group by group.

gmsh's order-1 and order-2 meshes of one geometry do not share their vertices, so
comparing them mixes two meshes' errors. Here every source has the vertices of gmsh's
order-2 mesh of the pelvis phantom (untangled only where needed, HighOrderOptimize = 1):

- that mesh as gmsh made it (exact midpoints);
- the same mesh made straight-sided (setOrder(1)), curved on load by the toolkit;
- that curved mesh with gmsh's exact midpoints put back on one group (or all), its
  cells untangled by gmsh's optimiser where the exact midpoints fold them.

Each is estimated through the README's workflow (family3d.py: train --synthetic 120
--rank 80, the truth's organ surfaces and 4 fiducials, prostate E = 50 by default).

    .venv/bin/python benchmarks/curving_sources.py [--out DIR] [--E 50] [--groups rectum bones all]
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import family3d  # noqa: E402
import independent as ind  # noqa: E402
from fenics_elasto.mesh.curving import curve_mesh  # noqa: E402
from fenics_elasto.mesh.gmsh_models import node_positions  # noqa: E402
from fenics_elasto.mesh.meshcheck import folds  # noqa: E402

GROUPS = ("bladder", "prostate_surface", "rectum", "bones", "skin")
TRIANGLE_EDGES = ((0, 1, 3), (1, 2, 4), (2, 0, 5))  # gmsh's 6-node triangle: (end, end, midpoint)


def surface_midpoints(gmsh, group: str) -> dict:
    """(the group's surface edges by their ends' rounded positions) -> (midpoint node tag, position)."""
    position = node_positions(gmsh)
    tag = next(t for _, t in gmsh.model.getPhysicalGroups(2) if gmsh.model.getPhysicalName(2, t) == group)
    out = {}
    for entity in gmsh.model.getEntitiesForPhysicalGroup(2, tag):
        rows = np.asarray(gmsh.model.mesh.getElementsByType(9, entity)[1], np.int64).reshape(-1, 6)
        for a, b, m in TRIANGLE_EDGES:
            for ends, mid in zip(np.round(position[rows[:, [a, b]]], 9), rows[:, m]):
                out[tuple(sorted(map(tuple, ends)))] = (int(mid), position[mid])
    return out


def straight_copy(exact: Path, folder: Path) -> Path:
    """gmsh's order-2 source made straight-sided (setOrder(1): the same vertices)."""
    folder.mkdir(parents=True, exist_ok=True)
    with ind.gmsh_model("straight") as gmsh:
        gmsh.open(str(exact / "source.msh"))
        gmsh.model.mesh.setOrder(1)
        gmsh.write(str(folder / "source.msh"))
    shutil.copy(exact / "problem.toml", folder / "problem.toml")
    return folder / "problem.toml"


def hybrid(exact: Path, straight: Path, groups: list[str], folder: Path) -> Path:
    """The straight copy curved by the toolkit, with gmsh's exact midpoints on ``groups``."""
    folder.mkdir(parents=True, exist_ok=True)
    with ind.gmsh_model("exact") as gmsh:
        gmsh.open(str(exact / "source.msh"))
        wanted = {group: surface_midpoints(gmsh, group) for group in groups}
    with ind.gmsh_model("hybrid") as gmsh:
        gmsh.open(str(straight / "source.msh"))
        curve_mesh(gmsh, 3)
        for group in groups:
            for key, (node, _) in surface_midpoints(gmsh, group).items():
                gmsh.model.mesh.setNode(node, wanted[group][key][1], [])
        gmsh.model.mesh.optimize("HighOrder")  # cells the exact midpoints fold, as gmsh's own mesh was untangled
        tags = gmsh.model.mesh.getElementsByType(11)[0]
        assert not folds(gmsh, tags).any(), "gmsh's optimiser left folded cells"
        gmsh.write(str(folder / "source.msh"))
    shutil.copy(straight / "problem.toml", folder / "problem.toml")
    return folder / "problem.toml"


def sources(out: Path, groups: list[str]) -> dict[str, Path]:
    exact = ind.plain_source(out / "sources", 2, optimize=1).parent
    straight = straight_copy(exact, out / "sources" / "straight")
    rows = {"gmsh order 2 (exact midpoints)": exact / "problem.toml",
            "the same vertices straight, curved on load": straight}
    for group in groups:
        chosen = list(GROUPS) if group == "all" else [group]
        rows[f"... with exact midpoints on {group}"] = hybrid(exact, straight.parent, chosen,
                                                               out / "sources" / f"exact-{group}")
    return rows


def run(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("out/curving_sources"))
    parser.add_argument("--E", type=float, default=50.0)
    parser.add_argument("--groups", nargs="+", default=["rectum", "bones", "all"], choices=[*GROUPS, "all"])
    args = parser.parse_args(argv)
    lines = ["| source | E | error | 95 % interval | parts of sigma | warnings |", "|---|---|---|---|---|---|"]
    for i, (name, problem) in enumerate(sources(args.out, args.groups).items()):
        result = family3d.estimate_on(problem, args.out, f"row{i}", 0, args.E, [])
        found = result["materials"]["prostate"]["E"]
        u = result["uncertainty"]["prostate.E"]
        parts = " ".join(f"{k} {v:.2f}" for k, v in u.get("parts", {}).items())
        lines.append(f"| {name} | {found:.2f} | {100 * (found / args.E - 1):+.2f} % | [{u['ci95'][0]:.2f}, "
                     f"{u['ci95'][1]:.2f}] | {parts} | {len(result['warnings'])} |")
        print(lines[-1], flush=True)
    print("\n".join(lines))


if __name__ == "__main__":
    run()
