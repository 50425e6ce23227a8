"""Camera paths (``omnirecon render``, the mesh-path videos of ``demo`` and ``reconstruct``): orbit,
LLFF-style spiral and keyframe interpolation. :func:`camera_path` makes one of a named kind from cameras.

Every path is built from a scene's cameras and returns OpenCV camera-to-world matrices
``# [F, 4, 4]`` (rigid, ``det R = +1``), in float64; :func:`path_cameras` adds intrinsics.

* :func:`orbit` circles the scene centre at the mean distance and mean elevation of the cameras
  (elevation measured from the plane orthogonal to the cameras' mean up direction); with ``arc_degrees=None``
  it sweeps only the azimuths the photos cover (:func:`captured_arc`), there and back, when they leave a gap
  wider than :data:`ORBIT_GAP_DEGREES` (a capture of a wall-mounted or half-seen object), so the video never
  circles to where no photo looks.
* :func:`spiral` is the NeRF/LLFF render path: around the mean pose, radii = 90th percentile of
  the camera offsets in the mean camera's frame, looking at a focus point at the harmonic blend
  of near and far depths (``1 / (0.25 / (0.9 near) + 0.75 / (5 far))``), two turns.
* :func:`interpolate` moves through keyframe cameras in order: rotations slerped (quaternions),
  centres and intrinsics linearly interpolated; frame ``i`` sits at keyframe time
  ``i (V - 1) / (F - 1)``, so the first and last frames are the first and last keyframes and
  every keyframe is hit exactly when ``F - 1`` is a multiple of ``V - 1``.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from omnirecon.cameras import Cameras, closest_point_to_axes, look_at

PathKind = Literal["orbit", "spiral", "interp"]
"""The kinds of :func:`camera_path`."""

ORBIT_GAP_DEGREES = 60.0
"""An orbit with ``arc_degrees=None`` circles fully only when no gap between the cameras' azimuths is wider
than this; else it sweeps the arc they cover. instant-ngp's fox (67 photos of a head mounted on a wall, posed by
`omnirecon process`) covers 93 degrees: `reconstruct`'s full orbit put 32 of its 48 frames more than 20 degrees from
the nearest photo (median 44, at most 127: behind the wall, rendered as shards), the covered arc none (median 7, at
most 11)."""

MAX_DEFAULT_KEYFRAMES = 8
"""``interp`` without ``keyframes`` uses at most this many views, evenly spaced in index order."""


WALK_RATIO = 1.5
"""A capture is a walk when its camera centres spread this many times more along their main axis than across it
(and the cameras look along that axis: :data:`WALK_LOOK`)."""
WALK_LOOK = math.cos(math.radians(45.0))
"""... and the median camera looks within 45 degrees of that axis, either way along it (a street walked out and
back): an orbit's cameras look across the chord of their arc, a forward-facing grid's across its plane."""


def is_walk(cameras: Cameras) -> bool:
    """Whether the cameras walk along their view direction (a street walked forward with a phone, possibly out and
    back): their centres spread :data:`WALK_RATIO` times more along their main axis than across it, and they look
    along that axis (:data:`WALK_LOOK`)."""
    c = cameras.centers.double()
    if len(c) <= 2:
        return False
    off = c - c.mean(0)
    axis = torch.linalg.svd(off, full_matrices=False).Vh[0]  # [3] the centres' main axis
    along = (off @ axis).abs().max()
    across = (off - (off @ axis)[:, None] * axis).norm(dim=-1).max()
    looks = (cameras.forward.double() @ axis).abs().median()
    return bool(along > WALK_RATIO * across and looks > WALK_LOOK)


def default_keyframes(n: int) -> list[int]:
    """All ``n`` views when there are few, else ``MAX_DEFAULT_KEYFRAMES`` evenly spaced ones."""
    if n <= MAX_DEFAULT_KEYFRAMES:
        return list(range(n))
    return np.unique(np.linspace(0, n - 1, MAX_DEFAULT_KEYFRAMES).round().astype(int)).tolist()


def camera_path(cameras: Cameras, kind: PathKind, frames: int, center: Tensor | None = None,
                near: float | None = None, far: float | None = None, keyframes: list[int] | None = None,
                arc: float | None = 360.0, rots: float = 2.0, beyond: float = 0.0) -> Cameras:
    """``frames`` cameras along a path of ``kind`` built from ``cameras`` (their resolution and the
    intrinsics of camera 0; interp: interpolated intrinsics), float64.

    Args:
        cameras: The scene's cameras.
        kind: ``"orbit"`` (:func:`orbit` around ``center``, default the point closest to all optical
            axes, over ``arc`` degrees; ``None``: the arc the cameras cover, reaching ``beyond`` degrees past each
            end), ``"spiral"`` (:func:`spiral` with
            ``rots`` turns; needs the scene's ``near`` and ``far`` z-depths) or ``"interp"`` (:func:`interpolate` through the
            views ``keyframes``, default :func:`default_keyframes`).
    Raises:
        ValueError: a spiral without ``near``/``far``, fewer than 2 keyframes or one out of range, or an
            unknown kind.
    """
    if kind == "orbit":
        return path_cameras(orbit(cameras, frames, center, arc, beyond), cameras)
    if kind == "spiral":
        if near is None or far is None:
            raise ValueError("a spiral path needs the scene's near and far depths")
        return path_cameras(spiral(cameras, near, far, frames, rots), cameras)
    if kind != "interp":
        raise ValueError(f"unknown path kind {kind!r}; use orbit, spiral or interp")
    keys = list(keyframes) if keyframes else default_keyframes(len(cameras))
    if len(keys) < 2 or any(not 0 <= k < len(cameras) for k in keys):
        raise ValueError(f"keyframes must name at least 2 views in 0..{len(cameras) - 1}, got {keys}")
    return interpolate(cameras[keys], frames)


UP_SPREAD = 0.03
"""Second eigenvalue of the cameras' right axes' scatter above which those axes span a plane (a yaw spread of more
than about 10 degrees), whose normal is then the up direction (:func:`mean_up`)."""


def mean_up(cams: Cameras) -> Tensor:
    """Unit world direction that the cameras show as up. Cameras are held level: their right axes (``x``) are
    horizontal whatever their pitch, so when those spread in yaw, up is the normal of the plane they span (signed like
    the mean of the cameras' ``-y`` axes); otherwise (parallel cameras) up is that mean. The mean alone tilts toward
    the object on a partial arc of cameras looking down at it. ``# [3]``"""
    up = -cams.R[:, :, 1].double().mean(0)
    up = up / up.norm().clamp_min(1e-12)
    x = cams.R[:, :, 0].double()  # [N, 3]
    evals, evecs = torch.linalg.eigh(x.T @ x / len(x))  # ascending
    if float(evals[1]) > UP_SPREAD:
        normal = evecs[:, 0]
        return normal if float(normal @ up) >= 0 else -normal
    return up


def orbit(cams: Cameras, frames: int, center: Tensor | None = None, arc_degrees: float | None = 360.0,
          beyond: float = 0.0) -> Tensor:
    """``frames`` cameras circling ``center`` (default: the point closest to all optical axes).

    The circle lies at the cameras' mean distance and mean elevation and starts at the azimuth of
    camera 0. A full turn (360 degrees) leaves out the end point, so the video loops; a partial
    arc includes both ends. ``arc_degrees=None``: the arc the cameras cover (:func:`captured_arc`): a full
    turn when they go around, else from one end of their azimuths to the other and back (eased at the ends,
    so the video loops), reaching ``beyond`` degrees past each end (where a user's orbit goes: the views just
    outside the photos). ``# [F, 4, 4]``
    """
    center = (closest_point_to_axes(cams) if center is None else center).double()
    up, e1, e2 = azimuth_frame(cams, center)
    off = cams.centers.double() - center  # [N, 3]
    radius = off.norm(dim=-1).mean()
    unit = off / off.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    elevation = torch.asin((unit @ up).clamp(-1, 1)).mean()
    if arc_degrees is None:
        start, span = captured_arc(off, up, e1, e2)
        start, span = start - math.radians(beyond), span + 2 * math.radians(beyond)
        if span < 2 * math.pi:  # there and back over the covered azimuths
            t = torch.arange(frames, dtype=torch.float64) / frames
            phi = start + span * (1 - torch.cos(2 * math.pi * t)) / 2
        else:
            phi = torch.linspace(0, 2 * math.pi, frames + 1, dtype=torch.float64)[:frames]
    else:
        full = abs(arc_degrees - 360.0) < 1e-9
        phi = torch.linspace(0, math.radians(arc_degrees), frames + 1 if full else frames, dtype=torch.float64)
        phi = phi[:frames]
    horiz = torch.cos(phi)[:, None] * e1 + torch.sin(phi)[:, None] * e2  # [F, 3]
    eye = center + radius * (torch.cos(elevation) * horiz + torch.sin(elevation) * up)
    return look_at(eye, center.expand_as(eye), up)


def captured_arc(off: Tensor, up: Tensor, e1: Tensor, e2: Tensor,
                 gap_degrees: float = ORBIT_GAP_DEGREES) -> tuple[float, float]:
    """``(start, span)`` in radians, azimuths measured from ``e1`` toward ``e2`` about ``up``: the arc the camera
    offsets from the centre ``off # [N, 3]`` cover, i.e. the circle less its widest gap between neighbouring
    azimuths; ``(0, 2 pi)`` when no gap is wider than ``gap_degrees`` (the cameras go around)."""
    az = torch.atan2(off @ e2, off @ e1).remainder(2 * math.pi).sort().values  # [N]
    gaps = torch.diff(torch.cat([az, az[:1] + 2 * math.pi]))  # [N]: gap after each azimuth
    k = int(gaps.argmax())
    if len(az) < 2 or float(gaps[k]) <= math.radians(gap_degrees):
        return 0.0, 2 * math.pi
    return float(az[(k + 1) % len(az)]), 2 * math.pi - float(gaps[k])


def azimuth_frame(cams: Cameras, center: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``(up, e1, e2)``: the cameras' mean up and the horizontal basis an orbit around ``center`` measures azimuth in
    (``e1`` toward camera 0, ``e2 = up x e1``), float64 ``# [3]`` each."""
    up = mean_up(cams)
    off = cams.centers.double() - center.double()
    e1 = off[0] - (off[0] @ up) * up
    if e1.norm() < 1e-9:  # camera 0 looks straight down the up axis: any horizontal start
        e1 = torch.linalg.svd(up[None]).Vh[1]
    e1 = e1 / e1.norm()
    return up, e1, torch.linalg.cross(up, e1)


def azimuths(cams: Cameras, center: Tensor) -> Tensor:
    """Azimuth of each camera around ``center`` about the cameras' mean up (:func:`azimuth_frame`), radians in
    ``[0, 2 pi)``, camera 0 at 0. ``# [N]`` float64"""
    up, e1, e2 = azimuth_frame(cams, center)
    off = cams.centers.double() - center.double()
    a = torch.atan2(off @ e2, off @ e1).remainder(2 * math.pi)
    return torch.where(a >= 2 * math.pi, a - 2 * math.pi, a)  # remainder rounds a tiny negative angle up to 2 pi


def nearest_photo_degrees(path: Tensor, cams: Cameras, center: Tensor) -> Tensor:
    """Per path pose ``path # [F, 4, 4]``: the angle at ``center`` between its camera and the nearest of
    ``cams`` (degrees; how far a frame extrapolates beyond the photos). ``# [F]``"""
    a = torch.nn.functional.normalize(path[:, :3, 3].double() - center.double(), dim=-1)  # [F, 3]
    b = torch.nn.functional.normalize(cams.centers.double() - center.double(), dim=-1)  # [N, 3]
    return torch.rad2deg(torch.acos((a @ b.T).clamp(-1, 1))).min(-1).values


def mean_pose(cams: Cameras) -> Tensor:
    """The average camera (NeRF's ``poses_avg``): mean centre, mean forward, mean up. ``# [4, 4]``"""
    c = cams.centers.double().mean(0)
    fwd = cams.forward.double().mean(0)
    return look_at(c[None], (c + fwd / fwd.norm())[None], mean_up(cams))[0]


def spiral(cams: Cameras, near: float, far: float, frames: int, rots: float = 2.0, zrate: float = 0.5,
           percentile: float = 90.0) -> Tensor:
    """LLFF-style spiral around the mean pose of a forward-facing capture. ``# [F, 4, 4]``

    Args:
        cams: The scene's cameras.
        near: Closest scene depth (scene units); the focus depth blends it with ``far``.
        far: Farthest scene depth.
        frames: Number of poses.
        rots: Turns of the spiral.
        zrate: Forward/backward oscillations per turn.
        percentile: Percentile of the absolute camera offsets (in the mean camera's frame) used as radii.
    """
    avg = mean_pose(cams)
    R, c = avg[:3, :3], avg[:3, 3]
    local = (cams.centers.double() - c) @ R  # [N, 3] offsets in the mean camera frame
    radii = torch.from_numpy(np.percentile(local.abs().numpy(), percentile, axis=0))  # [3]
    focus = 1.0 / (0.25 / (0.9 * near) + 0.75 / (5.0 * far))
    theta = torch.linspace(0, 2 * math.pi * rots, frames + 1, dtype=torch.float64)[:frames]
    # OpenCV frame: x right, y down, z forward (NeRF's GL path [cos, -sin, -sin(z t)] with y, z flipped).
    p = torch.stack([torch.cos(theta), torch.sin(theta), torch.sin(theta * zrate)], -1) * radii  # [F, 3]
    eye = c + p @ R.T
    target = (c + focus * R[:, 2]).expand_as(eye)
    return look_at(eye, target, -R[:, 1])


# ---------------------------------------------------------------------- keyframe interpolation
def matrix_to_quaternion(R: Tensor) -> Tensor:
    """Unit quaternions ``(w, x, y, z)`` of rotations ``R # [..., 3, 3]`` (Shepperd's method). ``# [..., 4]``"""
    m = R.double()
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    diag = torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    s = 2 * diag.clamp_min(1e-12).sqrt()  # [..., 4]: 4 * the largest component for each case
    a, b, c = m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]
    d, e, f = m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1]
    cand = torch.stack([
        torch.stack([s[..., 0] / 4, a / s[..., 0], b / s[..., 0], c / s[..., 0]], -1),
        torch.stack([a / s[..., 1], s[..., 1] / 4, d / s[..., 1], e / s[..., 1]], -1),
        torch.stack([b / s[..., 2], d / s[..., 2], s[..., 2] / 4, f / s[..., 2]], -1),
        torch.stack([c / s[..., 3], e / s[..., 3], f / s[..., 3], s[..., 3] / 4], -1),
    ], -2)  # [..., 4 cases, 4]
    best = diag.argmax(-1)[..., None, None].expand(*diag.shape[:-1], 1, 4)
    q = cand.gather(-2, best)[..., 0, :]
    return q / q.norm(dim=-1, keepdim=True)


def quaternion_to_matrix(q: Tensor) -> Tensor:
    """Rotation matrices of quaternions ``(w, x, y, z) # [..., 4]``. ``# [..., 3, 3]``"""
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], -1).reshape(*q.shape[:-1], 3, 3)


def slerp(q0: Tensor, q1: Tensor, t: Tensor) -> Tensor:
    """Shortest-arc spherical interpolation of unit quaternions ``# [..., 4]`` at ``t # [...]``."""
    dot = (q0 * q1).sum(-1, keepdim=True)
    q1 = torch.where(dot < 0, -q1, q1)
    dot = dot.abs().clamp(max=1.0)
    t = t[..., None]
    theta = torch.acos(dot)
    sin = torch.sin(theta)
    near = sin < 1e-6  # (almost) the same rotation: linear blend, renormalised
    w0 = torch.where(near, 1 - t, torch.sin((1 - t) * theta) / sin.clamp_min(1e-12))
    w1 = torch.where(near, t, torch.sin(t * theta) / sin.clamp_min(1e-12))
    q = w0 * q0 + w1 * q1
    return q / q.norm(dim=-1, keepdim=True)


def keyframe_times(keys: int, frames: int) -> Tensor:
    """Keyframe time of each frame: ``frames`` evenly spaced values from 0 to ``keys - 1``. ``# [F]``"""
    if frames == 1:
        return torch.zeros(1, dtype=torch.float64)
    return torch.linspace(0, keys - 1, frames, dtype=torch.float64)


def interpolate(cams: Cameras, frames: int) -> Cameras:
    """``frames`` cameras moving through ``cams`` in order (slerp rotations, lerp centres and intrinsics)."""
    if len(cams) < 2:
        raise ValueError("interpolation needs at least 2 keyframe cameras")
    t = keyframe_times(len(cams), frames)
    seg = t.floor().long().clamp(max=len(cams) - 2)  # [F]
    u = t - seg  # [F] in [0, 1]
    q = matrix_to_quaternion(cams.R.double())  # [V, 4]
    R = quaternion_to_matrix(slerp(q[seg], q[seg + 1], u))  # [F, 3, 3]
    def lerp(v: Tensor) -> Tensor:  # [V, ...] -> [F, ...]
        w = u.reshape(-1, *[1] * (v.dim() - 1))
        return v[seg] * (1 - w) + v[seg + 1] * w

    c2w = torch.eye(4, dtype=torch.float64).repeat(len(t), 1, 1)
    c2w[:, :3, :3] = R
    c2w[:, :3, 3] = lerp(cams.centers.double())
    return Cameras(*(lerp(getattr(cams, k).double()) for k in ("fx", "fy", "cx", "cy")), c2w,
                   cams.width, cams.height)


def path_cameras(c2w: Tensor, like: Cameras) -> Cameras:
    """Cameras at poses ``c2w # [F, 4, 4]`` with the intrinsics of camera 0 of ``like``."""
    n = c2w.shape[0]
    pick = lambda v: v[:1].double().expand(n)  # noqa: E731
    return Cameras(pick(like.fx), pick(like.fy), pick(like.cx), pick(like.cy), c2w.double(), like.width, like.height)
