"""reconstruct's stage clock: seconds, CPU seconds and the peak memory of each stage on its own."""

import sys

import numpy as np
import pytest

from omnirecon.workflows.reconstruct import Laps


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="peak memory per stage reads /proc (Linux)")
def test_each_stage_gets_its_own_peak_memory():
    lap = Laps()
    big = np.ones(50_000_000)  # 400 MB touched in this stage only
    assert big.sum() > 0
    del big
    lap("big")
    small = np.ones(1000)
    assert small.sum() > 0
    lap("small")
    assert set(lap.peak_rss_mb) == {"big", "small"} == set(lap.seconds) == set(lap.cpu_seconds)
    assert lap.peak_rss_mb["big"] - lap.peak_rss_mb["small"] > 300  # the mark was reset between the stages
