"""Meshes: depth fusion, marching cubes, cleaning and decimation; the mesh path's blend (one kernel), its real-time
renderer and finetune's pixels on it, colour baking, mesh scoring.

Above models (it renders depth with them), below the engine."""
