"""One camera model for the whole library.

Conventions (see ``docs/conventions.md``):

* **Camera frame: OpenCV.** x right, y down, z forward (the camera looks along +z).
* **Poses are camera-to-world** 4x4 matrices ``c2w``; the world-to-camera matrix is its inverse.
* **Pixels:** continuous image coordinates ``(u, v)`` with ``u`` along the width. Pixel ``(row i,
  column j)`` covers ``[j, j+1) x [i, i+1)`` and its centre is ``(j + 0.5, i + 0.5)``. Resizing an
  image by ``s`` therefore scales ``fx, fy, cx, cy`` by exactly ``s``.
* **Pinhole intrinsics** ``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``, no distortion (readers
  undistort or refuse).
* **Depth** means camera-frame z ("z-depth") unless a name says ``distance`` (Euclidean distance
  along a unit-length ray).

Every function works on a batch of ``N`` cameras; shapes are noted as ``# [N, ...]``.

Size: one camera type and every conversion to and from it (OpenCV, OpenGL, NeRF, LLFF, COLMAP, DTU):
splitting it would scatter the one convention readers and exports must agree on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from omnirecon.errors import InputError

# OpenGL/Blender camera frame (x right, y up, looking along -z) -> OpenCV: flip y and z.
OPENGL_TO_OPENCV = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))


class Projection(NamedTuple):
    """Result of :meth:`Cameras.project`."""

    uv: Tensor
    """Continuous pixel coordinates ``(u, v)``. ``# [N, P, 2]``"""
    depth: Tensor
    """Camera-frame z of each point. ``# [N, P]``"""
    in_front: Tensor
    """``depth > eps``: the point lies in front of the camera. ``# [N, P]`` bool"""
    in_image: Tensor
    """``0 <= u < W`` and ``0 <= v < H`` (and in front). ``# [N, P]`` bool"""


@dataclass
class Cameras:
    """A batch of ``N`` pinhole cameras sharing one image size.

    All tensors live on the same device; intrinsics are in pixels of a ``width x height`` image.
    """

    fx: Tensor
    """Focal length along u, pixels. ``# [N]``"""
    fy: Tensor
    """Focal length along v, pixels. ``# [N]``"""
    cx: Tensor
    """Principal point u, pixels (image centre = ``width / 2``). ``# [N]``"""
    cy: Tensor
    """Principal point v, pixels. ``# [N]``"""
    c2w: Tensor
    """Camera-to-world rigid transforms, OpenCV camera frame. ``# [N, 4, 4]``"""
    width: int
    """Image width in pixels."""
    height: int
    """Image height in pixels."""

    def __post_init__(self) -> None:
        n = self.c2w.shape[0]
        if self.c2w.shape != (n, 4, 4):
            raise ValueError(f"c2w must be [N, 4, 4], got {tuple(self.c2w.shape)}")
        for name in ("fx", "fy", "cx", "cy"):
            value = torch.as_tensor(getattr(self, name), dtype=self.c2w.dtype, device=self.c2w.device)
            value = value.reshape(-1).expand(n) if value.numel() == 1 else value.reshape(-1)
            if value.shape != (n,):
                raise ValueError(f"{name} must have {n} entries, got {value.shape[0]}")
            setattr(self, name, value.contiguous())
        self.width = int(self.width)
        self.height = int(self.height)

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_K(cls, K: Tensor, c2w: Tensor, width: int, height: int) -> Cameras:
        """Build from intrinsic matrices ``K # [N, 3, 3]`` (or one ``[3, 3]``) and ``c2w # [N, 4, 4]``."""
        K = torch.as_tensor(K, dtype=c2w.dtype).expand(c2w.shape[0], 3, 3)
        return cls(K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], c2w, width, height)

    def __len__(self) -> int:
        return self.c2w.shape[0]

    def __getitem__(self, index) -> Cameras:
        """Select cameras with an int, slice, index list/tensor or bool mask."""
        if isinstance(index, int):
            index = [index]
        index = torch.as_tensor(index, device=self.c2w.device) if isinstance(index, list) else index
        return Cameras(
            self.fx[index], self.fy[index], self.cx[index], self.cy[index], self.c2w[index],
            self.width, self.height,
        )

    def to(self, device=None, dtype=None) -> Cameras:
        f = lambda t: t.to(device=device, dtype=dtype)  # noqa: E731
        return Cameras(f(self.fx), f(self.fy), f(self.cx), f(self.cy), f(self.c2w), self.width, self.height)

    @staticmethod
    def cat(cams: list[Cameras]) -> Cameras:
        if len({(c.width, c.height) for c in cams}) != 1:
            raise ValueError("cannot concatenate cameras of different image sizes")
        return Cameras(
            *(torch.cat([getattr(c, k) for c in cams]) for k in ("fx", "fy", "cx", "cy", "c2w")),
            cams[0].width, cams[0].height,
        )

    def rescaled(self, scale: float) -> Cameras:
        """Cameras for the same views at ``scale`` x the resolution (e.g. 0.5 halves it)."""
        w, h = round(self.width * scale), round(self.height * scale)
        sx, sy = w / self.width, h / self.height
        return Cameras(self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, self.c2w, w, h)

    def transformed(self, T: Tensor) -> Cameras:
        """Cameras after moving the world by a similarity ``T # [4, 4]`` (rotation x scale, translation).

        A camera at ``c2w`` ends at ``T @ c2w`` with the scale removed from its rotation, so the
        result stays rigid. Images and intrinsics are unchanged.
        """
        T = T.to(self.c2w)
        scale = torch.linalg.det(T[:3, :3]).abs() ** (1.0 / 3.0)
        c2w = T @ self.c2w
        c2w[:, :3, :3] = c2w[:, :3, :3] / scale
        return Cameras(self.fx, self.fy, self.cx, self.cy, c2w, self.width, self.height)

    # ------------------------------------------------------------------ matrices
    @property
    def device(self) -> torch.device:
        return self.c2w.device

    @property
    def K(self) -> Tensor:
        """Intrinsic matrices. ``# [N, 3, 3]``"""
        K = torch.zeros(len(self), 3, 3, dtype=self.c2w.dtype, device=self.device)
        K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = self.fx, self.fy, self.cx, self.cy, 1
        return K

    @property
    def R(self) -> Tensor:
        """Camera-to-world rotations; columns are the camera x, y, z axes in world. ``# [N, 3, 3]``"""
        return self.c2w[:, :3, :3]

    @property
    def centers(self) -> Tensor:
        """Camera centres in world. ``# [N, 3]``"""
        return self.c2w[:, :3, 3]

    @property
    def forward(self) -> Tensor:
        """Optical axes (camera +z) in world, unit length. ``# [N, 3]``"""
        return self.c2w[:, :3, 2]

    @property
    def w2c(self) -> Tensor:
        """World-to-camera rigid transforms. ``# [N, 4, 4]``"""
        return rigid_inverse(self.c2w)

    # ------------------------------------------------------------------ rays
    def pixel_centers(self) -> Tensor:
        """Centres ``(u, v)`` of all pixels, row-major. ``# [H, W, 2]``"""
        v, u = torch.meshgrid(
            torch.arange(self.height, dtype=self.c2w.dtype, device=self.device) + 0.5,
            torch.arange(self.width, dtype=self.c2w.dtype, device=self.device) + 0.5,
            indexing="ij",
        )
        return torch.stack([u, v], dim=-1)

    def rays(self, uv: Tensor, normalize: bool = True) -> tuple[Tensor, Tensor]:
        """World rays through pixel coordinates.

        Args:
            uv: Continuous pixel coordinates, one set per camera. ``# [N, ..., 2]``
            normalize: Unit-length directions (``True``), or directions with camera-frame z = 1, so
                that ``origin + z * direction`` is the point at z-depth ``z``.

        Returns:
            ``origins # [N, ..., 3]`` and ``directions # [N, ..., 3]``.
        """
        n = len(self)
        shape = uv.shape[:-1]
        uv = uv.reshape(n, -1, 2).to(self.c2w)
        x = (uv[..., 0] - self.cx[:, None]) / self.fx[:, None]  # [N, P]
        y = (uv[..., 1] - self.cy[:, None]) / self.fy[:, None]  # [N, P]
        d_cam = torch.stack([x, y, torch.ones_like(x)], dim=-1)  # [N, P, 3]
        d = d_cam @ self.R.transpose(1, 2)  # [N, P, 3]
        if normalize:
            d = torch.nn.functional.normalize(d, dim=-1)
        o = self.centers[:, None, :].expand_as(d)
        return o.reshape(*shape, 3), d.reshape(*shape, 3)

    def image_rays(self, normalize: bool = True) -> tuple[Tensor, Tensor]:
        """Rays through every pixel centre of every camera. ``# [N, H, W, 3]`` each."""
        uv = self.pixel_centers().expand(len(self), self.height, self.width, 2)
        return self.rays(uv, normalize=normalize)

    # ------------------------------------------------------------------ projection
    def project(self, points: Tensor, eps: float = 1e-6) -> Projection:
        """Project world points into every camera.

        Args:
            points: ``# [P, 3]`` (the same points for all cameras) or ``# [N, P, 3]``.
        """
        if points.dim() == 2:
            points = points.expand(len(self), *points.shape)
        points = points.to(self.c2w)
        w2c = self.w2c
        p_cam = points @ w2c[:, :3, :3].transpose(1, 2) + w2c[:, None, :3, 3]  # [N, P, 3]
        z = p_cam[..., 2]
        in_front = z > eps
        zs = torch.where(in_front, z, torch.full_like(z, eps))
        u = self.fx[:, None] * p_cam[..., 0] / zs + self.cx[:, None]
        v = self.fy[:, None] * p_cam[..., 1] / zs + self.cy[:, None]
        uv = torch.stack([u, v], dim=-1)
        in_image = in_front & (u >= 0) & (u < self.width) & (v >= 0) & (v < self.height)
        return Projection(uv, z, in_front, in_image)

    def unproject(self, uv: Tensor, depth: Tensor) -> Tensor:
        """World points at z-depth ``depth # [N, ...]`` behind pixels ``uv # [N, ..., 2]``. ``# [N, ..., 3]``"""
        o, d = self.rays(uv, normalize=False)
        return o + d * depth[..., None]


# ---------------------------------------------------------------------- rigid helpers
def rigid_inverse(T: Tensor) -> Tensor:
    """Inverse of rigid transforms ``# [..., 4, 4]`` without a general matrix inverse."""
    R, t = T[..., :3, :3], T[..., :3, 3:]
    out = torch.zeros_like(T)
    out[..., :3, :3] = R.transpose(-1, -2)
    out[..., :3, 3:] = -R.transpose(-1, -2) @ t
    out[..., 3, 3] = 1
    return out


def opengl_to_opencv(c2w_gl: Tensor) -> Tensor:
    """Camera-to-world in the OpenGL camera frame (y up, looking along -z) -> OpenCV frame."""
    return c2w_gl @ OPENGL_TO_OPENCV.to(c2w_gl)


def check_poses(c2w: Tensor, source: object = None, tol: float = 1e-3) -> None:
    """Raise :class:`InputError` unless every pose is finite and rigid with ``det R = +1``.

    ``source`` names the file the poses came from (used in the message). Rotations that are
    orthonormal within ``tol`` pass; callers may re-orthonormalise afterwards.
    """
    if c2w.dim() != 3 or c2w.shape[1:] != (4, 4):
        raise InputError(f"camera poses must be 4x4 matrices, got shape {tuple(c2w.shape)}", source,
                         "store one 4x4 (or 3x4) camera-to-world matrix per view")
    finite = torch.isfinite(c2w).all(dim=(1, 2))
    if not finite.all():
        i = int((~finite).nonzero()[0])
        raise InputError(f"camera pose {i} contains NaN or infinite values", source,
                         "re-export the poses; every entry must be a finite number")
    R = c2w[:, :3, :3].double()
    err = (R.transpose(1, 2) @ R - torch.eye(3, dtype=R.dtype)).abs().amax(dim=(1, 2))
    det = torch.linalg.det(R)
    bad = (err > tol) | ((det - 1).abs() > tol)
    if bad.any():
        i = int(bad.nonzero()[0])
        kind = "a reflection (det R = -1)" if det[i] < 0 else "not a rotation (R^T R != I)"
        raise InputError(f"camera pose {i} is not rigid: its 3x3 part is {kind}", source,
                         "give camera-to-world matrices with an orthonormal, right-handed rotation")
    bottom = c2w[:, 3, :].double() - torch.tensor([0, 0, 0, 1.0], dtype=torch.float64)
    if (bottom.abs() > tol).any():
        i = int((bottom.abs() > tol).any(dim=1).nonzero()[0])
        raise InputError(f"camera pose {i} has a last row other than [0 0 0 1]", source,
                         "give camera-to-world matrices of the form [R t; 0 0 0 1]")


def orthonormalize(c2w: Tensor) -> Tensor:
    """Project each rotation to the nearest proper rotation (SVD), keeping translations."""
    U, _, Vh = torch.linalg.svd(c2w[:, :3, :3])
    R = U @ Vh
    fix = torch.linalg.det(R) < 0
    if fix.any():
        U = U.clone()
        U[fix, :, -1] *= -1
        R = U @ Vh
    out = c2w.clone()
    out[:, :3, :3] = R
    out[:, 3] = torch.tensor([0, 0, 0, 1], dtype=c2w.dtype, device=c2w.device)
    return out


def look_at(eye: Tensor, target: Tensor, up: Tensor) -> Tensor:
    """OpenCV camera-to-world matrices for cameras at ``eye # [N, 3]`` looking at ``target # [N, 3]``.

    ``up # [3]`` or ``[N, 3]`` is the world direction that should appear upwards in the image
    (the camera's -y axis is aligned with it as closely as possible).
    """
    eye, target = torch.as_tensor(eye), torch.as_tensor(target)
    eye = eye.reshape(-1, 3)
    target = torch.as_tensor(target, dtype=eye.dtype).expand_as(eye)
    up = torch.as_tensor(up, dtype=eye.dtype).expand_as(eye)
    z = torch.nn.functional.normalize(target - eye, dim=-1)
    x = torch.nn.functional.normalize(torch.cross(z, up, dim=-1), dim=-1)  # y = -up, x = y x z
    y = torch.cross(z, x, dim=-1)
    c2w = torch.eye(4, dtype=eye.dtype).repeat(eye.shape[0], 1, 1)
    c2w[:, :3, 0], c2w[:, :3, 1], c2w[:, :3, 2], c2w[:, :3, 3] = x, y, z, eye
    return c2w


# ---------------------------------------------------------------------- ray encodings
def plucker(origins: Tensor, directions: Tensor) -> Tensor:
    """Plücker coordinates ``(d, o x d)`` of rays with unit directions. ``# [..., 6]``

    The moment ``o x d`` is the same for every origin on the ray, so the encoding describes the
    line, not the point where it starts.
    """
    d = torch.nn.functional.normalize(directions, dim=-1)
    return torch.cat([d, torch.cross(origins, d, dim=-1)], dim=-1)


def canonical_transform(origins: Tensor, directions: Tensor, up: Tensor, eps: float = 1e-8) -> Tensor:
    """Per-ray canonical frame of GPNR, as a proper rigid transform.

    The returned ``T # [..., 4, 4]`` maps world points into a frame where the ray starts at the
    origin and points along +z; the roll is fixed by ``up``: the component of ``up`` orthogonal to
    the ray maps to +y. Rows of the rotation are ``(e_x, u_perp, d)`` with ``u_perp`` the
    normalised projection of ``up`` and ``e_x = u_perp x d``: orthonormal, ``det = +1`` (the
    reference code divides by the squared norm; this uses the norm).

    Args:
        origins: Ray origins. ``# [..., 3]``
        directions: Ray directions (need not be unit). ``# [..., 3]``
        up: Roll reference, normally the target camera's y axis (``c2w[:3, 1]``). ``# [..., 3]``
    """
    d = torch.nn.functional.normalize(directions, dim=-1)
    up = up.to(d).expand_as(d)
    u_perp = up - (up * d).sum(-1, keepdim=True) * d
    norm = u_perp.norm(dim=-1, keepdim=True)
    if (norm < 1e-6).any():  # ray parallel to `up`: fall back to any perpendicular axis
        alt = torch.where(d[..., :1].abs() < 0.9, torch.tensor([1.0, 0, 0]).to(d), torch.tensor([0, 1.0, 0]).to(d))
        alt = alt - (alt * d).sum(-1, keepdim=True) * d
        u_perp = torch.where(norm < 1e-6, alt, u_perp)
        norm = u_perp.norm(dim=-1, keepdim=True)
    u_perp = u_perp / norm.clamp_min(eps)
    e_x = torch.cross(u_perp, d, dim=-1)
    R = torch.stack([e_x, u_perp, d], dim=-2)  # [..., 3, 3], rows
    T = torch.zeros(*d.shape[:-1], 4, 4, dtype=d.dtype, device=d.device)
    T[..., :3, :3] = R
    T[..., :3, 3] = -(R @ origins.to(d)[..., None])[..., 0]
    T[..., 3, 3] = 1
    return T


def apply_transform(T: Tensor, points: Tensor) -> Tensor:
    """Apply ``T # [..., 4, 4]`` to points ``# [..., P, 3]`` (broadcasting over leading dims)."""
    return points @ T[..., :3, :3].transpose(-1, -2) + T[..., None, :3, 3]


# ---------------------------------------------------------------------- view selection
def view_distances(targets: Cameras, sources: Cameras, by: str = "distance", center: Tensor | None = None) -> Tensor:
    """Dissimilarity between each target and each source camera. ``# [T, S]``

    ``by="distance"``: Euclidean distance between camera centres (forward-facing captures).
    ``by="angle"``: angle in radians between the directions from ``center`` to the two cameras
    (object-centric 360° captures; ``center`` defaults to the point closest to all optical axes).
    """
    if by == "distance":
        return torch.cdist(targets.centers, sources.centers)
    if by == "angle":
        if center is None:
            center = closest_point_to_axes(Cameras.cat([targets, sources]))
        a = torch.nn.functional.normalize(targets.centers - center, dim=-1)
        b = torch.nn.functional.normalize(sources.centers - center, dim=-1)
        return torch.arccos((a @ b.T).clamp(-1, 1))
    raise ValueError(f"unknown view distance {by!r}; use 'distance' or 'angle'")


def nearest_views(
    targets: Cameras,
    sources: Cameras,
    k: int,
    by: str = "distance",
    exclude: Tensor | None = None,
    center: Tensor | None = None,
) -> Tensor:
    """Indices of the ``k`` nearest sources for each target, nearest first. ``# [T, k]``

    ``exclude # [T]`` gives, per target, one source index to skip (its own view when the target is
    also in the source set), or -1.
    """
    dist = view_distances(targets, sources, by=by, center=center).clone()
    if exclude is not None:
        rows = torch.arange(len(targets))
        ok = exclude >= 0
        dist[rows[ok], exclude[ok]] = math.inf
    k = min(k, len(sources) - (1 if exclude is not None and (exclude >= 0).any() else 0))
    return dist.topk(k, dim=1, largest=False).indices


def sample_views(
    targets: Cameras,
    sources: Cameras,
    k: int,
    n: int,
    generator: torch.Generator | None = None,
    by: str = "distance",
    exclude: Tensor | None = None,
    center: Tensor | None = None,
) -> Tensor:
    """Training-time selection: ``k`` sources drawn without replacement from the ``n`` nearest. ``# [T, k]``"""
    pool = nearest_views(targets, sources, max(n, k), by=by, exclude=exclude, center=center)  # [T, n]
    order = torch.rand(pool.shape, generator=generator).argsort(dim=1)[:, :k]
    return pool.gather(1, order)


def closest_point_to_axes(cams: Cameras) -> Tensor:
    """Least-squares point nearest to all optical axes (the look-at centre of a 360° rig). ``# [3]``"""
    d = cams.forward.double()
    P = torch.eye(3, dtype=d.dtype) - d[:, :, None] * d[:, None, :]  # [N, 3, 3]
    A = P.sum(0)
    b = (P @ cams.centers.double()[:, :, None]).sum(0)
    return torch.linalg.lstsq(A, b).solution[:, 0].to(cams.c2w.dtype)
