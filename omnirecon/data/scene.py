"""The one in-memory scene type that every reader returns."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import torch
from torch import Tensor

from omnirecon.cameras import Cameras
from omnirecon.errors import InputError


@dataclass
class Scene:
    """A posed multi-view capture in the *scene frame*.

    The scene frame is the frame the reader chose to work in (often the input frame itself, or a
    normalised one where the object fits in a unit sphere). ``to_input`` maps it back, so that
    meshes and points exported from the scene frame land in the user's own coordinates.
    """

    images: Tensor
    """RGB in [0, 1], composited on ``background`` where the input had alpha. ``# [N, H, W, 3]`` float32"""
    cameras: Cameras
    """One camera per image, in the scene frame (OpenCV, camera-to-world)."""
    near: Tensor
    """Per-view near z-depth bound in scene units. ``# [N]``"""
    far: Tensor
    """Per-view far z-depth bound in scene units. ``# [N]``"""
    bounds: Tensor
    """Axis-aligned box holding the content, ``[min, max]`` in the scene frame. ``# [2, 3]``"""
    splits: dict[str, list[int]]
    """View indices per split (at least ``"all"``; readers add ``train``/``val``/``test`` when known)."""
    to_input: Tensor = field(default_factory=lambda: torch.eye(4, dtype=torch.float64))
    """Similarity (rotation x scale + translation) from the scene frame to the input frame. ``# [4, 4]``"""
    masks: Tensor | None = None
    """Foreground masks. ``# [N, H, W]`` bool"""
    depths: Tensor | None = None
    """Metric z-depth in scene units, 0 where unknown or background. ``# [N, H, W]`` float32"""
    normals: Tensor | None = None
    """World-frame unit surface normals, 0 where unknown. ``# [N, H, W, 3]`` float32"""
    labels: Tensor | None = None
    """Per-pixel object ids, 0 = background. ``# [N, H, W]`` int64"""
    names: list[str] = field(default_factory=list)
    """Image file name per view (for messages and outputs)."""
    format: str = "unknown"
    """Reader that produced the scene, e.g. ``"blender"``."""
    path: Path | None = None
    """Folder the scene was read from."""
    rig: str = "unknown"
    """``"object"`` (cameras around the content), ``"forward"`` (forward-facing) or ``"unknown"``."""
    background: tuple[float, float, float] | None = None
    """Colour the images were composited on, when the input had alpha."""
    mesh_path: Path | None = None
    """Exact ground-truth mesh file, when the scene has one (procedural scenes)."""
    mesh_to_scene: Tensor = field(default_factory=lambda: torch.eye(4, dtype=torch.float64))
    """Similarity from the mesh file's coordinates to the scene frame. ``# [4, 4]``"""
    meta: dict = field(default_factory=dict)
    """Reader-specific extras (JSON-serialisable)."""

    def __post_init__(self) -> None:
        if "all" not in self.splits:
            self.splits = {"all": list(range(len(self))), **self.splits}
        if not self.names:
            self.names = [f"view_{i:04d}" for i in range(len(self))]

    def __len__(self) -> int:
        return self.images.shape[0]

    @property
    def height(self) -> int:
        return self.images.shape[1]

    @property
    def width(self) -> int:
        return self.images.shape[2]

    @property
    def scale_to_input(self) -> float:
        """Length of one scene unit in input units."""
        return float(torch.linalg.det(self.to_input[:3, :3]).abs() ** (1.0 / 3.0))

    def subset(self, indices) -> Scene:
        """The views ``indices`` as a new scene (splits are re-indexed; views not kept are dropped)."""
        idx = torch.as_tensor(list(indices), dtype=torch.long)
        remap = {int(old): new for new, old in enumerate(idx)}
        pick = lambda t: None if t is None else t[idx]  # noqa: E731
        splits = {k: [remap[i] for i in v if i in remap] for k, v in self.splits.items() if k != "all"}
        return replace(
            self,
            images=self.images[idx], cameras=self.cameras[idx], near=self.near[idx], far=self.far[idx],
            masks=pick(self.masks), depths=pick(self.depths), normals=pick(self.normals),
            labels=pick(self.labels), names=[self.names[i] for i in idx.tolist()], splits=splits,
        )

    def split(self, name: str) -> Scene:
        """The views of split ``name`` (e.g. ``"train"``)."""
        if name not in self.splits:
            raise InputError(f"scene has no split {name!r} (it has {sorted(self.splits)})", self.path,
                             "pick one of the listed splits")
        return self.subset(self.splits[name])

    def normalized(self, radius: float = 1.0) -> Scene:
        """The same scene in a frame where ``bounds`` is centred at 0 and fits a sphere of ``radius``.

        Cameras, near/far, depths, bounds and the mesh transform follow; ``to_input`` absorbs the
        inverse, so exports still land in the input frame.
        """
        centre = self.bounds.double().mean(0)
        half_diag = float((self.bounds[1] - self.bounds[0]).double().norm() / 2)
        s = radius / max(half_diag, 1e-12)
        S = torch.eye(4, dtype=torch.float64)
        S[:3, :3] *= s
        S[:3, 3] = -s * centre
        S_inv = torch.linalg.inv(S)
        bounds = (self.bounds.double() - centre) * s
        return replace(
            self,
            cameras=self.cameras.transformed(S),
            near=self.near * s, far=self.far * s,
            depths=None if self.depths is None else self.depths * s,
            bounds=bounds.to(self.bounds.dtype),
            to_input=self.to_input.double() @ S_inv,
            mesh_to_scene=S @ self.mesh_to_scene.double(),
        )

    def points_to_input(self, points: Tensor) -> Tensor:
        """Map scene-frame points ``# [P, 3]`` to the input frame."""
        T = self.to_input.to(points)
        return points @ T[:3, :3].T + T[:3, 3]

    def validate(self) -> None:
        """Check shapes and values; raise :class:`InputError` naming the scene on any problem."""
        n, h, w = len(self), self.height, self.width
        where = self.path
        if self.images.shape != (n, h, w, 3):
            raise InputError(f"images must be [N, H, W, 3], got {tuple(self.images.shape)}", where,
                             "give RGB(A) images of one size")
        if len(self.cameras) != n:
            raise InputError(f"{n} images but {len(self.cameras)} cameras", where,
                             "give exactly one pose per image")
        if (self.cameras.width, self.cameras.height) != (w, h):
            raise InputError(
                f"intrinsics are for {self.cameras.width}x{self.cameras.height} but images are {w}x{h}",
                where, "rescale the intrinsics to the image size")
        if not torch.isfinite(self.images).all():
            raise InputError("images contain NaN or infinite values", where,
                             "re-export the images (e.g. EXR without NaN/Inf)")
        for name in ("fx", "fy", "cx", "cy"):
            v = getattr(self.cameras, name)
            if not torch.isfinite(v).all() or (name in ("fx", "fy") and (v <= 0).any()):
                raise InputError(f"intrinsic {name} must be finite{' and positive' if name[0] == 'f' else ''}",
                                 where, "fix the focal length / principal point in the camera file")
        if not (torch.isfinite(self.near).all() and torch.isfinite(self.far).all()):
            raise InputError("near/far bounds are not finite", where, "fix the depth bounds in the camera file")
        if ((self.near <= 0) | (self.far <= self.near)).any():
            raise InputError("near/far bounds must satisfy 0 < near < far", where,
                             "fix the depth bounds (or the scale/aabb that sets them) in the camera file")
        for name, shape in (("masks", (n, h, w)), ("depths", (n, h, w)), ("normals", (n, h, w, 3)),
                            ("labels", (n, h, w))):
            t = getattr(self, name)
            if t is not None and tuple(t.shape) != shape:
                raise InputError(f"{name} must be {list(shape)}, got {list(t.shape)}", where,
                                 f"give {name} at the image size")
        for k, v in self.splits.items():
            if any(i < 0 or i >= n for i in v):
                raise InputError(f"split {k!r} names views outside 0..{n - 1}", where,
                                 "list only existing views in the split")

    def summary(self) -> dict:
        """A JSON-serialisable description (what ``omnirecon inspect`` prints)."""
        c = self.cameras
        return {
            "path": str(self.path) if self.path else None,
            "format": self.format,
            "rig": self.rig,
            "views": len(self),
            "resolution": [self.width, self.height],
            "splits": {k: len(v) for k, v in self.splits.items()},
            "fx": _range(c.fx), "fy": _range(c.fy), "cx": _range(c.cx), "cy": _range(c.cy),
            "near": _range(self.near), "far": _range(self.far),
            "bounds_min": [round(float(x), 4) for x in self.bounds[0]],
            "bounds_max": [round(float(x), 4) for x in self.bounds[1]],
            "camera_radius": _range((c.centers - self.bounds.mean(0).to(c.centers)).norm(dim=-1)),
            "scale_to_input": round(self.scale_to_input, 6),
            "has": [k for k in ("masks", "depths", "normals", "labels") if getattr(self, k) is not None]
            + (["mesh"] if self.mesh_path else []),
        }


def _range(t: Tensor) -> list[float] | float:
    lo, hi = float(t.min()), float(t.max())
    return round(lo, 4) if abs(hi - lo) < 1e-6 * max(1.0, abs(lo)) else [round(lo, 4), round(hi, 4)]
