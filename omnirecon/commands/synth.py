"""``omnirecon synth``: generate a batch of procedural scenes in parallel."""

from __future__ import annotations

from omnirecon.data.synth.batch import SynthConfig, run_batch
from omnirecon.outputs import claim


class SynthCommand(SynthConfig):
    __doc__ = SynthConfig.__doc__  # the options' description is the command's help

    def main(self) -> None:
        with claim(self.out, "synth"):  # checked, locked, marked: see outputs.claim
            self.check()
            run_batch(self, quiet=False)
