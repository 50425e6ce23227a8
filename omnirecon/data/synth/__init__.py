"""Procedural scenes with exact ground truth (``omnirecon synth``).

Textured primitives on an optional ground, rendered from a camera rig by a vectorised z-buffer
rasterizer that draws exactly the triangles of the exported mesh. See :mod:`.generate` for the
folder layout.
"""

from omnirecon.data.synth.generate import GENERATOR_VERSION, SynthOptions, generate_scene

__all__ = ["GENERATOR_VERSION", "SynthOptions", "generate_scene"]
