"""Two label maps of one body -> E +- sigma and a picture, in a few commands (issue #34 item 4).

The images are made here so that the truth is known: a rest label map -- a kidney
(label 1, an ellipsoid on anisotropic, rotated voxels) holding a tumour (label 2, a ball
4x stiffer) -- and the deformed one, the exact shapes moved by the displacement that
`simulate` computes with a probe pressing one side of the kidney, its hilum held, and
voxelized on the rest map's grid (x -> the shapes' label at X with X + u(X) = x, by
fixed-point steps), as a second scan of the same patient would be. The toolkit made
this truth, so it checks the chain, not the accuracy (validation.md has those).

The chain a user runs (printed with its output):

    fenics-elasto scene spec.toml --out src                      # rest label map -> mesh
    fenics-elasto train src/problem.toml --synthetic 60 --rank 24 --out bases.npz
    fenics-elasto estimate src/problem.toml --out est --set "reduction={bases='bases.npz'}" \\
        --set "target={labels={image='deformed.nii.gz', outer=[1, 2], tumour_surface=2}}"
    fenics-elasto render est --out est.png

    .venv/bin/python benchmarks/labelmap_chain.py [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import labelmaps as lm  # noqa: E402
from fenics_elasto.app.cli import main  # noqa: E402

TRUE_RATIO = 4.0
def sides() -> dict:
    """The hilum at one end of the kidney's long axis, the probe at the other's side: name
    -> (point, normal) of each cutting plane; "push": the probe's displacement."""
    axis = lm.rotation() @ np.array([1.0, 0.0, 0.0])  # the ellipsoid's first axis, in the world
    side = lm.rotation() @ np.array([0.0, 1.0, 0.0])
    centre = lm.world_centre()
    return {"hilum": (centre - 0.8 * lm.AXES[0] * axis, -axis), "probe": (centre + 0.7 * lm.AXES[1] * side, side),
            "push": -4.5 * side}


def warped(labels: np.ndarray, u) -> np.ndarray:
    """The deformed label map on the rest map's grid: each voxel centre x takes the exact
    shapes' label at X, X + u(X) = x -- the deformed shapes voxelized, as a second scan
    would be. (Until 2026-12-07 it took the rest map's label at the voxel nearest X: a
    half-voxel jitter no scan has, which left the 6 mm tumour's interval missing once the
    label surfaces were smoothed.)"""
    from fenics_elasto.model.observation import distances_to_body, probe

    affine = lm.affine()
    ijk = np.indices(labels.shape).reshape(3, -1).T
    x = ijk @ affine[:3, :3].T + affine[:3, 3]
    mesh = u.function_space.mesh
    near = distances_to_body(mesh, x) < 6.0  # voxels the body may reach; the rest stay background
    X = x[near].copy()
    for _ in range(6):  # fixed point: u is small and smooth
        inside = distances_to_body(mesh, X) <= 0.0
        shift = np.zeros_like(X)
        shift[inside] = probe(u, X[inside])
        X = x[near] - shift
    out = np.zeros(labels.size, labels.dtype)
    out[np.flatnonzero(near)] = lm.labels_at(X)
    return out.reshape(labels.shape)


def run(out: Path) -> None:
    import fenics_elasto as fe

    out.mkdir(parents=True, exist_ok=True)
    rest = lm.label_map()
    lm.write_nifti(out / "rest.nii.gz", rest)
    geometry = sides()
    (out / "spec.toml").write_text(lm.kidney_spec("rest.nii.gz", 2.5, {k: geometry[k] for k in ("hilum", "probe")}))
    assert main(["scene", str(out / "spec.toml"), "--out", str(out / "src")]) == 0
    problem = out / "src" / "problem.toml"
    truth = fe.load_scene(problem, overrides={"materials.tumour.E": TRUE_RATIO * 10.0, "boundary.fixed": ["hilum"],
                                              "boundary.displacement.probe": {"value": geometry["push"].tolist()}})
    simulation = fe.simulate(truth)
    lm.write_nifti(out / "deformed.nii.gz", warped(rest, simulation.u))
    bases = out / "bases.npz"
    common = ["--set", "boundary.fixed=['hilum']", "--set", "boundary.loaded=['probe']",
              "--set", "boundary.matched=['outer', 'tumour_surface']"]
    assert main(["train", str(problem), "--synthetic", "60", "--rank", "24", "--out", str(bases)] + common) == 0
    target = f"target={{labels={{image='{out / 'deformed.nii.gz'}', outer=[1, 2], tumour_surface=2}}}}"
    assert main(["estimate", str(problem), "--out", str(out / "est"), "--set", f"reduction={{bases='{bases}'}}",
                 "--set", target] + common) == 0
    assert main(["render", str(out / "est"), "--out", str(out / "est.png")]) == 0
    result = json.loads((out / "est" / "result.json").read_text())
    E, entry = result["materials"]["tumour"]["E"], result["uncertainty"]["tumour.E"]
    print(f"tumour E = {E:.2f} +- {entry['std']:.2f} (95 %: {entry['ci95'][0]:.2f}-{entry['ci95'][1]:.2f}); "
          f"truth {TRUE_RATIO * 10:g}; picture {out / 'est.png'}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("out/labelmap_chain"))
    run(parser.parse_args().out)
