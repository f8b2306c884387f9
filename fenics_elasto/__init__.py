"""fenics_elasto: elasticity parameter estimation from surface deformation (DOLFINx).

The public API (``import fenics_elasto as fe``)::

    path = fe.build_scene("letter-a", "out/scene")            # or fe.Scene.from_mesh(...)
    scene = fe.load_scene(path, overrides={"materials.letter.nu": 0.35})
    sim = fe.simulate(scene)                                  # sim.u, sim.surface("outline")
    result = fe.estimate(fe.load_scene(path), fe.Target(surfaces=sim.surface("outline")))
    print(result)                                             # result.values, .std, .ci95

Progress lines are silent from Python until ``fenics_elasto.util.logs.show()``; the
warnings are in ``result.warnings`` either way.

The PyPI wheel of DOLFINx (dolfinx-solver-real) requires ``dolfinx_solver`` to be
imported before ``dolfinx`` and ``petsc4py``; doing it here once means no other module
has to remember. A DOLFINx from conda or a container has no such module, and needs none.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    import dolfinx_solver  # noqa: F401  (must precede dolfinx / petsc4py where that wheel is installed)
except ImportError:  # DOLFINx from conda, a container or a source build
    pass

from fenics_elasto.util.memory import retain_freed_memory
from fenics_elasto.util.threads import share_cores_among_ranks

share_cores_among_ranks()  # under mpiexec: one BLAS thread per core share, not per core
retain_freed_memory()  # big blocks freed and allocated again reuse their pages (util/memory.py)

from fenics_elasto.util.errors import UserError  # noqa: E402
from fenics_elasto.model.scene import Scene  # noqa: E402
from fenics_elasto.inverse.reduction.bases import Bases  # noqa: E402
from fenics_elasto.app.target import Target  # noqa: E402
from fenics_elasto.app.outcomes import Estimate, Simulation  # noqa: E402
from fenics_elasto.app.api import build_scene, estimate, load_scene, render, scene_from_spec, simulate, train  # noqa: E402

try:
    __version__ = version("fenics_elasto")
except PackageNotFoundError:  # run from a source tree that was never installed
    __version__ = "0+unknown"

__all__ = ["Bases", "Estimate", "Scene", "Simulation", "Target", "UserError", "__version__", "build_scene", "estimate",
           "load_scene", "render", "scene_from_spec", "simulate", "train"]
