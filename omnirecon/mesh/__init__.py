"""Meshes: depth fusion, marching cubes, cleaning, decimation and the mesh path."""
