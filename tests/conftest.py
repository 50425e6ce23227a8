"""Shared fixtures. Real scenes come from ../shared/data (present in CI, absent in a user's clone)."""

import os
from pathlib import Path

import pytest
import torch

# Tests run small tensors: one thread is as fast, and on a shared 2-core machine two threads ran
# TSDF fusion 25x and the Omni-Recon overfit 17x slower than one.
torch.set_num_threads(1)

SHARED_DATA = Path(os.environ.get("OMNIRECON_SHARED_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data"))


def shared_scene(rel: str) -> Path:
    """Path of a scene under ../shared/data, or skip the test with the reason."""
    path = SHARED_DATA / rel
    if not path.is_dir():
        if os.environ.get("CI") == "true":
            pytest.fail(f"CI must have {path} (the shared scenes sit beside the clone in CI)")
        pytest.skip(f"{path} not found: the real scenes live in ../shared/data beside the clone "
                    "(set OMNIRECON_SHARED_DATA to point elsewhere)")
    return path


@pytest.fixture
def shared_data():
    return shared_scene
