"""fenics_elasto: elasticity parameter estimation from surface deformation (DOLFINx).

The PyPI wheel of DOLFINx (dolfinx-solver-real) requires ``dolfinx_solver`` to be
imported before ``dolfinx`` and ``petsc4py``; doing it here once means no other module
has to remember. A DOLFINx from conda or a container has no such module, and needs none.
"""

try:
    import dolfinx_solver  # noqa: F401  (must precede dolfinx / petsc4py where that wheel is installed)
except ImportError:  # DOLFINx from conda, a container or a source build
    pass

from fenics_elasto.util.errors import UserError
from fenics_elasto.model.scene import Scene, load_scene

__all__ = ["Scene", "UserError", "load_scene"]
