"""Structure from motion with pycolmap: SIFT features, matching, incremental mapping, undistortion.

:func:`run_sfm` turns a folder of staged images into a reconstruction in ``work/``; :func:`write_scene`
undistorts its largest model to PINHOLE cameras and writes a standard COLMAP scene (``sparse/0/`` +
``images/`` + ``images_2/``, ``images_4/``) that :mod:`omnirecon.data.colmap` reads.

Matching: every pair of images (``exhaustive``, up to 20 photos), or each image with the next ``overlap``
images and those 2, 4, 8, ... further on (``sequential``, for video frames), plus with ``loop_pairs``
the images most like it (a walk's loop closures), or each photo with its next 2 in name order and the
ones most like it, then bridge pairs while the verified matches leave groups apart (``retrieval``, more
than 20 photos). The pairs are
matched in chunks so that progress and its ETA advance while COLMAP works. One thread by default
(``threads``; the features, the same at any count: ``feature_threads``), a fixed seed: the same input gives the same
model. When too few images register,
the mapping is retried without the EXIF focal length, with affine-adapted features and with relaxed
settings (:class:`SfmOptions`). The
kept model's poses are checked against their verified pairs and a contradicted view is dropped
(:mod:`omnirecon.capture.consistency`).

Size: features, matching, the mapping and its retries, and the scene writer share one set of options
and one work folder; split apart they would pass both around.
"""

from __future__ import annotations

import contextlib
import shutil
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

from PIL import Image

from omnirecon.capture import consistency, learned, retrieval
from omnirecon.capture.learned import DETECTOR
from omnirecon.errors import InputError
from omnirecon.options import CameraModel, Seeded, check_options
from omnirecon.progress import progress_bar

CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
MIN_POINTS = 8  # the COLMAP reader needs this many to bound depths
NEAR = 2
"""Retrieval matching: each photo is matched with this many next ones in name order (a walk's photos are
numbered in order), besides its :attr:`SfmOptions.retrieval_pairs` most similar ones."""
BRIDGE_ROUNDS = 3
"""Retrieval matching: rounds of bridge pairs at most (:func:`_matched_pairs`)."""
BRIDGE_PAIRS = 10
"""Retrieval matching: the most similar pairs between a group left apart and the other images, per round."""
MAPPER = {"init_min_tri_angle": 4.0, "init_min_num_inliers": 50, "abs_pose_min_num_inliers": 15,
          "abs_pose_min_inlier_ratio": 0.15}
"""COLMAP mapper settings relaxed from its defaults (16 degrees, 100, 30, 0.25) for small captures:
20 images of a few hundred pixels give few features, and short arcs give small angles."""
RELAXED = {"mapper.abs_pose_min_num_inliers": 12, "mapper.abs_pose_min_inlier_ratio": 0.1, "mapper.max_reg_trials": 5,
           "triangulation.ignore_two_view_tracks": False}
"""Mapper settings of the retry that continues the largest model: images posed from 12 inlier
correspondences, and points seen in two images kept, so images at the end of a chain of weakly
overlapping views can still be posed."""
MIN_MATCHES = 15  # verified matches a pair needs in every mapping (COLMAP's default)


@dataclass
class SfmOptions(CameraModel, Seeded):
    """How COLMAP runs."""

    per_image_cameras: bool = False
    """One camera per image (photos from several cameras or zoom settings); default one shared camera."""
    matcher: Literal["auto", "exhaustive", "sequential", "retrieval"] = "auto"
    """Image pairs to match: auto = sequential for video frames, exhaustive for up to 20 photos, retrieval above
    (each photo with its next 2 in name order and its ``retrieval_pairs`` most similar ones by visual words,
    :mod:`omnirecon.capture.retrieval`, then bridge pairs while groups of photos share no verified match)."""
    retrieval_pairs: int = 6
    """Retrieval matching: each photo is also matched with this many of the photos most like it."""
    overlap: int = 10
    """Sequential matching: each image is matched with this many following ones (plus 2^k further)."""
    loop_pairs: int = 0
    """Sequential matching: also match each image with this many of the images most like it further than
    ``overlap`` away (visual words of its own SIFT features, :mod:`omnirecon.capture.retrieval`): closes
    the loop of a walk around a subject. 0 = off; a video's denser pass uses 5."""
    max_image_size: int = 1600
    """SIFT runs on images downscaled so their long side is at most this (the scene keeps full size)."""
    max_features: int = 8192
    """Most SIFT features per image."""
    affine_sift: bool = False
    """Affine-adapted SIFT with domain-size pooling (COLMAP's option for wide baselines; slower)."""
    guided_matching: bool = True
    """Re-match each verified pair guided by its epipolar geometry (more matches; on 20 views of dtu_scan37 it
    registered 18 instead of 14). Exhaustive and sequential matching only: retrieval matching (photo sets over 20)
    never, since guided matching of a pair of photos with thousands of keypoints each takes many times as long."""
    peak_threshold: float = 0.0067
    """SIFT detection threshold (COLMAP's default 0.0067; lower finds more features in small images)."""
    first_octave: int = -1
    """SIFT's first octave: -1 (COLMAP's default) doubles the image before detection, -2 quadruples it
    (more, finer features on small images; slower)."""
    max_ratio: float = 0.8
    """Lowe's ratio test when matching (COLMAP's default 0.8; higher keeps more ambiguous matches)."""
    retry_below: float = 1.0
    """When the first mapping registers fewer than this fraction of the images, retry: map again with the
    focal length estimated from the matches instead of the EXIF one (photos with a focal length in their
    EXIF), with affine-adapted SIFT features (``affine_retry``), then continue the largest model with relaxed
    settings (:data:`RELAXED`), stopping once every image has a pose; a retry's model is kept when it has
    more images and agrees with the current one on the images both pose (:data:`omnirecon.capture.consistency.AGREE_DEG`). 0 turns
    retries off; a capture whose images all register is never retried."""
    learned: Literal["auto", "prefer", "off"] = "off"
    """Retries include learned matches (DISK + LightGlue, the optional ``capture-learned`` extra) for the
    images SIFT left without a pose and a few partners each, not all pairs (:mod:`omnirecon.capture.hybrid`);
    auto: its model (after the pose check) kept under the retry rule (more images, the same poses on the
    ones both have); prefer: kept whenever it poses more images. Off by default: on 20 lego views the kept
    learned model still held views placed the wrong way round (bench poses --methods hybrid)."""
    learned_features: Literal["aliked", "disk"] = DETECTOR
    """The learned detector whose keypoints LightGlue matches (:data:`omnirecon.capture.learned.DETECTORS`; ALIKED
    is the faster)."""
    affine_retry: bool = True
    """Retries include re-extracting features with affine shape and domain-size pooling (wide
    baselines on object captures; features take about 3x longer)."""
    mask_dilate: int = 0
    """Grow each mask (``--masks``) by this many pixels before features are detected: the object's
    outline and a turntable's top turn with the object, and add features."""
    min_registered: float = 0.5
    """Fail when fewer than this fraction of the images (or fewer than 3) get a pose (after the pose check)."""
    min_explained: float = 0.5
    """Pose check: drop a registered image whose pose explains less than this share of the verified
    matches of its image pairs (median over its pairs, weighted by matches), e.g. one placed the wrong way
    round (:mod:`omnirecon.capture.consistency`); 0 turns the check off."""
    threads: int = 1
    """CPU threads for COLMAP (1 gives reproducible models: with more, pairs are verified side by side and two runs may
    keep slightly different matches, and poses)."""
    feature_threads: int | None = None
    """CPU threads for the SIFT features alone (each image on its own: the same features at any count); ``None``:
    ``threads``."""

    def check(self) -> None:
        if self.camera_model not in CAMERA_MODELS:
            raise InputError(f"unsupported --camera-model {self.camera_model}", None, f"use one of {', '.join(CAMERA_MODELS)}")
        check_options("process", self, memory=False)  # every number's range: omnirecon/options.py


@dataclass
class SfmResult:
    """The chosen reconstruction and what happened on the way."""

    reconstruction: object
    """The largest pycolmap.Reconstruction."""
    names: list[str]
    """All images given."""
    registered: list[str]
    """Images with a pose in the chosen model."""
    models: int
    """How many separate models the mapper produced."""
    pairs: int
    """Image pairs matched."""
    matcher: str
    seconds: dict[str, float] = field(default_factory=dict)
    dropped: dict[str, str] = field(default_factory=dict)
    """Why each unregistered image got no pose (:func:`omnirecon.capture.dropped.drop_reasons`)."""
    attempts: list[dict] = field(default_factory=list)
    """Each mapping tried: what, images registered, models, seconds; ``kept`` marks the chosen one."""
    reachable: int | None = None
    """Images linked to the kept model's by pairs of enough verified matches: the most any mapping of
    these features could pose (None when every image registered)."""
    motions: dict | None = None
    """The turntable check on the matches and poses (:func:`omnirecon.capture.motions.still_background`)."""
    learned: dict | None = None
    """What the learned matcher did (:func:`_learned_attempt`); None when SIFT needed no help."""
    pose_check: dict | None = None
    """The pose check's summary (:func:`omnirecon.capture.consistency.check_poses`); None when it is off."""

    @property
    def unregistered(self) -> list[str]:
        got = set(self.registered)
        return [n for n in self.names if n not in got]

    def stats(self) -> dict:
        r = self.reconstruction
        return {
            "images_given": len(self.names), "images_registered": len(self.registered),
            "unregistered": self.unregistered, "dropped": [{"name": n, "reason": self.dropped.get(n, "")}
                                                           for n in self.unregistered],
            "attempts": self.attempts, "reachable": len(self.names) if self.reachable is None else self.reachable,
            "models": self.models, "matcher": self.matcher, "pairs": self.pairs,
            "points3D": int(r.num_points3D()), "mean_reprojection_error_px": float(r.compute_mean_reprojection_error()),
            "mean_track_length": float(r.compute_mean_track_length()) if r.num_points3D() else 0.0,
            "motions": self.motions, "pose_check": self.pose_check,
            "learned": None if self.learned is None else {k: v for k, v in self.learned.items()
                                                          if k not in ("database", "dropped")},
        }


class Stages:
    """Rich progress (one bar with ETA per stage) and the seconds (wall and CPU) each stage took."""

    def __init__(self, quiet: bool = False):
        self.seconds: dict[str, float] = {}
        self.cpu: dict[str, float] = {}
        """CPU seconds of this process (all its threads) per stage."""
        self.quiet = quiet
        self.progress = None

    def __enter__(self):
        if not self.quiet:
            self.progress = progress_bar("{task.description:<10}")
            self.progress.__enter__()
        return self

    def __exit__(self, *exc):
        if self.progress is not None:
            self.progress.__exit__(*exc)

    @contextlib.contextmanager
    def stage(self, name: str, total: int | None):
        """Yields ``advance(n=1, total=None)``; records the stage's seconds."""
        t0, c0 = time.perf_counter(), time.process_time()
        task = self.progress.add_task(name, total=total) if self.progress is not None else None

        def advance(n: int = 1, total: int | None = None):
            if task is not None:
                self.progress.update(task, advance=n, **({} if total is None else {"total": total}))

        try:
            yield advance
        finally:
            self.seconds[name] = round(self.seconds.get(name, 0.0) + time.perf_counter() - t0, 3)  # a stage run twice adds up
            self.cpu[name] = round(self.cpu.get(name, 0.0) + time.process_time() - c0, 3)
            if task is not None:
                t = self.progress.tasks[task]
                self.progress.update(task, completed=t.total if t.total is not None else t.completed)


def _matched_pairs(db: Path, work: Path, names: list[str], kind: str, options: SfmOptions, stages: Stages) -> list:
    """Choose the image pairs of matcher ``kind`` (:func:`omnirecon.capture.retrieval.matcher_kind`), match them into ``db`` and return them.

    Retrieval: the pairs of :func:`omnirecon.capture.retrieval.chosen_pairs`; while the verified matches leave
    groups of images apart, up to :data:`BRIDGE_ROUNDS` more rounds match each smaller group's
    :data:`BRIDGE_PAIRS` most similar pairs with the other images."""
    from omnirecon.capture.dropped import match_graph

    if kind != "retrieval":
        pairs = retrieval.image_pairs(len(names), kind == "sequential", options.overlap)
        if kind == "sequential" and options.loop_pairs:
            pairs = sorted(set(pairs) | set(retrieval.similar_pairs(db, names, options.loop_pairs, options.overlap,
                                                                    options.seed)))
        _match(db, work, names, pairs, options, stages)
        return pairs
    sim = retrieval.similarity(db, names, options.seed)  # [N, N]
    pairs = retrieval.chosen_pairs(sim, NEAR, options.retrieval_pairs)
    _match(db, work, names, pairs, options, stages)
    index = {nm: i for i, nm in enumerate(names)}
    for _ in range(BRIDGE_ROUNDS):
        groups = [[index[nm] for nm in g] for g in match_graph(db).groups(MIN_MATCHES)]
        extra = retrieval.bridge_pairs(sim, groups, BRIDGE_PAIRS, set(pairs))
        if not extra:
            break
        _match(db, work, names, extra, options, stages, stage="matching (bridges)")
        pairs = sorted(set(pairs) | set(extra))
    return pairs


def _quiet_colmap() -> None:
    import pycolmap  # lazy: the optional 'capture' extra

    pycolmap.logging.minloglevel = 3  # fatal only: failures come back as InputError, progress from our bars
    pycolmap.logging.stderrthreshold = 3


def _extract(db: Path, image_dir: Path, names: list[str], options: SfmOptions, stages: Stages, mask_dir: Path | None,
             affine: bool, stage: str = "features") -> None:
    """SIFT features into ``db``, in chunks (progress); the first chunk creates the shared camera."""
    import pycolmap  # lazy: the optional 'capture' extra

    n = len(names)
    extract = pycolmap.FeatureExtractionOptions()
    extract.num_threads = options.feature_threads or options.threads
    extract.max_image_size = options.max_image_size
    extract.sift.max_num_features = options.max_features
    extract.sift.peak_threshold = options.peak_threshold
    extract.sift.first_octave = options.first_octave
    if affine:
        extract.sift.estimate_affine_shape = True
        extract.sift.domain_size_pooling = True
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = options.camera_model
    if mask_dir is not None:
        reader.mask_path = str(mask_dir)
    mode = pycolmap.CameraMode.PER_IMAGE if options.per_image_cameras else pycolmap.CameraMode.SINGLE
    chunk = max(1, min(8, n // 10))
    with stages.stage(stage, n) as advance:
        for k in range(0, n, chunk):
            part = names[k:k + chunk]
            pycolmap.extract_features(db, image_dir, image_names=part, camera_mode=mode, reader_options=reader,
                                      extraction_options=extract, device=pycolmap.Device.cpu)
            if k == 0 and not options.per_image_cameras:
                with pycolmap.Database.open(db) as d:
                    reader.existing_camera_id = d.read_all_cameras()[0].camera_id
            advance(len(part))


def _match(db: Path, work: Path, names: list[str], pairs: list[tuple[int, int]], options: SfmOptions,
           stages: Stages, stage: str = "matching") -> None:
    """Match and verify ``pairs`` in chunks written as match lists (progress with ETA)."""
    import pycolmap  # lazy: the optional 'capture' extra

    match = pycolmap.FeatureMatchingOptions()
    match.num_threads = options.threads
    match.guided_matching = options.guided_matching
    match.sift.max_ratio = options.max_ratio
    verify = pycolmap.TwoViewGeometryOptions()
    if hasattr(verify, "ransac"):
        verify.ransac.random_seed = options.seed
    step = max(1, min(200, len(pairs) // 20))
    with stages.stage(stage, len(pairs)) as advance:
        for k in range(0, len(pairs), step):
            part = pairs[k:k + step]
            lst = work / "pairs.txt"
            lst.write_text("".join(f"{names[i]} {names[j]}\n" for i, j in part))
            pairing = pycolmap.ImportedPairingOptions()
            pairing.match_list_path = str(lst)
            pycolmap.match_image_pairs(db, matching_options=match, pairing_options=pairing,
                                       verification_options=verify, device=pycolmap.Device.cpu)
            advance(len(part))


def _map(db: Path, image_dir: Path, out: Path, options: SfmOptions, relaxed: bool, advance=None,
         start: Path | None = None) -> list:
    """Incremental mapping (``relaxed``: with :data:`RELAXED`; ``start``: continue a model written
    there). Returns the models, largest first; the callback fires once per newly registered image."""
    import pycolmap  # lazy: the optional 'capture' extra

    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = options.threads
    mapping.random_seed = options.seed
    mapping.mapper.random_seed = options.seed
    mapping.triangulation.random_seed = options.seed
    mapping.min_model_size = 3
    mapping.min_num_matches = MIN_MATCHES
    settings = {**{f"mapper.{k}": v for k, v in MAPPER.items()}, **(RELAXED if relaxed else {})}
    for key, v in settings.items():
        *path, name = key.split(".")
        obj = mapping
        for part in path:
            obj = getattr(obj, part)
        setattr(obj, name, v)
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    tick = advance or (lambda n=1: None)
    models = pycolmap.incremental_mapping(db, image_dir, out, mapping, input_path=str(start or ""),
                                          initial_image_pair_callback=lambda: tick(2),
                                          next_image_callback=lambda: tick(1))
    return sorted(models.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()), reverse=True)


def _check_poses(db: Path, rec, options: SfmOptions, groups: list[list[str]] = ()) -> tuple[dict[str, str], dict | None]:
    """The pose check (:attr:`SfmOptions.min_explained`) on the chosen model ``rec``, in place: the views it
    de-registered with their reasons, and its summary (None when off). ``groups``: views posed apart before
    learned matches joined them (:func:`omnirecon.capture.consistency.contested_groups`)."""
    if options.min_explained <= 0:
        return {}, None
    from omnirecon.capture.consistency import check_poses

    t0 = time.perf_counter()
    reasons, summary = check_poses(db, rec, options.min_explained, MIN_MATCHES, options.seed, groups)
    summary["seconds"] = round(time.perf_counter() - t0, 3)
    return reasons, summary


def _learned_attempt(image_dir: Path, names: list[str], work: Path, models: list, db: Path, sequential: bool,
                     options: SfmOptions, stages: Stages) -> dict:
    """The learned matches' database for the images the best model so far (``models[0]``) left out; returns
    what was done (``database``: its path), or why nothing was (not installed, switched off)."""
    if options.learned == "off":
        return {"status": "off"}
    if not learned.available():
        return {"status": "not installed", "install": learned.INSTALL}
    from omnirecon.capture.hybrid import learned_database, learned_pairs

    got = set(_names(models[0])) if models else set()
    unplaced = [nm for nm in names if nm not in got]
    pairs = learned_pairs(db, names, unplaced, sequential, seed=options.seed)
    out = work / "database_learned.db"
    matcher = learned.LearnedMatcher(max_size=options.max_image_size, detector=options.learned_features)
    info = learned_database(db, out, image_dir, names, pairs, matcher, stages, options.seed)
    return {"status": "used", "detector": options.learned_features, "unplaced": len(unplaced), **info,
            "database": str(out)}


def without_focal_prior(db: Path, out: Path) -> bool:
    """Copy database ``db`` to ``out`` (may be ``db``) with its cameras' focal lengths marked as unknown (COLMAP
    then estimates them from the matches instead of trusting the EXIF focal length). Returns False, writing
    nothing, when no camera has a focal length from EXIF."""
    import pycolmap  # lazy: the optional 'capture' extra

    with pycolmap.Database.open(str(db)) as d:
        if not any(c.has_prior_focal_length for c in d.read_all_cameras()):
            return False
    if out != db:
        shutil.copyfile(db, out)
    with pycolmap.Database.open(str(out)) as d:
        for c in d.read_all_cameras():
            c.has_prior_focal_length = False
            d.update_camera(c)
    return True


def needed(min_registered: float, n: int) -> int:
    """Images that must get a pose out of ``n`` (:attr:`SfmOptions.min_registered`, at least 3)."""
    return max(3, int(-(-min_registered * n // 1)))


def _names(rec) -> list[str]:
    return sorted(rec.images[i].name for i in rec.reg_image_ids())


def run_sfm(image_dir: Path, names: list[str], work: Path, options: SfmOptions, stages: Stages,
            video: bool = False, source: Path | None = None, mask_dir: Path | None = None) -> SfmResult:
    """Features, matches and incremental mapping of ``names`` in ``image_dir``; files go to ``work``.

    When fewer than ``options.retry_below`` of the images register, the mapping is retried (see
    :attr:`SfmOptions.retry_below`) and the result with the most images kept; every attempt and the
    reason each left-out image got no pose are recorded. Raises :class:`InputError` (naming
    ``source``, the user's input) when no model comes out or too few images are registered.
    ``mask_dir`` holds COLMAP masks (``<name>.png``, features only where non-zero), e.g. to ignore a
    static background behind an object on a turntable.
    """
    from omnirecon.capture.dropped import drop_reasons, match_graph
    from omnirecon.capture.motions import still_background

    source = image_dir if source is None else source
    _quiet_colmap()
    work.mkdir(parents=True, exist_ok=True)
    db = work / "database.db"
    n = len(names)
    _extract(db, image_dir, names, options, stages, mask_dir, options.affine_sift)
    kind = retrieval.matcher_kind(options.matcher, n, video)
    sequential = kind == "sequential"
    if kind == "retrieval":  # see SfmOptions.guided_matching
        options = replace(options, guided_matching=False)
    pairs = _matched_pairs(db, work, names, kind, options, stages)

    attempts: list[dict] = []

    def attempt(what: str, database: Path, relaxed: bool, start=None, advance=None) -> list:
        t0 = time.perf_counter()
        models = _map(database, image_dir, work / f"sparse_{len(attempts)}", options, relaxed, advance, start)
        attempts.append({"attempt": what, "relaxed": relaxed, "registered": models[0].num_reg_images() if models else 0,
                         "models": len(models), "seconds": round(time.perf_counter() - t0, 3)})
        return models

    with stages.stage("mapping", n) as advance:
        models, chosen = attempt("default settings", db, False, advance=advance), 0
    best_db, learned_info, apart = db, None, []
    if options.retry_below > 0 and (not models or models[0].num_reg_images() < options.retry_below * n):
        with stages.stage("retries", None):

            def consider(cand: list, database: Path, affine: bool = False, prefer: bool = False) -> None:
                nonlocal models, chosen, best_db  # cand: the attempt just made
                k = len(attempts) - 1
                now = models[0].num_reg_images() if models else None
                got = cand[0].num_reg_images() if cand else 0
                agree = consistency.agreement(models[0], cand[0]) if models and cand and got >= now else None
                attempts[k]["agrees_deg"] = agree
                if consistency.replaces(now, got, agree, affine, n) or (prefer and got > (now or 0)):
                    models, chosen, best_db = cand, k, database

            no_prior = work / "database_no_focal_prior.db"
            if without_focal_prior(db, no_prior):  # an EXIF focal length the matches contradict
                consider(attempt("EXIF focal length ignored", no_prior, False), no_prior)
            unprior = best_db == no_prior
            short = lambda: not models or models[0].num_reg_images() < n  # noqa: E731 - retries go on while short
            if options.affine_retry and not options.affine_sift and short():
                db2 = work / "database_affine.db"
                _extract(db2, image_dir, names, options, stages, mask_dir, True, stage="features (affine)")
                if unprior:
                    without_focal_prior(db2, db2)
                _match(db2, work, names, pairs, options, stages, stage="matching (affine)")
                consider(attempt("affine SIFT", db2, False), db2, affine=True)
            apart = [_names(m) for m in models[1:]]  # SIFT's separate models: joined only by learned matches
            learned_info = _learned_attempt(image_dir, names, work, models, best_db, sequential, options, stages) \
                if short() else {"status": "not needed"}
            if learned_info.get("database"):
                db3 = Path(learned_info["database"])
                cand = attempt(f"learned matches ({learned.label(options.learned_features)}) for the images SIFT "
                               "left out", db3, False)
                if cand:  # its flipped views go before it is compared (their reasons kept with it)
                    learned_info["dropped"], _ = _check_poses(db3, cand[0], options, apart)
                    attempts[-1]["registered"] = cand[0].num_reg_images()
                    attempts[-1]["pose_check_dropped"] = sorted(learned_info["dropped"])
                consider(cand, db3, prefer=options.learned == "prefer")
            if models and short():  # continue the largest model: leftovers and smaller models' images may join it
                start = work / "start_model"
                start.mkdir(exist_ok=True)
                models[0].write(start)
                consider(attempt("relaxed, continuing the largest model", best_db, True, start), best_db)
    if chosen < len(attempts):
        attempts[chosen]["kept"] = True
    if not models:
        raise InputError(f"no camera poses found: 0 of {n} images registered", source,
                         "take more overlapping photos (each spot seen from 3+ viewpoints, 60-80% overlap), "
                         "with texture and without motion blur")
    best = models[0]
    learned_db = learned_info and best_db == Path(learned_info.get("database", ""))
    checked, pose_check = _check_poses(best_db, best, options, apart if learned_db else ())
    if learned_db:
        checked = {**learned_info.get("dropped", {}), **checked}
    if best.num_points3D() < MIN_POINTS:
        raise InputError(f"the largest model has {best.num_reg_images()} images but only {best.num_points3D()} 3-D "
                         "points", source, "take more overlapping, textured photos")
    registered = _names(best)
    result = SfmResult(best, list(names), registered, len(models), len(pairs),
                       kind, dict(stages.seconds), attempts=attempts,
                       learned=learned_info,
                       motions=still_background(best_db, best), pose_check=pose_check)  # turntable check
    if len(registered) < n:
        graph = match_graph(best_db)
        result.dropped = {**drop_reasons(names, registered, [_names(m) for m in models[1:]], graph, MIN_MATCHES),
                          **checked}
        result.reachable = len(graph.reachable(registered, MIN_MATCHES))
    need = needed(options.min_registered, n)
    if len(registered) < need:
        missing = result.unregistered
        shown = ", ".join(missing[:8]) + (f" and {len(missing) - 8} more" if len(missing) > 8 else "")
        raise InputError(f"only {len(registered)} of {n} images registered (need {need}); not registered: {shown}",
                         source, "add photos that overlap those views, or remove them; "
                         "lower --min-registered to accept a partial model")
    return result


def write_scene(result: SfmResult, image_dir: Path, work: Path, scene: Path, stages: Stages,
                threads: int = 1, factors: tuple[int, ...] = (2, 4), masks: Path | None = None) -> dict:
    """Undistort the chosen model to PINHOLE and write the scene folder ``scene`` (must not exist).

    With per-image cameras whose undistorted sizes differ, every image is centre-cropped to the
    smallest size (principal points shifted), since the reader wants one image size. ``masks``: a folder
    of object masks ``<image name>.png`` at the photos' size, undistorted and cropped like the images into
    ``scene/masks``, ``scene/masks_<f>`` (:mod:`omnirecon.capture.masks`). Returns ``{"size": [W, H],
    "crop": bool}``.
    """
    import pycolmap  # lazy: the optional 'capture' extra

    _quiet_colmap()
    model_dir = work / "chosen"
    model_dir.mkdir(parents=True, exist_ok=True)
    result.reconstruction.write(model_dir)
    und = work / "undistorted"
    with stages.stage("undistort", len(result.registered)) as advance:
        opts = pycolmap.UndistortCameraOptions()
        pycolmap.undistort_images(und, model_dir, image_dir, output_type="COLMAP", undistort_options=opts,
                                  num_threads=threads)
        advance(len(result.registered))
    rec = pycolmap.Reconstruction(und / "sparse")
    sizes = {(c.width, c.height) for c in rec.cameras.values()}
    w, h = min(s[0] for s in sizes), min(s[1] for s in sizes)
    crop = len(sizes) > 1
    offsets = {im.name: ((rec.cameras[im.camera_id].width - w) // 2, (rec.cameras[im.camera_id].height - h) // 2)
               for im in rec.images.values()}
    scene.mkdir(parents=True)
    shutil.move(str(und / "images"), str(scene / "images"))
    if masks is not None:
        from omnirecon.capture.masks import write_masks

        with stages.stage("masks", len(rec.images)) as advance:
            advance(write_masks(masks, result.reconstruction, rec, scene, (w, h), offsets, factors))
    if crop:
        for im in rec.images.values():
            cam = rec.cameras[im.camera_id]
            x0, y0 = offsets[im.name]
            path = scene / "images" / im.name
            with Image.open(path) as pic:
                pic.crop((x0, y0, x0 + w, y0 + h)).save(path)
            cam.params = [cam.params[0], cam.params[1], cam.params[2] - x0, cam.params[3] - y0]
            cam.width, cam.height = w, h
    (scene / "sparse" / "0").mkdir(parents=True)
    rec.write_binary(scene / "sparse" / "0")
    with stages.stage("downscale", len(rec.images) * len(factors)) as advance:
        for f in factors:
            size = (round(w / f), round(h / f))
            (scene / f"images_{f}").mkdir()
            for im in rec.images.values():
                with Image.open(scene / "images" / im.name) as pic:
                    pic.resize(size, Image.Resampling.BOX).save(scene / f"images_{f}" / im.name)
                advance()
    return {"size": [w, h], "crop": crop}
