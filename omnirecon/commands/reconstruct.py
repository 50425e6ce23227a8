"""``omnirecon reconstruct``: photos or a video in; a mesh, a tuned real-time mesh path, an export and a
report out."""

from __future__ import annotations

from omnirecon.workflows.reconstruct import ReconstructConfig, run_reconstruct


class ReconstructCommand(ReconstructConfig):
    __doc__ = ReconstructConfig.__doc__  # the options' description is the command's help

    def main(self) -> None:
        record = run_reconstruct(self)
        for line in record["lines"]:
            print(line)
        kept = record.get("resumed", {})
        print("seconds: " + ", ".join(f"{k} {v:.1f}" + (f" (kept from an earlier run: {kept[k]:.1f})" if k in kept else "")
                                      for k, v in record["seconds"].items()))
        print(f"report: {record['report']}; viewer: omnirecon view {self.out / 'export'}")
