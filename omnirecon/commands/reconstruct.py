"""``omnirecon reconstruct``: photos or a video to a mesh, a tuned model, a web viewer and a report page."""

from __future__ import annotations

from omnirecon.workflows.reconstruct import ReconstructConfig, run_reconstruct


class ReconstructCommand(ReconstructConfig):
    __doc__ = ReconstructConfig.__doc__  # the options' description is the command's help

    def main(self) -> None:
        record = run_reconstruct(self)
        print(f"wrote {record['report']} (timings: " + ", ".join(f"{k} {v:.1f} s" for k, v in record["seconds"].items())
              + ")")
