"""Compare recovered camera poses with reference poses after a similarity alignment (Umeyama 1991)."""

from __future__ import annotations

import numpy as np


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Scale ``s``, rotation ``R # [3, 3]`` and translation ``t # [3]`` minimising
    ``sum |dst - (s R src + t)|^2`` over corresponding points ``src, dst # [N, 3]`` (N >= 3, not collinear)."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    cov = b.T @ a / len(src)  # [3, 3]
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    var = (a ** 2).sum() / len(src)
    s = float(np.trace(np.diag(D) @ S) / max(var, 1e-300))
    return s, R, mu_d - s * R @ mu_s


def align_poses(c2w_est: np.ndarray, c2w_ref: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity ``(s, R, t)`` taking estimated camera-to-world poses ``# [N, 4, 4]`` onto reference ones.

    The rotation is the Kabsch solution over both the camera centres (about their means, each set
    scaled to unit RMS) and the cameras' three axes, so that a rig whose centres barely spread (a
    forward-facing capture, a short arc) still fixes it; scale and translation then follow from the
    centres by least squares, as in Umeyama's method.
    """
    est, ref = np.asarray(c2w_est, np.float64), np.asarray(c2w_ref, np.float64)
    a, b = est[:, :3, 3], ref[:, :3, 3]
    mu_a, mu_b = a.mean(0), b.mean(0)
    a0, b0 = a - mu_a, b - mu_b
    H = (b0 / max(np.sqrt((b0 ** 2).sum(1).mean()), 1e-300)).T @ (a0 / max(np.sqrt((a0 ** 2).sum(1).mean()), 1e-300))
    H = H + np.einsum("nik,njk->ij", ref[:, :3, :3], est[:, :3, :3])  # sum_n R_ref R_est^T  [3, 3]
    U, _, Vt = np.linalg.svd(H)
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ S @ Vt
    s = float((b0 * (a0 @ R.T)).sum() / max((a0 ** 2).sum(), 1e-300))
    return s, R, mu_b - s * R @ mu_a


def pose_errors(c2w_est: np.ndarray, c2w_ref: np.ndarray, extent: float) -> dict:
    """Rotation (degrees) and camera-centre errors (% of ``extent``) of estimated camera-to-world poses
    ``# [N, 4, 4]`` against reference ones (same order, OpenCV frame), after the similarity alignment
    of :func:`align_poses`. Returns medians, means, maxima, per view, and the similarity ``[s, R, t]``."""
    est, ref = np.asarray(c2w_est, np.float64), np.asarray(c2w_ref, np.float64)
    s, R, t = align_poses(est, ref)
    centres = s * est[:, :3, 3] @ R.T + t  # [N, 3]
    c_err = np.linalg.norm(centres - ref[:, :3, 3], axis=1) / extent * 100
    rel = np.einsum("nji,jk,nkl->nil", ref[:, :3, :3], R, est[:, :3, :3])  # R_ref^T R R_est  [N, 3, 3]
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)
    r_err = np.degrees(np.arccos(cos))
    return {
        "rotation_deg_median": float(np.median(r_err)), "rotation_deg_mean": float(r_err.mean()),
        "rotation_deg_max": float(r_err.max()),
        "centre_pct_median": float(np.median(c_err)), "centre_pct_mean": float(c_err.mean()),
        "centre_pct_max": float(c_err.max()),
        "rotation_deg": r_err.tolist(), "centre_pct": c_err.tolist(),
        "similarity": {"scale": s, "rotation": R.tolist(), "translation": t.tolist()},
    }
