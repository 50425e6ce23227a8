"""``omnirecon finetune``: tune Omni-Recon's mesh path on one scene in seconds; PSNR-vs-time curve."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from omnirecon.outputs import claim
from omnirecon.workflows.finetune import FinetuneConfig, run_finetune


class FinetuneCommand(FinetuneConfig):
    __doc__ = FinetuneConfig.__doc__  # the options' description is the command's help

    def main(self) -> None:
        out = self.out or Path("outputs/finetune") / Path(self.scene).name  # the workflow's default
        # curve.json, the pictures and the tuned checkpoint are one set: built beside --out, swapped in whole.
        with claim(out, "finetune", inputs=(self.ckpt, self.scene, self.mesh), mode="replace") as c:
            result = run_finetune(replace(self, out=c.work))
        c = result["curve"]
        print(f"held-out PSNR {c[0]['psnr']:.2f} dB before, " + ", ".join(
            f"{p['psnr']:.2f} dB after {p['seconds']:g} s ({p['steps']} steps)" for p in c[1:])
            + f"; coverage {result['coverage']:.1%} of held-out pixels on the mesh (the rest: {result['fill']} fill)")
        d = result.get("defects") or {}
        if d:
            print(f"held-out pixels on faces no photo supports: {d['any']:.1%} (fills {d['fill']:.1%}, unseen "
                  f"{d['unseen']:.1%}, fragments {d['small']:.1%})")
        print(f"wrote {out}/curve.json, curve.png, before_after.png")
