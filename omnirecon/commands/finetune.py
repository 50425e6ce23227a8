"""``omnirecon finetune``: tune Omni-Recon's mesh path on one scene in seconds; PSNR-vs-time curve."""

from __future__ import annotations

from omnirecon.outputs import claim
from omnirecon.workflows.finetune import FinetuneConfig, run_finetune


class FinetuneCommand(FinetuneConfig):
    __doc__ = FinetuneConfig.__doc__  # the options' description is the command's help

    def main(self) -> None:
        with claim(self.out, "finetune", inputs=(self.ckpt, self.scene, self.mesh)):  # see outputs.claim
            result = run_finetune(self)
        c = result["curve"]
        print(f"held-out PSNR {c[0]['psnr']:.2f} dB before, " + ", ".join(
            f"{p['psnr']:.2f} dB after {p['seconds']:g} s ({p['steps']} steps)" for p in c[1:]))
        print(f"wrote {result['out']}/curve.json, curve.png, before_after.png")
