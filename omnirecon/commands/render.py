"""``omnirecon render``: render a camera path through a scene to PNG frames and a video."""

from __future__ import annotations

from omnirecon.workflows.render import RenderConfig, run_render


class RenderCommand(RenderConfig):
    __doc__ = RenderConfig.__doc__  # the options' description is the command's help

    def main(self) -> None:
        out, video = run_render(self)
        print(f"wrote {self.frames} frames to {out / 'frames'}" + (f" and {video}" if video else ""))
