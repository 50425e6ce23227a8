"""Meshes: depth fusion, marching cubes, cleaning and decimation; the real-time mesh IBR path, colour
baking, mesh scoring.

Above models (it renders depth with them), below the engine."""
