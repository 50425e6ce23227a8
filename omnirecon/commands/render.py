"""``omnirecon render``: render a camera path through a scene to PNG frames and a video."""

from __future__ import annotations

from omnirecon.outputs import prepare_out
from omnirecon.workflows.render import RenderConfig, run_render


class RenderCommand(RenderConfig):
    __doc__ = RenderConfig.__doc__  # the options' description is the command's help

    def main(self) -> None:
        prepare_out(self.out)  # writable, stale temporaries gone: before any work
        out, video = run_render(self)
        print(f"wrote {self.frames} frames to {out / 'frames'}" + (f" and {video}" if video else ""))
