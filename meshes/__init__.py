"""The built-in scenes' gmsh sources and problem templates (data only; installed with the package)."""
