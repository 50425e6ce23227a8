"""Process-group membership for multi-process training (``torchrun``; world 1 without it)."""

from __future__ import annotations

import os
from dataclasses import dataclass


@dataclass
class DistEnv:
    """Process group membership from torchrun's environment (world 1 without torchrun)."""

    world: int = 1
    rank: int = 0
    local_rank: int = 0

    @staticmethod
    def from_env() -> DistEnv:
        return DistEnv(int(os.environ.get("WORLD_SIZE", 1)), int(os.environ.get("RANK", 0)),
                       int(os.environ.get("LOCAL_RANK", 0)))

    @property
    def main(self) -> bool:
        return self.rank == 0
