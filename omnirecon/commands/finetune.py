"""``omnirecon finetune``: tune Omni-Recon's mesh path on one scene in seconds; PSNR-vs-time curve."""

from __future__ import annotations

from omnirecon.outputs import prepare_out
from omnirecon.workflows.finetune import FinetuneConfig, run_finetune


class FinetuneCommand(FinetuneConfig):
    __doc__ = FinetuneConfig.__doc__  # the options' description is the command's help

    def main(self) -> None:
        prepare_out(self.out)  # writable, stale temporaries gone: before any work
        result = run_finetune(self)
        c = result["curve"]
        print(f"held-out PSNR {c[0]['psnr']:.2f} dB before, " + ", ".join(
            f"{p['psnr']:.2f} dB after {p['seconds']:g} s ({p['steps']} steps)" for p in c[1:])
            + f"; coverage {result['coverage']:.1%} of held-out pixels on the mesh (the rest: {result['fill']} fill)")
        print(f"wrote {result['out']}/curve.json, curve.png, before_after.png")
