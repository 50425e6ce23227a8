"""``omnirecon finetune``'s pictures and table: the PSNR-vs-seconds curve (``curve.png``), the held-out views
before and after (``before_after.png``), and the curve as a report table (reconstruct's and the demo's)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import torch

from omnirecon.data.io import atomic_path, write_image
from omnirecon.engine.tuning import Setup, Tuned

if TYPE_CHECKING:
    from omnirecon.workflows.finetune import FinetuneConfig


def plot_curve(cfg: FinetuneConfig, s: Setup, t: Tuned, out: Path) -> None:
    """``curve.png``: held-out (and validation) PSNR against seconds of tuning."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.2), dpi=120)
    ts = [c["seconds"] for c in t.curve]
    ax.plot(ts, [c["psnr"] for c in t.curve], "o-", color="C0", label="test (held out), whole image")
    if "psnr_masked" in t.curve[0]:
        ax.plot(ts, [c["psnr_masked"] for c in t.curve], "s-", color="C1", label="test (held out), objects")
    if s.val_px:
        vs = [c["seconds"] for c in t.validation]
        ax.plot(vs, [c["psnr"] for c in t.validation], ".:", color="C0", alpha=0.6, label="validation (current state)")
        if "psnr_masked" in t.validation[0]:
            ax.plot(vs, [c["psnr_masked"] for c in t.validation], ".:", color="C1", alpha=0.6, label="validation, objects")
    ax.set_xlabel(f"seconds of fine-tuning ({cfg.clock} clock)")
    ax.set_ylabel("PSNR (dB)")
    ax.set_title(f"{Path(cfg.scene).name}: mesh path, {len(s.held_px)} held-out views, coverage {t.after['coverage']:.0%}",
                 fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(out / "curve.png") as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def write_before_after(s: Setup, t: Tuned, out: Path) -> None:
    """``before_after.png``: GT | before | after, one row per scored held-out view (the PSNR is their mean: a
    first view alone misled, e.g. dtu_scan24's view 0 has a white backdrop, views 35 and 48 a dark one)."""
    rows = []
    for i, v in enumerate(s.held_px):
        gt = s.scene.images[v.index].float()
        white = torch.ones(gt.shape[0], 2, 3)
        rows += [torch.cat([gt, white, t.before["renders"][i], white, t.after["renders"][i]], 1),
                 torch.ones(2, 3 * gt.shape[1] + 4, 3)]
    write_image(out / "before_after.png", torch.cat(rows[:-1], 0).numpy())


def curve_table(curve: list[dict]) -> tuple[list[str], list[list]]:
    """The curve as a report table: per evaluation, test (held out) and validation PSNR apart, whole image and
    (with masks) objects, and which state was returned."""
    masked = "psnr_masked" in curve[0]
    head = ["seconds", "steps", "test: whole image (dB)", *(["test: objects"] if masked else []),
            "validation: shaded pixels", *(["validation: objects"] if "val_psnr_masked" in curve[0] else []),
            "returned state from (s)", "coverage"]
    rows = [[c["seconds"], c["steps"], round(c["psnr"], 2), *([round(c["psnr_masked"], 2)] if masked else []),
             round(c["val_psnr"], 2), *([round(c["val_psnr_masked"], 2)] if "val_psnr_masked" in c else []),
             c["returned_from"]["seconds"], f"{c['coverage']:.1%}"] for c in curve]
    return head, rows
