"""``omnirecon render``: render a camera path through a scene to PNG frames and a video."""

from __future__ import annotations

from dataclasses import replace

from omnirecon.outputs import claim
from omnirecon.workflows.render import RenderConfig, default_out, run_render


class RenderCommand(RenderConfig):
    __doc__ = RenderConfig.__doc__  # the options' description is the command's help

    def main(self) -> None:
        out = default_out(self)
        # The frames, cameras.json and the video are one set: built beside --out, swapped in whole.
        with claim(out, "render", inputs=(self.scene, self.ckpt), mode="replace") as c:
            _, video = run_render(replace(self, out=c.work))
        print(f"wrote {self.frames} frames to {out / 'frames'}" + (f" and {out / video.name}" if video else ""))
