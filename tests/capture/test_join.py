"""Joining two models through cross-model pairs (bench/join_models.py, the pose_join experiment): exact synthetic geometry."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from bench import join_models as join


def ring(n: int, radius: float = 4.0, start: float = 0.0) -> list[tuple[np.ndarray, np.ndarray]]:
    """World-to-camera poses (R [3, 3], t [3]) of ``n`` cameras on a circle looking at the origin."""
    out = []
    for k in range(n):
        phi = start + 2 * np.pi * k / n
        c = radius * np.array([np.cos(phi), np.sin(phi), 0.3])
        z = -c / np.linalg.norm(c)
        x = np.cross([0.0, 0.0, 1.0], z)
        x /= np.linalg.norm(x)
        r = np.stack([x, np.cross(z, x), z])  # rows: camera axes in the world
        out.append((r, -r @ c))
    return out


def scene(s: float, q: np.ndarray, u: np.ndarray, nb: int = 4):
    """Views a0..a5 posed in frame A and views b0.. (``nb``) posed in frame B, where ``X_B = s q X_A + u``; the true
    world is frame A. Returns both models' poses and a function giving a pair's true relative pose."""
    cams_a = ring(6)
    cams_b_world = ring(nb, start=0.4)  # in frame A
    a = {f"a{k}": p for k, p in enumerate(cams_a)}
    b = {}
    for k, (r, t) in enumerate(cams_b_world):  # x = r X_A + t = r q^T (X_B - u) / s + t, times s
        b[f"b{k}"] = (r @ q.T, s * t - r @ q.T @ u)

    def relative(na: str, nb: str):
        (ra, ta), (rb, tb) = a[na], cams_b_world[int(nb[1:])]
        r_ab = rb @ ra.T
        return r_ab, tb - r_ab @ ta  # x_b = r_ab x_a + t_ab, in frame A's units

    return a, b, relative


def candidates(a, b, relative, pairs, flip: set[str] = frozenset()):
    out = []
    for na, nb in pairs:
        r_ab, t_ab = relative(na, nb)
        if nb in flip:  # a front-to-back false match on a symmetric object: the back seen as the front,
            turn = Rotation.from_euler("z", 180, degrees=True).as_matrix()  # a half turn about the world's up axis
            r_ab = r_ab @ a[na][0] @ turn @ a[na][0].T
        out.append(join.pair_candidate(na, nb, *a[na], *b[nb], r_ab, t_ab, 100))
    return out


PAIRS = [(f"a{i}", f"b{k}") for k in range(4) for i in (k, k + 1)]
S, Q, U = 2.5, Rotation.from_euler("xyz", [20, -40, 70], degrees=True).as_matrix(), np.array([1.0, -2.0, 0.5])


def test_agreeing_pairs_give_the_similarity():
    a, b, relative = scene(S, Q, U)
    got = join.decide(candidates(a, b, relative, PAIRS), len(PAIRS))
    assert got.accepted and got.consensus["views"] == 4
    assert join.angle_deg(got.rotation @ Q.T) < 1e-4  # the angle from the trace: float64 resolves ~1e-6 degrees
    assert abs(got.scale - S) < 1e-6 and np.allclose(got.translation, U, atol=1e-6)


def test_one_flipped_view_does_not_stop_three_agreeing_ones():
    a, b, relative = scene(S, Q, U)
    got = join.decide(candidates(a, b, relative, PAIRS, flip={"b3"}), len(PAIRS))
    assert got.accepted and got.consensus["views"] == 3
    assert [c["b"] for c in got.candidates if c["deg_off"] > 90] == ["b3", "b3"]
    assert abs(got.scale - S) < 1e-6


def test_a_join_whose_pairs_disagree_by_180_degrees_is_refused():
    a, b, relative = scene(S, Q, U)
    got = join.decide(candidates(a, b, relative, PAIRS, flip={"b2", "b3"}), len(PAIRS))
    assert not got.accepted and got.scale is None
    assert got.consensus["views"] == 2 and got.consensus["rival_views"] == 2
    offs = sorted(c["deg_off"] for c in got.candidates)
    assert offs[:4] == [0.0] * 4 and min(offs[4:]) > 170  # the two groups: 180 degrees apart


def test_too_few_views_are_refused_even_when_they_agree():
    a, b, relative = scene(S, Q, U)
    got = join.decide(candidates(a, b, relative, PAIRS[:4]), 4)
    assert not got.accepted and got.consensus["views"] == 2 and "need 3" in got.reason


def test_three_views_against_three_on_the_rotation_180_degrees_off_is_refused():
    a, b, relative = scene(S, Q, U, nb=6)
    pairs = [(f"a{k}", f"b{k}") for k in range(6)] + [(f"a{(k + 1) % 6}", f"b{k}") for k in range(6)]
    got = join.decide(candidates(a, b, relative, pairs, flip={"b3", "b4", "b5"}), len(pairs))
    assert not got.accepted and got.consensus["views"] == 3 and got.consensus["rival_views"] == 3
    assert "3 on another rotation" in got.reason
