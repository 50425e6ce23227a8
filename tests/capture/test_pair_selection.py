"""Retrieval matching: a photo folder's pairs chosen by name order and visual words instead of all pairs,
with bridge pairs while groups of photos share no verified match.

The capture is the 12 views of a procedural frontal scene (256 px) renamed in a shuffled order, so that the
neighbours in name order are not the neighbours in space and the similar pairs must find them.
"""

import shutil

import numpy as np
import pytest

from omnirecon.capture.retrieval import bridge_pairs, chosen_pairs

pycolmap = pytest.importorskip("pycolmap", reason="pycolmap is the optional `capture` extra: pip install pycolmap")

from conftest import procedural_photos  # noqa: E402


def test_chosen_pairs():
    """Neighbours in name order plus each image's most similar others beyond them."""
    sim = np.eye(6)
    sim[0, 5] = sim[5, 0] = 0.9  # 0 and 5 look alike: a loop
    sim[1, 4] = sim[4, 1] = 0.5
    pairs = chosen_pairs(sim, near=1, per_image=1)
    assert {(0, 1), (1, 2), (2, 3), (3, 4), (4, 5)} <= set(pairs)
    assert (0, 5) in pairs and (1, 4) in pairs
    assert all(i < j for i, j in pairs)


def test_bridge_pairs():
    """A group apart gets its most similar pairs with the rest, never ones already matched."""
    sim = np.full((5, 5), 0.1)
    sim[3, 1] = sim[1, 3] = 0.8
    sim[4, 0] = sim[0, 4] = 0.6
    sim[3, 2] = sim[2, 3] = 0.7
    groups = [[0, 1, 2], [3, 4]]
    assert bridge_pairs(sim, groups, 2, done=set()) == [(1, 3), (2, 3)]
    assert bridge_pairs(sim, groups, 2, done={(1, 3)}) == [(0, 4), (2, 3)]
    assert bridge_pairs(sim, [[0, 1, 2, 3, 4]], 2, done=set()) == []  # one group: nothing to bridge


def test_retrieval_matching_poses_a_shuffled_capture(tmp_path):
    """12 views under shuffled names: retrieval matching (2 name neighbours + 2 similar per photo, bridges)
    matches fewer pairs than exhaustive, links every photo and poses all 12."""
    from omnirecon.capture.colmap_sfm import SfmOptions, Stages, run_sfm
    from omnirecon.capture.dropped import match_graph
    from omnirecon.capture.images import stage_images

    photos = procedural_photos(tmp_path, 256)
    shuffled = tmp_path / "shuffled"
    shuffled.mkdir()
    order = np.random.default_rng(3).permutation(12)
    for k, p in enumerate(sorted(photos.iterdir(), key=lambda p: int(p.stem.split("_")[-1]))):
        shutil.copyfile(p, shuffled / f"p{order[k]:02d}{p.suffix}")
    staged = stage_images(shuffled, tmp_path / "input", min_images=3, shared_camera=True)
    options = SfmOptions(matcher="retrieval", retrieval_pairs=2, learned="off", retry_below=0)
    with Stages(quiet=True) as stages:
        result = run_sfm(staged.folder, staged.names, tmp_path / "work", options, stages)
    assert result.matcher == "retrieval"
    assert result.pairs < 12 * 11 // 2
    assert len(match_graph(tmp_path / "work" / "database.db").groups()) == 1
    assert len(result.registered) == 12


def test_without_focal_prior(tmp_path):
    """Photos whose EXIF gives a focal length: the copy of their database has it marked unknown (the mapping
    retry for an EXIF focal length the matches contradict), the original keeps it; without one nothing is written."""
    from PIL import Image

    from omnirecon.capture.colmap_sfm import without_focal_prior

    rng = np.random.default_rng(0)
    for exif_focal, folder in ((35, "exif"), (None, "plain")):
        (tmp_path / folder).mkdir()
        for k in range(2):
            exif = Image.Exif()
            if exif_focal is not None:
                exif.get_ifd(0x8769)[41989] = exif_focal  # FocalLengthIn35mmFilm
            Image.fromarray(rng.integers(0, 255, (96, 128, 3), dtype=np.uint8)).save(
                tmp_path / folder / f"{k}.jpg", exif=exif)
        db = tmp_path / f"{folder}.db"
        pycolmap.extract_features(db, tmp_path / folder, camera_mode=pycolmap.CameraMode.SINGLE,
                                  device=pycolmap.Device.cpu)
        out = tmp_path / f"{folder}_no_prior.db"
        assert without_focal_prior(db, out) == (exif_focal is not None)
        with pycolmap.Database.open(str(db)) as d:
            assert all(c.has_prior_focal_length == (exif_focal is not None) for c in d.read_all_cameras())
        if exif_focal is None:
            assert not out.exists()
            continue
        with pycolmap.Database.open(str(out)) as d:
            assert not any(c.has_prior_focal_length for c in d.read_all_cameras())


def test_the_features_are_the_same_at_any_number_of_threads(tmp_path):
    """``SfmOptions.feature_threads`` (what ``reconstruct --threads`` gives COLMAP's SIFT): each image is extracted on its
    own, so 2 threads write the same keypoints and descriptors as 1."""
    from omnirecon.capture.colmap_sfm import SfmOptions, Stages, _extract

    photos = procedural_photos(tmp_path, 128, views=4)
    names = sorted(p.name for p in photos.iterdir())
    found = []
    for threads in (1, 2):
        db = tmp_path / f"t{threads}.db"
        with Stages(quiet=True) as stages:
            _extract(db, photos, names, SfmOptions(feature_threads=threads), stages, None, affine=False)
        with pycolmap.Database.open(db) as d:
            found.append({im.name: (d.read_keypoints(im.image_id), np.asarray(d.read_descriptors(im.image_id).data))
                          for im in d.read_all_images()})
    assert set(found[0]) == set(names) and all(len(found[0][n][0]) > 0 for n in names)
    for n in names:
        assert np.array_equal(found[0][n][0], found[1][n][0]) and np.array_equal(found[0][n][1], found[1][n][1]), n
