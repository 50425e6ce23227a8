"""Training data: a bank of scenes from mixed sources, loaded on demand, and per-step batches.

Sources (``--data`` / ``--val-scenes`` of ``omnirecon train``):

* ``synth:RIG`` or ``synth:RIG:N`` (RIG = ``object``, ``frontal`` or ``forward``): ``N`` procedural
  scenes, generated on first use into ``CACHE/<rig>_<res>`` (``_v<views>`` appended when not the
  default 40 views). Training scene ``i`` gets the seed drawn from :data:`TRAIN_SEEDS` by
  ``(seed, i)``; validation uses the first ``N`` seeds of :data:`VAL_SEEDS`.
  ``synth:RIG:seeds=A,B`` names the seeds; training refuses seeds in :data:`EVAL_SEEDS` and :data:`VAL_SEEDS`.
* a scene folder in any format :func:`~omnirecon.data.load_scene` reads, or a folder of scene
  folders. Training refuses a scene folder named in :data:`EVAL_ONLY_SCENES` (or holding a
  procedural scene of an evaluation seed); inside a folder of scenes such scenes are skipped with a note.

Every scene is moved by :meth:`Scene.normalized` so that its content box fits the unit sphere.
Both models depend on the absolute scene scale: GPNR Fourier-encodes Plücker moments and canonical
point coordinates with fixed frequencies (2^0 .. 2^(L-1)), so a scene 10x larger lands on other
frequency bands; IBRNet places its samples in metric ``[near, far]`` and its two-sphere/ray codes
assume a bounded scene. Training on normalised scenes lets one set of weights serve captures
whose units differ (metres, millimetres, COLMAP's arbitrary scale).

Size: sources, bank and batches are one path (a training step's data), in the sections below.
"""

from __future__ import annotations

import fcntl
import math
import os
import re
from collections import OrderedDict
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from omnirecon.cameras import closest_point_to_axes, nearest_views, view_distances
from omnirecon.data import ReadOptions, detect_format, load_scene
from omnirecon.data.io import read_json
from omnirecon.data.scene import Scene
from omnirecon.data.synth.generate import SynthOptions, generate_scene, same_scene, scene_name
from omnirecon.errors import InputError
from omnirecon.rays import Rays, Sources
from omnirecon.scene_kind import scene_kind
from omnirecon.splits import EVAL_ONLY_SCENES, EVAL_SEEDS, TRAIN_SEEDS, VAL_SEEDS

RIGS = ("object", "frontal", "forward")
DEFAULT_SYNTH_VIEWS = SynthOptions().views
BACKGROUNDS = ("white", "black", "random")
"""Backgrounds behind the objects of scenes read from RGBA images (:class:`SceneBank`'s ``background``)."""


@dataclass(frozen=True)
class SceneRef:
    """Where one scene comes from; :meth:`SceneBank.get` materialises it."""

    path: Path
    """The scene folder (for procedural scenes: where it is, or will be, generated)."""
    seed: int | None = None
    """Procedural seed (``None`` for scenes read from disk)."""
    rig: str | None = None
    """Procedural rig."""
    views: int = DEFAULT_SYNTH_VIEWS
    """Procedural view count."""

    @property
    def name(self) -> str:
        return f"synth:{self.rig}:{self.seed}" if self.seed is not None else self.path.name


# ---------------------------------------------------------------------- source specs
def _seed_index(seed: int, i: int) -> int:
    """Procedural training seed number ``i`` of run seed ``seed`` (a deterministic draw from TRAIN_SEEDS)."""
    state = np.random.SeedSequence([seed, i, 0x5EED]).generate_state(1)[0]
    return TRAIN_SEEDS[int(state) % len(TRAIN_SEEDS)]


def synth_folder(cache: Path, rig: str, resolution: int, views: int) -> Path:
    suffix = "" if views == DEFAULT_SYNTH_VIEWS else f"_v{views}"
    return Path(cache) / f"{rig}_{resolution}{suffix}"


def _parse_synth(spec: str, role: str, seed: int, count: int, cache: Path, resolution: int,
                 views: int) -> list[SceneRef]:
    parts = spec.split(":")
    rig = parts[1] if len(parts) > 1 else ""
    if rig not in RIGS or len(parts) > 3:
        raise InputError(f"bad procedural source {spec!r}", None,
                         "write synth:RIG, synth:RIG:N or synth:RIG:seeds=A,B with RIG one of " + ", ".join(RIGS))
    arg = parts[2] if len(parts) == 3 else ""
    if arg.startswith("seeds="):
        try:
            seeds = [int(s) for s in arg[6:].split(",") if s]
        except ValueError:
            seeds = []
        if not seeds:
            raise InputError(f"bad seed list in {spec!r}", None, "write e.g. synth:object:seeds=3,4,5")
    else:
        try:
            n = int(arg) if arg else count
        except ValueError:
            raise InputError(f"bad scene count in {spec!r}", None, "write e.g. synth:object:16") from None
        if n < 1:
            raise InputError(f"scene count must be at least 1 in {spec!r}", None, "write e.g. synth:object:16")
        if role == "train":
            seeds, i = [], 0
            while len(seeds) < n:  # prefix-stable: asking for more scenes keeps the first ones
                s = _seed_index(seed, i)
                seeds += [] if s in seeds else [s]
                i += 1
        else:
            seeds = list(VAL_SEEDS[:n])
    if role == "train":
        bad = [s for s in seeds if s in EVAL_SEEDS or s in VAL_SEEDS]
        if bad:
            raise InputError(f"procedural seed {bad[0]} is reserved for evaluation and validation "
                             f"({EVAL_SEEDS.start}..{VAL_SEEDS.stop - 1})", None,
                             f"train on seeds below {EVAL_SEEDS.start}")
        if any(s < 0 for s in seeds):
            raise InputError("procedural seeds must be non-negative", None, "use seeds >= 0")
    folder = synth_folder(cache, rig, resolution, views)
    return [SceneRef(folder / scene_name(s), s, rig, views) for s in seeds]


def _procedural_seed(folder: Path) -> int | None:
    """Seed recorded by the procedural generator in ``folder``, if it is a procedural scene."""
    for f in sorted(folder.glob("transforms*.json")) + [folder / "scene.json"]:
        if f.is_file():
            try:
                seed = read_json(f).get("seed")
            except InputError:
                return None
            return int(seed) if isinstance(seed, int) else None
    m = re.fullmatch(r"scene_(\d+)", folder.name)
    return int(m.group(1)) if m else None


def _reserved(folder: Path) -> str | None:
    """Why ``folder`` may not be trained on, or ``None``."""
    name = Path(os.path.abspath(folder)).name  # the name given (a link named fern counts)
    if name in EVAL_ONLY_SCENES:
        return f"scene {name!r} is reserved for evaluation (EVAL_ONLY_SCENES)"
    seed = _procedural_seed(folder)
    if seed is not None and (seed in EVAL_SEEDS or seed in VAL_SEEDS):
        return f"procedural scene of seed {seed} is reserved for evaluation and validation"
    return None


def _parse_path(spec: str, role: str, notes: list[str]) -> list[SceneRef]:
    path = Path(spec).expanduser()
    if not path.exists():
        raise InputError("data path does not exist", path, "pass a scene folder, a folder of scenes or synth:RIG")
    if not path.is_dir():
        raise InputError("data path is a file", path, "pass a scene folder or a folder of scenes")
    try:
        detect_format(path)
        scenes = [path]
    except InputError:
        scenes = [p for p in sorted(path.iterdir()) if p.is_dir() and not p.name.startswith(".") and _is_scene(p)]
        if not scenes:
            raise InputError("no scene found in this folder or its sub-folders", path,
                             "pass a scene folder (blender, ngp, llff, dtu, colmap) or a folder of them") from None
        if role == "train":
            kept = [p for p in scenes if _reserved(p) is None]
            notes += [f"skipped {p}: {_reserved(p)}" for p in scenes if p not in kept]
            scenes = kept
            if not scenes:
                raise InputError("every scene in this folder is reserved for evaluation", path,
                                 "train on other scenes")
        return [SceneRef(p) for p in scenes]
    if role == "train" and _reserved(path):
        raise InputError(_reserved(path), path, "train on other scenes; evaluation scenes stay unseen")
    return [SceneRef(p) for p in scenes]


def _is_scene(folder: Path) -> bool:
    try:
        detect_format(folder)
        return True
    except InputError:
        return False


def parse_sources(specs, role: str, *, seed: int, synth_scenes: int, cache: Path, resolution: int,
                  synth_views: int, notes: list[str] | None = None) -> list[list[SceneRef]]:
    """Resolve each source spec into its scenes (one list per spec). ``role``: ``"train"`` or ``"val"``."""
    notes = [] if notes is None else notes
    out = []
    for spec in specs:
        if spec.startswith("synth:") or spec == "synth":
            out.append(_parse_synth(spec, role, seed, synth_scenes if role == "train" else 2, Path(cache),
                                    resolution, synth_views))
        else:
            out.append(_parse_path(spec, role, notes))
    return out


# ---------------------------------------------------------------------- prepared scenes
@dataclass
class PreparedScene:
    """A normalised scene with its training views and their neighbour order, ready for batches."""

    name: str
    scene: Scene
    """Normalised to the unit sphere, float32 images and cameras."""
    targets: list[int]
    """Views a training step renders and draws sources from (the train split, else all views)."""
    neighbours: Tensor
    """For each entry of ``targets``, the positions of the other targets, nearest first. ``# [T, T-1]``"""
    by: str
    """View distance: ``"angle"`` around the scene centre (object rigs) or camera ``"distance"``."""
    center: Tensor | None
    """Look-at centre of an object rig (for ``by="angle"``). ``# [3]``"""
    clear: Tensor | None = None
    """For a scene read from RGBA images whose batches choose their background: the transparency ``1 - alpha``
    of every pixel, while ``scene.images`` holds the object on black (premultiplied colour), so that
    ``images + colour * clear`` is the object on ``colour``; ``None`` otherwise (the images as read). ``# [N, H, W, 1]``"""
    background: str = "white"
    """What :func:`draw_batch` puts behind the object where ``clear`` is set (one of :data:`BACKGROUNDS`)."""

    def sources(self, indices) -> Sources:
        return Sources.from_scene(self.scene, indices)


def prepare(scene: Scene, name: str, on_black: Scene | None = None, background: str = "white") -> PreparedScene:
    """``scene`` ready for batches. ``on_black``: the same views read on black; where the two differ (RGBA images)
    the batches put the object on ``background`` (:data:`BACKGROUNDS`, :attr:`PreparedScene.clear`)."""
    if background not in BACKGROUNDS:
        raise InputError(f"unknown training background {background!r}", None, "use one of " + ", ".join(BACKGROUNDS))
    clear = None
    if on_black is not None and not torch.equal(scene.images, on_black.images):
        clear = (scene.images - on_black.images).mean(-1, keepdim=True).clamp(0, 1)  # 1 - alpha  [N, H, W, 1]
        scene = replace(scene, images=on_black.images)
    scene = scene.normalized()
    scene.cameras = scene.cameras.to(dtype=torch.float32)
    targets = list(scene.splits.get("train") or range(len(scene)))
    if len(targets) < 2:
        raise InputError(f"scene has {len(targets)} training view(s); training needs at least 2", scene.path,
                         "use a scene with more views")
    by = scene_kind(scene).rank_by
    center = closest_point_to_axes(scene.cameras) if by == "angle" else None
    cams = scene.cameras[targets]
    d = view_distances(cams, cams, by=by, center=center).double()
    d.fill_diagonal_(math.inf)
    neighbours = d.argsort(dim=1, stable=True)[:, :-1]
    return PreparedScene(name, scene, targets, neighbours, by, center, clear, background)


class SceneBank:
    """Scenes of several weighted sources, loaded (and generated) on demand, ``capacity`` kept in memory."""

    def __init__(self, sources: list[list[SceneRef]], weights: list[float] | None, resolution: int,
                 capacity: int = 8, max_views: int | None = None, background: str = "white"):
        if background not in BACKGROUNDS:
            raise InputError(f"unknown training background {background!r}", None,
                             "use one of " + ", ".join(BACKGROUNDS))
        self.background = background  # not white: scenes read from disk are also read on black (prepare's on_black)
        self._opaque: set[Path] = set()  # scenes read from disk found without alpha (read once, as they are)
        self.sources = sources
        w = torch.tensor(weights if weights else [1.0] * len(sources), dtype=torch.float64)
        self.weights = w / w.sum()
        self.resolution = resolution
        self.capacity = max(1, capacity)
        self.max_views = max_views
        self._cache: OrderedDict[SceneRef, PreparedScene] = OrderedDict()
        self._downscale: dict[Path, float] = {}
        self.annotate = None
        """Optional ``(ref, scene) -> scene`` for scenes read from disk without depths (the trainer's stereo
        pseudo ground truth: a layer above data computes it)."""

    def __len__(self) -> int:
        return sum(len(s) for s in self.sources)

    def choose(self, gen: torch.Generator) -> SceneRef:
        """A scene drawn by source weight, then uniformly within the source."""
        src = self.sources[int(torch.multinomial(self.weights, 1, generator=gen))]
        return src[int(torch.randint(len(src), (1,), generator=gen))]

    def get(self, ref: SceneRef) -> PreparedScene:
        if ref in self._cache:
            self._cache.move_to_end(ref)
            return self._cache[ref]
        scene = self._load(ref)
        if self.annotate is not None and ref.seed is None and scene.depths is None:
            scene = self.annotate(ref, scene)
        on_black = None
        if self.background != "white" and ref.seed is None and ref.path not in self._opaque:  # procedural: RGB
            on_black = self._load(ref, "black")
            if torch.equal(on_black.images, scene.images):
                self._opaque.add(ref.path)
        prepared = prepare(scene, ref.name, on_black, self.background)
        self._cache[ref] = prepared
        while len(self._cache) > self.capacity:
            self._cache.popitem(last=False)
        return prepared

    def _load(self, ref: SceneRef, background: str = "white") -> Scene:
        if ref.seed is not None:
            ensure_generated(ref, self.resolution)
            return load_scene(ref.path)
        if ref.path not in self._downscale:  # probe the image size with one view
            probe = load_scene(ref.path, options=ReadOptions(max_views=1))
            self._downscale[ref.path] = max(1.0, max(probe.width, probe.height) / self.resolution)
        return load_scene(ref.path, options=ReadOptions(downscale=self._downscale[ref.path], max_views=self.max_views,
                                                        background=background))


def ensure_generated(ref: SceneRef, resolution: int) -> Path:
    """Generate the procedural scene ``ref`` unless present with the same options; safe when several
    processes ask at once."""
    options = SynthOptions(rig=ref.rig, views=ref.views, resolution=resolution)
    if ref.path.is_dir() and same_scene(ref.path, ref.seed, options):
        return ref.path
    ref.path.parent.mkdir(parents=True, exist_ok=True)
    with open(ref.path.parent / f".{ref.path.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            generate_scene(ref.path.parent, ref.seed, options)
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
    return ref.path


# ---------------------------------------------------------------------- batches
@dataclass
class Batch:
    """One training step's input: sources, target rays and their ground-truth colours (and depths)."""

    sources: Sources
    rays: Rays
    rgb: Tensor
    """Ground-truth colour of each ray. ``# [R, 3]``"""
    target: int
    """Target view index in the scene."""
    source_ids: list[int]
    """Source view indices in the scene."""
    depth: Tensor | None = None
    """Ground-truth z-depth of each ray in (normalised) scene units, 0 where unknown; ``None`` when the
    scene has no depths. ``# [R]``"""
    mask: Tensor | None = None
    """Object mask at each ray (1 object, 0 not); ``None`` when the scene has no masks. ``# [R]``"""

    def to(self, device) -> Batch:
        depth = None if self.depth is None else self.depth.to(device)
        mask = None if self.mask is None else self.mask.to(device)
        return Batch(self.sources.to(device), self.rays.to(device), self.rgb.to(device), self.target, self.source_ids,
                     depth, mask)


def draw_batch(ps: PreparedScene, num_views: int, pool: int, rays: int, gen: torch.Generator,
               foreground: float = 0.0) -> Batch:
    """A random target of ``ps.targets``, ``num_views`` sources drawn from its ``pool`` nearest other
    targets, and ``rays`` random pixels of the target (a ``foreground`` fraction of them on the
    foreground mask, when the scene has masks), with their colours and, when the scene has depths,
    their z-depths (already in the normalised frame: :meth:`Scene.normalized` scales them). Where ``ps.clear`` is
    set, target and sources show the object on one colour (:func:`backdrop`, drawn last: a white batch's draws)."""
    t = int(torch.randint(len(ps.targets), (1,), generator=gen))
    near = ps.neighbours[t, :max(pool, num_views)]  # [n]
    pick = near[torch.randperm(len(near), generator=gen)[:num_views]]
    source_ids = [ps.targets[int(i)] for i in pick]
    target = ps.targets[t]
    scene = ps.scene
    H, W = scene.height, scene.width
    n_fg = 0
    if foreground > 0 and scene.masks is not None:
        fg = scene.masks[target].reshape(-1).nonzero()[:, 0]  # [F]
        if len(fg):
            n_fg = round(rays * foreground)
            fg_pix = fg[torch.randint(len(fg), (n_fg,), generator=gen)]
    n_rest = rays - n_fg
    rest = torch.randperm(H * W, generator=gen)[:n_rest] if n_rest <= H * W else \
        torch.randint(H * W, (n_rest,), generator=gen)
    pix = torch.cat([fg_pix, rest]) if n_fg else rest  # [R] flat pixel index
    uv = torch.stack([pix % W, pix // W], -1).to(torch.float32) + 0.5  # pixel centres (u, v)  [R, 2]
    cam = scene.cameras[[target]]
    ray_batch = Rays.from_pixels(cam, torch.zeros(rays, dtype=torch.long), uv)
    rgb = scene.images[target].reshape(-1, 3)[pix]
    depth = None if scene.depths is None else scene.depths[target].reshape(-1)[pix].to(rgb.dtype)
    mask = None if scene.masks is None else scene.masks[target].reshape(-1)[pix].to(rgb.dtype)
    sources = ps.sources(source_ids)
    if ps.clear is not None:
        colour = backdrop(ps.background, gen).to(rgb.dtype)  # [3]
        rgb = rgb + colour * ps.clear[target].reshape(-1, 1)[pix]
        sources.images = sources.images + colour * ps.clear[source_ids]
    return Batch(sources, ray_batch, rgb, target, source_ids, depth, mask)


def backdrop(background: str, gen: torch.Generator) -> Tensor:
    """The flat colour behind a batch's object for ``background`` (:data:`BACKGROUNDS`); ``random`` draws white,
    black or a uniform random colour (equal odds) from ``gen``. ``# [3]``"""
    if background == "random":
        kind = int(torch.randint(3, (1,), generator=gen))
        colour = torch.rand(3, generator=gen)
        return torch.full((3,), float(kind == 0)) if kind < 2 else colour
    return torch.full((3,), 1.0 if background == "white" else 0.0)


def val_views(ps: PreparedScene, count: int, num_views: int) -> list[tuple[int, list[int]]]:
    """Deterministic validation pairs ``(target, sources)``: the first ``count`` test (else val) views,
    each with its ``num_views`` nearest training views; without such splits, the last views of the scene."""
    scene = ps.scene
    held = scene.splits.get("test") or scene.splits.get("val")
    pool = ps.targets
    if not held:
        held = [i for i in range(len(scene))][-count:]
        pool = [i for i in range(len(scene)) if i not in held] or pool
    pairs = []
    for t in held[:count]:
        cand = [i for i in pool if i != t]
        idx = nearest_views(scene.cameras[[t]], scene.cameras[cand], num_views, by=ps.by, center=ps.center)[0]
        pairs.append((t, [cand[int(i)] for i in idx]))
    return pairs
