"""From photos or a video to a posed scene: input checks, frame sampling, COLMAP structure from motion
(pycolmap), frame normalisation and pose-alignment metrics. ``omnirecon process`` is the command."""
