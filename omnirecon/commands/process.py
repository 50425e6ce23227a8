"""``omnirecon process``: camera poses for a folder of photos or a video (COLMAP via pycolmap)."""

from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path

import tyro

from omnirecon.capture.colmap_sfm import SfmOptions
from omnirecon.capture.process import process, summary_lines
from omnirecon.errors import InputError
from omnirecon.options import CaptureInput, OutPath, Overwrites, command_defaults
from omnirecon.outputs import prepare_out


@dataclass
@command_defaults(out=Path("outputs/scene"))
class ProcessCommand(CaptureInput, OutPath, Overwrites, SfmOptions):
    """Find camera poses for photos (or a video's frames) with COLMAP: SIFT features, matching,
    incremental mapping, undistortion to PINHOLE. Writes a COLMAP scene (sparse/0, images, images_2,
    images_4, process.json) that every omnirecon command reads. Needs `pip install pycolmap`
    (the `capture` extra)."""

    source: tyro.conf.Positional[Path | None] = None
    """Folder of photos (JPEG/PNG; EXIF orientation honoured) or a video file."""
    max_frames: int = 300
    """Video input: keep at most this many frames."""
    keep_work: bool = False
    """Keep COLMAP's database and raw models in <out>/colmap_work (for debugging)."""
    quiet: bool = False
    """No progress bars."""

    def main(self) -> None:
        try:
            import pycolmap  # noqa: F401  # lazy: the optional 'capture' extra, checked before any work
        except ImportError as e:
            raise InputError("pycolmap is not installed", None,
                             "pip install pycolmap (or pip install -e '.[capture]')") from e
        if self.source is None:
            raise InputError("no input given", None, "pass a folder of photos or a video: omnirecon process PATH --out SCENE")
        prepare_out(self.out)  # the common preflight: writable, nothing in the way, before the run
        options = SfmOptions(**{f.name: getattr(self, f.name) for f in fields(SfmOptions)})
        summary = process(self.source, self.out, options, fps=self.fps, max_frames=self.max_frames,
                          overwrite=self.overwrite, quiet=self.quiet, keep_work=self.keep_work,
                          masks=self.masks)
        for line in summary_lines(summary):
            print(line)
        print(f"wrote {self.out} (read it with any omnirecon command, e.g. omnirecon inspect {self.out})")
