"""Draw the figures of docs/conventions.md from the library's own camera code.

    python docs/make_figures.py            # writes docs/figures/conventions.png
"""

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Line3DCollection  # noqa: E402

from omnirecon.cameras import Cameras, canonical_transform, look_at  # noqa: E402


def main(out: Path = Path(__file__).parent / "figures" / "conventions.png") -> None:
    fig = plt.figure(figsize=(15, 5.6), dpi=110)

    # (a) the camera frame, drawn from a real Cameras object
    ax = fig.add_subplot(1, 3, 1, projection="3d")
    c2w = look_at(torch.tensor([[0.0, -3.0, 1.0]]), torch.zeros(3), torch.tensor([0, 0, 1.0]))
    cam = Cameras(torch.tensor([40.0]), torch.tensor([40.0]), torch.tensor([32.0]), torch.tensor([24.0]), c2w, 64, 48)
    corners = torch.tensor([[[0, 0], [64, 0], [64, 48], [0, 48]]], dtype=torch.float32)
    pts = cam.unproject(corners, torch.ones(1, 4))[0].numpy()
    c = cam.centers[0].numpy()
    segs = [[c, p] for p in pts] + [[pts[i], pts[(i + 1) % 4]] for i in range(4)]
    ax.add_collection3d(Line3DCollection(segs, colors="gray"))
    for k, (name, col) in enumerate(zip("xyz", ("tab:red", "tab:green", "tab:blue"))):
        axis = cam.R[0, :, k].numpy() * 0.8
        ax.quiver(*c, *axis, color=col, arrow_length_ratio=0.15)
        ax.text(*(c + axis * 1.15), f"{name}", color=col, fontsize=12)
    ax.text(*pts[0], "pixel (0,0)\ncorner", fontsize=8)
    ax.scatter(0, 0, 0, color="k")
    ax.text(0, 0, 0.1, "look-at", fontsize=8)
    ax.set_xlim(-1.5, 1.5), ax.set_ylim(-3.2, 0.3), ax.set_zlim(-0.5, 2)
    ax.set_title("(a) OpenCV camera: x right, y down, z forward;\nc2w columns = axes in world, last column = centre")

    # (b) pixel grid and centres
    ax = fig.add_subplot(1, 3, 2)
    w, h = 4, 3
    for x in range(w + 1):
        ax.plot([x, x], [0, h], color="gray", lw=0.8)
    for y in range(h + 1):
        ax.plot([0, w], [y, y], color="gray", lw=0.8)
    uv = Cameras(torch.ones(1), torch.ones(1), torch.zeros(1), torch.zeros(1), torch.eye(4)[None], w, h).pixel_centers()
    ax.scatter(uv[..., 0].ravel(), uv[..., 1].ravel(), color="tab:blue", s=18)
    ax.annotate("centre of pixel (row 0, col 0) = (0.5, 0.5)", (0.5, 0.5), (1.2, -0.45), arrowprops=dict(arrowstyle="->"), fontsize=8)
    ax.annotate("(u, v) = (0, 0): image corner", (0, 0), (-0.7, -0.75), arrowprops=dict(arrowstyle="->"), fontsize=8)
    ax.annotate("", (w, h + 0.25), (0, h + 0.25), arrowprops=dict(arrowstyle="->", color="tab:red"))
    ax.text(w / 2, h + 0.6, "u (width)", color="tab:red", ha="center")
    ax.annotate("", (-0.25, h), (-0.25, 0), arrowprops=dict(arrowstyle="->", color="tab:green"))
    ax.text(-0.45, h / 2, "v (height)", color="tab:green", rotation=90, va="center")
    ax.set_xlim(-0.8, w + 0.5), ax.set_ylim(h + 1.0, -0.9), ax.set_aspect("equal"), ax.axis("off")
    ax.set_title("(b) pixels: continuous (u, v), centres at +0.5;\nresizing by s scales fx, fy, cx, cy by s")

    # (c) GPNR canonical frame of one target ray
    ax = fig.add_subplot(1, 3, 3, projection="3d")
    o, d = cam.rays(torch.tensor([[[50.0, 12.0]]]))
    T = canonical_transform(o[0, 0], d[0, 0], cam.R[0, :, 1])
    R = T[:3, :3].numpy()
    o_np, d_np = o[0, 0].numpy(), d[0, 0].numpy()
    ax.plot(*np.stack([o_np, o_np + 3.2 * d_np]).T, color="k", lw=2, label="target ray")
    for row, (name, col) in enumerate(zip(("x' = u' x d", "y' = up projected", "z' = d"), ("tab:red", "tab:green", "tab:blue"))):
        ax.quiver(*o_np, *(R[row] * 0.8), color=col, arrow_length_ratio=0.15)
        ax.text(*(o_np + R[row] * 0.95), name, color=col, fontsize=8)
    ax.set_xlim(-1.5, 1.5), ax.set_ylim(-3.2, 0.3), ax.set_zlim(-0.5, 2)
    ax.legend(fontsize=8)
    ax.set_title("(c) canonical frame of a target ray (GPNR): rows of R\nare orthonormal, det = +1; ray -> origin, +z")
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
