"""``omnirecon bench``: FPS of Omni-Recon's real-time mesh path vs its volumetric path, and their ratio."""

from __future__ import annotations

from omnirecon.engine.speed import BenchConfig, measure
from omnirecon.outputs import claim


class BenchCommand(BenchConfig):
    __doc__ = BenchConfig.__doc__  # the options' description is the command's help

    def main(self) -> None:
        with claim(self.out, "bench", inputs=(self.ckpt,), mode="file", overwrite=self.overwrite):  # checked, locked: see outputs.claim
            r = measure(self)
        print(f"mesh path {r['mesh']['fps']:.1f} FPS, volumetric {r['volumetric']['fps_equivalent']:.5f} FPS "
              f"(extrapolated from {r['volumetric']['rays_per_s']:.0f} rays/s), ratio {r['ratio']:.0f}x -> {self.out}")
