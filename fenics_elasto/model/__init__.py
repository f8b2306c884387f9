"""The forward model: a scene (mesh, groups, materials), K(theta), its solvers, fields
from boundary controls, and where they are observed."""
