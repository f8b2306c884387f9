"""fenics_elasto: elasticity parameter estimation from surface deformation (DOLFINx).

The DOLFINx wheel requires ``dolfinx_solver`` to be imported before ``dolfinx`` and
``petsc4py``; doing it here once means no other module has to remember.
"""

import dolfinx_solver  # noqa: F401  (must precede dolfinx / petsc4py)

from fenics_elasto.util.errors import UserError
from fenics_elasto.model.scene import Scene, load_scene

__all__ = ["Scene", "UserError", "load_scene"]
