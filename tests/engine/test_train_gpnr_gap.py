"""bench/train_gpnr_gap.py's per-view statistics."""

import math

import torch

from bench.train_gpnr_gap import summary, view_stats


def test_view_stats_counts_dark_leaks_and_unseen_pixels():
    """A 2x2 white ground truth rendered with one black pixel: PSNR 10 log10(4), one dark leak in four pixels,
    one pixel no source sees; a dark ground-truth pixel rendered dark is no leak, a pixel off by 0.4 no gross error."""
    gt = torch.ones(2, 2, 3)
    pred = gt.clone()
    pred[0, 0] = 0.0
    seen = torch.tensor([[True, True], [True, False]])
    s = view_stats(pred, gt, seen)
    assert abs(s["psnr"] - 10 * math.log10(4)) < 1e-3
    assert s["dark_leak"] == 0.25 and s["gross"] == 0.25 and s["unseen"] == 0.25
    assert s["gt_mean"] == 1.0 and s["mean"] == 0.75
    gt[0, 0] = 0.0
    assert view_stats(pred, gt, seen)["dark_leak"] == 0.0 and view_stats(pred, gt, seen)["gross"] == 0.0
    pred[0, 1] = 0.6  # off by 0.4: not gross, not dark
    assert view_stats(pred, gt, seen)["gross"] == 0.0 and view_stats(pred, gt, seen)["dark_leak"] == 0.0
    views = [{m: {"psnr": p, "dark_leak": 0.0} for m in ("gpnr-tiny", "ibrnet-tiny")} for p in (10.0, 20.0)]
    assert summary(views)["gpnr-tiny"]["psnr"] == 15.0
