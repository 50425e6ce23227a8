"""``omnirecon train``: train a generalizable model on procedural and real scenes (torchrun for DDP)."""

from __future__ import annotations

import os
import sys
from contextlib import nullcontext
from pathlib import Path

from omnirecon.engine.distributed import DistEnv
from omnirecon.engine.train import Trainer
from omnirecon.engine.train_config import TrainConfig
from omnirecon.outputs import claim


class TrainCommand(TrainConfig):
    __doc__ = TrainConfig.__doc__  # the options' description is the command's help

    def main(self) -> None:
        env = DistEnv.from_env()
        # One run per folder (rank 0 holds the lock; --resume continues the folder, never replaces it).
        inputs = (*self.data, *(self.val_scenes or ()))
        with claim(self.out or Path("outputs/train") / self.model, "train", inputs=inputs, recursive=True,
                   adopt=self.resume) \
                if env.rank == 0 else nullcontext():
            trainer = Trainer(self, env)
            try:
                trainer.run()
            finally:
                trainer.close()
        if env.world > 1:  # clean exit recipe (docs/deps.md §7): avoids a teardown abort in gloo
            import torch.distributed as dist

            dist.barrier()
            dist.destroy_process_group()
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(0)
