"""Pose recovery that does not give up: retries when images are left out, the reason each photo was
dropped, the agreement guard that keeps a retry from changing poses, and grown masks.

The capture is the same 12-view procedural scene as ``test_process.py`` (its RGB files only).
"""


import numpy as np
import pytest

pycolmap = pytest.importorskip("pycolmap", reason="pycolmap is the optional `capture` extra: pip install pycolmap")

from conftest import procedural_photos  # noqa: E402

from omnirecon.capture.colmap_sfm import SfmOptions  # noqa: E402
from omnirecon.capture.consistency import AGREE_DEG, agreement, replaces  # noqa: E402
from omnirecon.capture.dropped import MatchGraph, drop_reasons  # noqa: E402
from omnirecon.capture.images import stage_images, stage_masks  # noqa: E402
from omnirecon.capture.process import process, summary_lines  # noqa: E402
from omnirecon.errors import InputError  # noqa: E402


@pytest.fixture(scope="module")
def photos(tmp_path_factory):
    return procedural_photos(tmp_path_factory.mktemp("capture"), 256)


def test_drop_reasons_each_kind():
    g = MatchGraph(features={"a": 900, "b": 800, "c": 700, "blank": 0, "alone": 300, "weak": 500, "side": 600,
                             "s2": 600, "s3": 600, "pair1": 400, "pair2": 400, "leaf": 350},
                   pairs={("a", "b"): 200, ("a", "c"): 150, ("b", "c"): 120, ("a", "weak"): 9, ("side", "s2"): 80,
                          ("s2", "s3"): 70, ("pair1", "pair2"): 40, ("a", "leaf"): 25})
    names = sorted(g.features)
    r = drop_reasons(names, ["a", "b", "c"], [["side", "s2", "s3"]], g, min_matches=15)
    assert set(r) == set(names) - {"a", "b", "c"}
    assert r["blank"].startswith("no features")
    assert r["alone"] == "matched no other photo (300 features)"
    assert r["weak"].startswith("matched no other photo (500 features; best pair 9 verified matches, 15 needed")
    assert r["side"].startswith("posed in a separate model of 3 photos")
    assert r["pair1"].startswith("in a group of 2 photos (pair1, pair2) that shares no pair of 15+")
    assert r["side"].startswith("posed in a separate model of 3 photos that shares no pair of 15+")
    assert r["leaf"].startswith("matched 1 posed photos (at most 25 verified matches)")


def test_match_groups_bound_what_can_be_posed():
    """Groups of photos linked by pairs of 15+ verified matches: a photo outside the kept model's group
    can never be posed from these features, and its reason says so; one inside it whose neighbours got
    no pose is told apart."""
    g = MatchGraph(features={n: 500 for n in ("a", "b", "c", "x", "y", "p", "q", "r", "lone")},
                   pairs={("a", "b"): 90, ("b", "c"): 60, ("a", "y"): 20, ("x", "y"): 30, ("p", "q"): 50,
                          ("q", "r"): 40, ("c", "p"): 14, ("a", "lone"): 3})
    assert g.groups(15) == [["a", "b", "c", "x", "y"], ["p", "q", "r"], ["lone"]]
    assert g.groups(10)[0] == ["a", "b", "c", "p", "q", "r", "x", "y"]
    assert g.reachable(["a", "b"], 15) == ["a", "b", "c", "x", "y"] and g.reachable(["q"], 15) == ["p", "q", "r"]
    r = drop_reasons(sorted(g.features), ["a", "b", "c"], [], g, min_matches=15)
    assert r["x"] == "matched 1 photos, none of which got a pose"
    assert r["y"].startswith("matched 1 posed photos (at most 20 verified matches)")
    assert all(r[n].startswith("in a group of 3 photos (p, q, r) that shares no pair of 15+ verified matches")
               for n in "pqr")
    assert r["lone"].startswith("matched no other photo (500 features; best pair 3 verified matches")


def test_retry_replaces_rule():
    """A retry replaces the current model with more images only when they agree; the affine-feature
    model also on a tie when they disagree (the first model is then the suspect one); never with fewer."""
    good, bad = (0.3, 1.2), (9.4, 30.0)

    def rep(current, candidate, agree, affine, total=20):
        return replaces(current, candidate, agree, affine, total)

    assert rep(None, 5, None, False) and not rep(None, 0, None, True)
    assert rep(10, 12, good, False) and not rep(10, 12, bad, False) and not rep(10, 12, None, True)
    assert not rep(12, 12, good, False) and not rep(12, 12, bad, False)
    assert rep(12, 12, bad, True) and not rep(12, 12, good, True)
    assert not rep(12, 11, bad, True) and not rep(12, 11, good, False)
    assert rep(12, 14, (AGREE_DEG[0], AGREE_DEG[1]), True) and not rep(12, 14, (AGREE_DEG[0] + 0.1, 1.0), True)
    assert rep(4, 11, bad, True) and rep(9, 10, bad, False) and not rep(10, 11, bad, False)  # under half: unprotected
    assert not rep(4, 4, bad, False) and not rep(4, 3, good, True)


def test_retry_and_dropped_record(photos, tmp_path, views_with_noise):
    """6 views + 2 noise images: the first mapping leaves 2 out, so the retries run (recorded, and
    never with fewer images); the noise images are dropped with their reason in process.json and in
    the summary line, and the views keep their poses."""
    d = views_with_noise(photos, 2)
    s = process(d, tmp_path / "scene", SfmOptions(min_registered=0.5, learned="auto"), quiet=True)
    assert s["images_registered"] >= 5 and {"noise_0.png", "noise_1.png"} <= set(s["unregistered"]), s
    steps = [a["attempt"] for a in s["attempts"]]
    assert steps[0] == "default settings" and "affine SIFT" in steps and len(steps) >= 3, steps
    assert all(a["registered"] <= 6 for a in s["attempts"]) and sum(bool(a.get("kept")) for a in s["attempts"]) == 1
    kept = next(a for a in s["attempts"] if a.get("kept"))
    assert kept["registered"] == s["images_registered"] == max(a["registered"] for a in s["attempts"] if a is kept
                                                               or a["attempt"] == "default settings")
    assert [x["name"] for x in s["dropped"]] == s["unregistered"] and all(x["reason"] for x in s["dropped"])
    noise = {x["name"]: x["reason"] for x in s["dropped"] if x["name"].startswith("noise")}
    assert all(r.startswith("matched no other photo") for r in noise.values()), s["dropped"]
    line = next(x for x in summary_lines(s) if x.startswith("dropped"))
    assert "noise_0.png (matched no other photo" in line and line.startswith(f"dropped {len(s['unregistered'])} photos")
    assert (tmp_path / "scene" / "process.json").read_text().count("matched no other photo") >= 2
    from omnirecon.capture.learned import available

    if available():  # learned matches for those left out (4 posed partners, matched among themselves, and 2
        # unposed ones each): not all 28 pairs
        assert "learned matches (DISK + LightGlue) for the images SIFT left out" in steps
        lp = s["learned"]
        assert lp["status"] == "used" and 2 <= lp["unplaced"] <= 3 and lp["pairs"] <= 12 * lp["unplaced"]
        assert lp["pairs"] < 28
    else:
        assert s["learned"]["status"] == "not installed"


def test_no_retry_when_all_register(photos, tmp_path):
    """A capture whose images all register is mapped once, exactly as before (no silent change)."""
    s = process(photos, tmp_path / "scene", quiet=True)
    assert s["images_registered"] == 12 and len(s["attempts"]) == 1 and s["attempts"][0]["kept"]
    assert s["dropped"] == [] and not any(x.startswith(("dropped", "retried")) for x in summary_lines(s))
    off = process(photos, tmp_path / "scene2", SfmOptions(retry_below=0.0), quiet=True)
    assert off["images_registered"] == 12


def test_agreement_guard(photos, tmp_path):
    """Same poses up to a similarity agree to ~0 degrees; one image turned by 10 degrees shows as the
    largest difference (a little of it goes into the alignment), above the guard's limit."""
    process(photos, tmp_path / "scene", quiet=True)
    a = pycolmap.Reconstruction(tmp_path / "scene" / "sparse" / "0")
    b = pycolmap.Reconstruction(tmp_path / "scene" / "sparse" / "0")
    b.transform(pycolmap.Sim3d(2.0, pycolmap.Rotation3d(np.array([0.1, 0.2, 0.3, 0.9]) / np.linalg.norm([0.1, 0.2, 0.3, 0.9])),
                               np.array([1.0, -2.0, 0.5])))
    med, worst = agreement(a, b)
    assert med < 0.01 and worst < 0.01
    i = sorted(b.reg_image_ids())[0]
    im = b.images[i]
    turn = pycolmap.Rotation3d(np.array([0.0, np.sin(np.radians(5)), 0.0, np.cos(np.radians(5))]))  # 10 degrees
    pose = im.cam_from_world()
    b.frames[im.frame_id].rig_from_world = pycolmap.Rigid3d(turn * pose.rotation, pose.translation)
    med, worst = agreement(a, b)
    assert AGREE_DEG[1] < 8.0 < worst < 10.5 and med < AGREE_DEG[0], (med, worst)


def test_mask_dilate(photos, tmp_path):
    from PIL import Image

    staged = stage_images(photos, tmp_path / "staged")
    masks = tmp_path / "masks"
    masks.mkdir()
    a = np.zeros((256, 256), np.uint8)
    a[100:120, 100:120] = 1
    for n in staged.names:
        Image.fromarray(a).save(masks / n)
    out = stage_masks(masks, staged, tmp_path / "m", dilate=5)
    m = np.asarray(Image.open(out / f"{staged.names[0]}.png")) > 0
    ys, xs = np.nonzero(m)
    assert (ys.min(), ys.max(), xs.min(), xs.max()) == (95, 124, 95, 124)
    with pytest.raises(InputError, match="mask-dilate"):
        SfmOptions(mask_dilate=-1).check()
