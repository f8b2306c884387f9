# petsc4py for mypy: every name Any (its own stubs type PETSc's enums as classes where
# the API hands out ints, and would need a cast at every call). pyproject: [tool.mypy].
from typing import Any

def __getattr__(name: str) -> Any: ...
