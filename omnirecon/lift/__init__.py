"""Zero-shot 3-D understanding: lift any per-view 2-D prediction into novel views with a model's own
colour blend weights and ray weights (Omni-Recon's predict-then-blend, ``omnirecon.md`` §8).

* :mod:`omnirecon.lift.predictors`: the :class:`~omnirecon.lift.predictors.Predictor` plug-in interface
  (image -> ``[H, W, C]`` map with a kind) and offline built-ins (Sobel, Canny, Harris, SLIC, oracles
  from procedural ground truth, a noisy oracle, a fitted k-NN pixel classifier);
* :mod:`omnirecon.lift.blend`: :func:`~omnirecon.lift.blend.lift_view` (predict-then-blend, volumetric),
  :func:`~omnirecon.lift.blend.lift_mesh_view` (through a baked mesh) and
  :func:`~omnirecon.lift.blend.render_then_predict` (the baseline);
* :mod:`omnirecon.lift.surface`: the mesh of a scene (exact, baked or a file) and per-face labels;
* :mod:`omnirecon.lift.tune`: LoRA / bias-only tuning of the appearance branch on lifted semantics;
* :mod:`omnirecon.lift.edit`: recolour / remove an object in the sources and re-blend; face edits, GLB;
* :mod:`omnirecon.lift.embed`: dense embeddings (HED VGG features, CLIP/LSeg) classified by cosine;
* :mod:`omnirecon.lift.metrics`: mIoU, edge F-score, keypoint heat-map error, normal error;
* :mod:`omnirecon.workflows.lift`: ``omnirecon lift``.

Models take ``signals # [K, H, W, C]`` in ``render_rays`` / ``render_view`` and return ``signal``: the maps
blended exactly as their RGB (Omni-Recon, IBRNet: final pass; GPNR: the weights of ``rgb_blend``, its
blended source colours).
"""

from omnirecon.lift.blend import (
                                  lift_mesh_view,
                                  lift_points,
                                  lift_view,
                                  predict_then_blend,
                                  render_lifted,
                                  render_lifted_mesh,
                                  render_then_predict,
                                  supports_lifting,
)
from omnirecon.lift.predictors import Predictor, builtin

__all__ = ["Predictor", "builtin", "lift_mesh_view", "lift_points", "lift_view", "predict_then_blend", "render_lifted",
           "render_lifted_mesh", "render_then_predict", "supports_lifting"]
