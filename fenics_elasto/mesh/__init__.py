"""Meshes: gmsh quietly, meshes checked before DOLFINx reads them, built-in scenes, scenes from anatomy, atlases."""
