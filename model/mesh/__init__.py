"""Meshes: the tetrahedral mesh and its surfaces, mesh files, the built-in prostate's geometry and its gmsh
generation."""
