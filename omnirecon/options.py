"""The options several commands share, declared once, and every numeric option of every command, checked in one
place before the command starts.

The shared options are small ``kw_only`` dataclasses a command's configuration inherits (:class:`Seeded`,
:class:`Overwrites`, :class:`OutFolder`, :class:`OutPath`, :class:`SceneInput`, :class:`SourceViews`,
:class:`SceneCache`, :class:`ProtocolScenes`, :class:`SynthEvalScenes`, :class:`ViewerBundle`, :class:`CaptureInput`,
:class:`ImageSize`, :class:`PhotoSize`, :class:`CameraPath`, :class:`MeshFile`, :class:`Meshing`, :class:`MeshBlend`,
:class:`CameraModel`, ...; the model and machine groups are in :mod:`omnirecon.engine.machine`), so a flag is
spelled, typed and described once (``tests/test_options.py`` refuses a field declared twice); where only the default
differs, a command states its own with :func:`command_defaults`. Nested groups (``--guided.*``) are checked too.

:func:`check_options` runs in ``omnirecon.cli`` on the parsed configuration of whichever command was chosen,
before its ``main()``: each ``int``/``float`` field (and each element of a tuple of them) must be finite and
inside its :class:`Rule`, looked up by field name in :data:`RULES` (a ``"command.field"`` entry overrides
the field's shared rule), and the options that size an allocation (frames, resolutions, image sizes, rays,
views) are checked against the memory available now by :data:`omnirecon.option_memory.MEMORY`, an estimate per command, so that
an out-of-reach value is refused with the number, the limit and the fix before anything is allocated.
A numeric field without a rule is a bug (``tests/test_options.py`` walks every command); ``None`` always
means "the default" and is not checked. ``--device`` is checked for its spelling here too.

Size: one table of rules for every option of every command (~100 fields), the option groups that declare the
shared ones and the memory model; splitting it by command would scatter the one place this module exists to be.
"""

from __future__ import annotations

import dataclasses
import math
import re
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from omnirecon.errors import InputError
from omnirecon.option_memory import MEMORY, check_sizes
from omnirecon.splits import EVAL_SEEDS


@dataclass(frozen=True)
class Rule:
    """An option's allowed values: ``lo <= v <= hi`` (``lo < v`` when ``above``); ``example`` goes in the fix."""

    lo: float | None = None
    hi: float | None = None
    above: bool = False
    example: str = ""
    unit: str = ""
    """The values' unit, said after the range (``voxels``); empty for plain numbers."""
    below: bool = False
    """``v < hi`` instead of ``v <= hi``."""
    off: bool = False
    """0 is allowed too, outside the range (it turns the option off)."""

    def text(self) -> str:
        if self.lo is not None and self.hi is not None:
            text = f"in {'(' if self.above else '['}{_num(self.lo)}, {_num(self.hi)}{')' if self.below else ']'}"
        elif self.lo is not None:
            text = f"{'>' if self.above else '>='} {_num(self.lo)}"
        else:
            text = f"{'<' if self.below else '<='} {_num(self.hi)}"
        text = f"0 (off) or {text}" if self.off else text
        return f"{text} {self.unit}" if self.unit else text

    def ok(self, v: float) -> bool:
        if self.off and v == 0:
            return True
        if self.lo is not None and (v <= self.lo if self.above else v < self.lo):
            return False
        return self.hi is None or (v < self.hi if self.below else v <= self.hi)


def _num(v: float) -> str:
    return str(int(v)) if float(v).is_integer() else f"{v:g}"


DAY = 86_400.0
COUNT = Rule(1, 1_000_000, example="e.g. 3")
SEED = Rule(0, 2**32 - 1, example="e.g. 0")
WEIGHT = Rule(0, example="e.g. 1.0")
FRACTION = Rule(0, 1, example="e.g. 0.5")
PIXELS = Rule(8, 16_384, example="e.g. 128")

RULES: dict[str, Rule] = {
    # sizes (also checked against free memory, see MEMORY)
    "resolution": PIXELS, "mix_resolution": Rule(0, 16_384, example="e.g. 64 (0: off)"), "mesh_resolution": PIXELS, "source_resolution": PIXELS,
    "render.samples": Rule(2, 4096, example="e.g. 24"),
    "size": PIXELS, "max_image_size": Rule(64, 16_384, example="e.g. 1600"),
    "frames": Rule(1, 1_000_000, example="e.g. 60"), "max_frames": Rule(3, 100_000, example="e.g. 300"),
    "rays": Rule(1, 1_048_576, example="e.g. 1024"), "chunk": Rule(1, 1_048_576, example="e.g. 4096"),
    "views": Rule(0, 1_000_000, example="e.g. 40"), "synth.views": Rule(1, 1_000_000, example="e.g. 40"), "num_views": COUNT, "num_views_range": COUNT,
    "bake_views": COUNT, "face_views": COUNT, "val_views": COUNT, "synth_views": Rule(2, 10_000, example="e.g. 40"),
    "num_scenes": Rule(1, 100_000, example="e.g. 1"), "synth_scenes": Rule(1, 100_000, example="e.g. 32"),
    "synth_count": Rule(1, len(EVAL_SEEDS), example="e.g. 10"), "scenes_in_memory": Rule(1, 10_000, example="e.g. 8"),
    "max_views": COUNT, "train.max_views": Rule(2, 1_000_000, example="e.g. 40"), "max_targets": COUNT, "nearest": Rule(0, 1_000_000, example="e.g. 4, or 0 for every source"), "angle_sources": Rule(0, 1_000_000, example="e.g. 6, or 0 for every source"), "max_held_out": Rule(1, 10_000, example="e.g. 4"),
    "max_faces": Rule(0, example="e.g. 200000"), "face_budget": Rule(0, example="e.g. 200000 (0: the full mesh)"),
    "max_features": Rule(64, 1_000_000, example="e.g. 8192"),
    "max_objects": Rule(1, 254, example="e.g. 6"), "min_objects": Rule(1, 254, example="e.g. 2"),
    "min_views": Rule(1, 10_000, example="e.g. 2"), "num_pairs": Rule(1, 1_000, example="e.g. 4"),
    "labelled": Rule(1, 100_000, example="e.g. 6"), "pool": COUNT, "keep": Rule(1, 100_000, example="e.g. 2"),
    # time and steps (finite, so a run ends)
    "seconds": Rule(0, DAY, above=True, example="e.g. 60 (at most a day)"),
    "finetune_seconds": Rule(0, DAY, example="e.g. 60, or 0 to skip tuning (at most a day)"),
    "eval_at": Rule(0, DAY, example="e.g. 0 10 30 60"),
    "time_budget": Rule(0, 30 * DAY, above=True, example="e.g. 3600"),
    "cpu_budget": Rule(0, 30 * DAY, above=True, example="e.g. 3600"),
    "steps": Rule(1, 1_000_000_000, example="e.g. 1000"), "stop_at": Rule(1, 1_000_000_000, example="e.g. 500"),
    "warmup": Rule(0, 1_000_000, example="e.g. 3"), "volume_repeats": Rule(1, 10_000, example="e.g. 3"),
    "ckpt_every": Rule(0, 1_000_000_000, example="e.g. 250"), "val_every": Rule(0, 1_000_000_000, example="e.g. 250"),
    "log_every": Rule(1, 1_000_000_000, example="e.g. 10"), "switch_every": Rule(1, 1_000_000_000, example="e.g. 10"),
    # optimisation (finite, or the run writes NaN weights)
    "lr": Rule(0, 1, above=True, example="e.g. 5e-4"), "min_lr_ratio": FRACTION,
    "encoder_lr_scale": Rule(0, 100, example="e.g. 0.1"), "weight_decay": Rule(0, 10, example="e.g. 0.0"),
    "clip": Rule(0, 1e6, example="e.g. 1.0 (0: off)"), "aux_weight": WEIGHT, "depth_weight": WEIGHT,
    "mask_weight": WEIGHT, "data_weights": Rule(0, 1e6, example="e.g. 1 1"), "foreground": FRACTION, "objects": FRACTION, "mix_share": FRACTION,
    # camera paths and video
    "arc": Rule(0, 360, above=True, example="e.g. 360"), "rots": Rule(0, 100, above=True, example="e.g. 2"),
    "render.fps": Rule(1, 240, example="e.g. 24"), "fps": Rule(0, 240, above=True, example="e.g. 2"),
    "keyframes": Rule(0, 1_000_000, example="e.g. 0 5 9"), "overlap": Rule(1, 10_000, example="e.g. 10"),
    # picking views, pixels, labels
    "pair": Rule(0, 1_000_000, example="e.g. 0 1"), "targets": Rule(0, 1_000_000, example="e.g. 0 1"),
    "click": Rule(0, 1_000_000, example="e.g. 40 32"), "click_view": Rule(0, 1_000_000, example="e.g. 0"),
    "label": Rule(0, 1_000_000, example="e.g. 1"), "dilation": Rule(0, 1_000, example="e.g. 1"),
    "colour": Rule(0, 1, example="e.g. 0.9 0.1 0.8"),
    # meshing
    "voxel": Rule(0, 0.1, above=True, example="e.g. 0.004"),
    "trunc": Rule(1, 100, example="e.g. 4", unit="voxels"),
    "max_edge": Rule(1e-4, 1, off=True, example="e.g. 0.005 (0: off)"),
    "min_acc": FRACTION, "min_component": FRACTION, "visibility_tol": Rule(0, 1, below=True, example="e.g. 0.01"),
    "shifts": Rule(-1, 1, above=True, below=True, example="e.g. 0.036 (a fraction of the camera's distance)"),
    # photos in
    "downscale": Rule(0, 1024, above=True, example="e.g. 1 or 4"), "min_registered": FRACTION,
    "peak_threshold": Rule(0, 1, above=True, example="e.g. 0.0067"),
    "first_octave": Rule(-3, 1, example="e.g. -1"), "max_ratio": Rule(0, 1, above=True, example="e.g. 0.8"),
    "retry_below": FRACTION, "mask_dilate": Rule(0, 10_000, example="e.g. 0 or 8"), "min_explained": FRACTION,
    "loop_pairs": Rule(0, 1000, example="e.g. 0 or 5"), "retrieval_pairs": Rule(0, 1000, example="e.g. 6"),
    # tuning
    "reg": WEIGHT, "consensus": Rule(0, 10, example="e.g. 0.1 (0: off)"), "soften": Rule(0, 10, example="e.g. 0.7 (px; 0: off)"), "finetune.val_views": Rule(0, 10_000, example="e.g. 2, or 0 for none"),
    "step_views": Rule(0, 1_000_000, example="e.g. 1, or 0 for every tuning view"),
    "skip_nearest": Rule(0, 1_000_000, example="e.g. 1, or 0 for the nearest sources"),
    "val_skip": Rule(0, 1_000_000, example="e.g. 2, or 0 for the nearest sources"),
    "cracks": Rule(0, 16, example="e.g. 2 (0: off)"),
    "residual_res": Rule(1, 256, example="e.g. 16"), "residual_lr": Rule(0, 1, above=True, example="e.g. 1e-2"),
    "surface_lr": Rule(0, 10, above=True, example="e.g. 0.05"),
    "surface_limit": Rule(0, 1, above=True, example="e.g. 0.01 (of the scene box's diagonal)"),
    "surface_res": Rule(0, 512, example="e.g. 32, or 0 for an offset per vertex"),
    "surface_smooth": Rule(0, 1e6, example="e.g. 1 (0: off)"),
    "surface_every": Rule(0, 1_000_000, example="e.g. 50 (steps; 0: never)"),
    # verbs that need more than the shared rule
    "bench.resolution": Rule(16, 16_384, example="e.g. 512"), "bench.size": Rule(16, 16_384, example="e.g. 504 378"),
    "bench.views": Rule(1, 1_000_000, example="e.g. 3"),
    "demo.resolution": Rule(16, 16_384, example="e.g. 96"), "demo.num_views": Rule(2, 1_000_000, example="e.g. 3"),
    "reconstruct.frames": Rule(2, 1_000_000, example="e.g. 48"), "pet.labelled": Rule(2, 100_000, example="e.g. 6"),
    "finetune.val_every": Rule(0, DAY, above=True, example="e.g. 2 (seconds)"),
    "val_margin": Rule(0, 100, example="e.g. 0.1 (dB)"),
    "val_guard": Rule(0, 100, example="e.g. 0 (dB)"),
    # nested option groups (``--group.field``)
    "guided.prior_scale": Rule(1, 64, example="e.g. 4"), "guided.band_samples": Rule(2, 1024, example="e.g. 8"),
    "guided.guard_samples": Rule(0, 1024, example="e.g. 4"), "guided.band": Rule(0, 1, example="e.g. 0.03"),
    "guided.grid_samples": Rule(2, 1024, example="e.g. 32"),
    "guided.max_spread": FRACTION, "guided.min_opacity": FRACTION,
    "guided.upsample": Rule(1, 16, example="e.g. 2"), "guided.edge_spread": FRACTION,
    "guided.colour_samples": Rule(1, 1024, example="e.g. 8"),
    "pet.options.steps": Rule(0, 1_000_000_000, example="e.g. 40"), "options.rank": Rule(1, 1024, example="e.g. 4"),
    "options.alpha": Rule(0, 1e6, above=True, example="e.g. 4"), "options.min_weight": FRACTION,
    # procedural scenes
    "antialias": Rule(1, 8, example="e.g. 2"), "detail": Rule(0, 2, example="e.g. 1"), "blur": Rule(0, 100, example="e.g. 1"),
    "noise": Rule(0, 1, example="e.g. 0.02"), "exposure": Rule(0, 10, example="e.g. 0.3"), "specular": FRACTION,
    "shininess": Rule(0, 10_000, above=True, example="e.g. 32"), "light_variation": FRACTION,
    "white_balance": FRACTION, "vignetting": FRACTION, "aspect": Rule(0.25, 4, example="e.g. 0.75 (4:3 landscape)"),
    # machine and the rest
    "threads": Rule(1, 1024, example="e.g. 1"), "feature_threads": Rule(1, 1024, example="e.g. 2"), "workers": Rule(1, 1024, example="e.g. 2"),
    "port": Rule(0, 65_535, example="e.g. 8765, or 0 for any free port"), "seed": SEED,
}

DEVICE = re.compile(r"^(auto|cpu|mps|cuda(:\d{1,3})?)$")


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def _numbers(value) -> list | None:
    """The numbers in a field value (a number, or a tuple/list of them); ``None`` for anything else."""
    if isinstance(value, bool):
        return None
    if isinstance(value, (int, float)):
        return [value]
    if isinstance(value, (tuple, list)) and value and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                         for v in value):
        return list(value)
    return None


def numeric_fields(cls) -> list[str]:
    """Names of the fields of dataclass ``cls`` annotated with ``int``/``float`` (or tuples/options of them)."""
    hints = typing.get_type_hints(cls)
    out = []
    for f in dataclasses.fields(cls):
        text = str(hints[f.name])
        if "Literal" in text or "bool" in text and "int" not in text:
            continue
        if re.search(r"\b(int|float)\b", text):
            out.append(f.name)
    return out


def option_fields(cls, prefix: str = "") -> list[str]:
    """:func:`numeric_fields` of ``cls`` and of its nested option groups, as dotted names (``guided.band``)."""
    hints = typing.get_type_hints(cls)
    out = [prefix + name for name in numeric_fields(cls)]
    for f in dataclasses.fields(cls):
        sub = _group(hints[f.name])
        if sub is not None:
            out += option_fields(sub, f"{prefix}{f.name}.")
    return out


def _group(hint) -> type | None:
    """The dataclass a field's type names (a nested option group), else ``None``."""
    return hint if isinstance(hint, type) and dataclasses.is_dataclass(hint) else None


def rule_for(command: str | None, name: str) -> Rule | None:
    """The rule of option ``name`` (dotted inside a nested group): ``command.name``, ``name``, then the rule of its
    last part (a nested ``options.seed`` is a seed)."""
    return RULES.get(f"{command}.{name}") or RULES.get(name) or RULES.get(name.rsplit(".", 1)[-1])


def check_options(command: str | None, config, prefix: str = "", memory: bool = True) -> None:
    """InputError for the first option of ``config`` (a command's parsed dataclass, its nested option groups
    included) that is not finite, out of its range, or (``memory``: ``config`` is the command's whole configuration)
    would need more memory than the run may use. ``prefix``: the group's dotted name when ``config`` is a nested
    group checked on its own (``"guided."``)."""
    if not dataclasses.is_dataclass(config):
        return
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        name = prefix + f.name
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            check_options(command, value, f"{name}.", memory=False)  # a nested group: --group.field
            continue
        if f.name == "device" and isinstance(value, str) and not DEVICE.match(value):
            raise InputError(f"--device {value!r} is not a device", None, "use --device cpu, cuda, cuda:0 or auto")
        _check_value(name, _numbers(value), rule_for(command, name))
    estimate = MEMORY.get(command or "") if memory else None
    if estimate is not None:
        check_sizes(estimate(config))


def check_value(name: str, value, command: str | None = None) -> None:
    """InputError naming ``--name`` when ``value`` breaks its rule (for a library function given one option)."""
    _check_value(name, _numbers(value), rule_for(command, name))


def _check_value(name: str, numbers: list | None, rule: Rule | None) -> None:
    """InputError naming ``--name`` when one of ``numbers`` is not finite or outside ``rule``."""
    if numbers is None:
        return
    shown = " ".join(_num(v) if math.isfinite(v) else str(v) for v in numbers)
    for v in numbers:
        if not math.isfinite(v):
            want = f"{rule.text()} (a finite number)" if rule else "a finite number"
            raise InputError(f"{_flag(name)} must be {want}, got {shown}", None,
                             f"use {rule.example}" if rule and rule.example else "pass a finite number")
        if rule is not None and not rule.ok(v):
            raise InputError(f"{_flag(name)} must be {rule.text()}, got {shown}", None,
                             f"use {rule.example}" if rule.example else f"pass a value {rule.text()}")


# ---------------------------------------------------------------------------- shared options
def command_defaults(**values):
    """Class decorator, below ``@dataclass``: a command's own defaults of options declared in the option groups it
    inherits. Each field keeps its group's type and help (declared once); only its default is the command's, in
    the dataclass's ``__init__`` (the library) and so in ``omnirecon VERB --help``'s ``(default: ...)`` (the CLI).
    The names are kept in the class's ``COMMAND_DEFAULTS`` (``tests/test_options.py`` tells them from a field
    declared twice)."""

    def apply(cls):
        own = dict(cls.__dict__.get("__annotations__", {}))
        for name, value in values.items():
            group = next((b for b in cls.__mro__[1:] if name in getattr(b, "__dataclass_fields__", {})), None)
            if group is None or name in own:
                raise TypeError(f"{cls.__name__}.{name}: a command default needs the field declared in an option "
                                "group it inherits, and not again in the command")
            own[name] = typing.get_type_hints(group)[name]  # the group's type, resolved in the group's module
            setattr(cls, name, dataclasses.field(default=value, kw_only=True))
        cls.__annotations__ = own
        cls.COMMAND_DEFAULTS = {**getattr(cls, "COMMAND_DEFAULTS", {}), **values}
        return cls

    return apply


@dataclass(kw_only=True)
class Seeded:
    """A command with random draws."""

    seed: int = 0
    """Random seed of the run's draws (sampled pixels, rays and views, initial weights, procedural scenes, SfM's
    RANSAC; synth: the first scene's): the same seed repeats the run."""


@dataclass(kw_only=True)
class Overwrites:
    """A command that refuses an existing output unless told."""

    overwrite: bool = False
    """Replace an existing --out (without it the command refuses it; mesh and bench replace the files an earlier run
    of theirs wrote either way; synth regenerates the scene folders it finds instead of keeping them, so without it
    an interrupted run resumes)."""


@dataclass(kw_only=True)
class OutFolder:
    """A command that writes one output folder, named after its input when not given."""

    out: Path | None = None
    """Output folder (default: a folder under outputs/<command>/ named after the input or the model)."""


@dataclass(kw_only=True)
class SourceViews:
    """A command that renders or fuses from the K nearest source views."""

    num_views: int = 3
    """Source views K: the nearest views each rendered pixel, depth map or target draws on (and where a command picks
    its views itself and none are given, how many it picks)."""


@dataclass(kw_only=True)
class OutPath:
    """A command that writes one output folder of a fixed default name (demo, process, synth, reconstruct)."""

    out: Path = Path("outputs")
    """Output folder: demo, its report (index.html, demo.json, videos, meshes, pictures); process, the scene folder;
    synth, one scene_NNNNN folder per scene; reconstruct, the whole run. process and reconstruct build it beside
    and rename it into place at the end. The default is the command's own."""


@dataclass(kw_only=True)
class SceneCache:
    """A command that may generate procedural scenes (the synth:eval sets, train's scenes)."""

    cache: Path = Path("outputs/cache")
    """Where procedural scenes are generated, once (later runs read them): the synth:eval sets; train, its training
    scenes in <rig>_<resolution> sub-folders."""


@dataclass(kw_only=True)
class SynthCount:
    """A command that runs on several scenes of a synth:eval set."""

    synth_count: int = 1
    """Scenes taken from a synth:eval set (seeds 900000, 900001, ...): eval scores them together, lift and pet run
    each separately."""


@dataclass(kw_only=True)
class SceneInput:
    """A command that reads one scene folder."""

    scene: Path
    """Scene folder (any supported format: COLMAP, LLFF, Blender, DTU, procedural), normalised as every command reads
    it; its resolution: the command's --resolution where it has one."""


@dataclass(kw_only=True)
class ProtocolScenes(SceneCache):
    """A command that runs on held-out scenes under an evaluation protocol (lift, edit, pet)."""

    scene: str = "synth:eval"
    """A scene folder (any supported format; edit and pet need its label maps) or synth:eval[:object|frontal|forward]
    (held-out procedural scenes with ground-truth labels, normals and depth)."""

    protocol_set: Literal["cpu", "full"] = "cpu"
    """Resolution and targets: cpu (64 px, fewer targets) or full (128 px, the published protocols)."""


@dataclass(kw_only=True)
class SynthEvalScenes(ProtocolScenes, SynthCount):
    """A command that runs on several held-out procedural scenes (lift, pet)."""


@dataclass(kw_only=True)
class ViewerBundle:
    """A command that may write the web viewer (export, reconstruct)."""

    viewer: bool = True
    """Write the web viewer bundle (needs three.js: `npm install` in omnirecon/viewer, done by `make setup`)."""


@dataclass(kw_only=True)
class CaptureInput:
    """A command that finds camera poses for photos or a video (process, reconstruct)."""

    masks: Path | None = None
    """Photos: a folder of masks named like the photos; features only where a mask is non-zero (an object on a
    turntable, whose background does not move with it)."""
    fps: float = 2.0
    """Video input: frames sampled per second of video."""


@dataclass(kw_only=True)
class ImageSize:
    """A command that renders or generates images at one size of its own (render, train, bench, demo, synth)."""

    resolution: int = 128
    """Long side of the images, in pixels (procedural scenes are square unless synth's --aspect; photos are never upscaled): render, the
    frames and their sources; train, the procedural scenes generated and the real ones read; bench, the timed
    targets; demo, the novel-view orbits (its embedded scene is generated at this size, at least 128 px); synth, the
    scenes written. The default is the command's own."""


@dataclass(kw_only=True)
class PhotoSize:
    """A command that reads a scene's photos at a size it may choose (finetune, mesh, export, reconstruct)."""

    resolution: int | None = None
    """Long side of the images read, in pixels, never upscaled: mesh, the images meshed; finetune, the views tuned
    and scored; reconstruct, fine-tuning, the held-out scores and the video; export, the source images. Default: the
    photos' own, at most 512; export: --finetune's, else the scene's evaluation protocol's (128)."""


@dataclass(kw_only=True)
class CameraPath:
    """A command that renders a video along a camera path (render, reconstruct, demo)."""

    frames: int = 60
    """Frames of the camera-path video (demo: of each novel-view orbit, whose volumetric frames dominate its time on
    a CPU; raise it on a GPU). The default is the command's own."""


@dataclass(kw_only=True)
class MeshFile:
    """A command that may take a mesh made before (finetune, export, bench)."""

    mesh: Path | None = None
    """Mesh file in the input scene's frame, as `omnirecon mesh` writes it. finetune and export without it: the mesh
    `omnirecon mesh` makes from the model at the sources; bench: the mesh it times, with --scene."""


@dataclass(kw_only=True)
class Meshing:
    """A command that meshes a scene from depth maps (mesh; export without --mesh)."""

    voxel: float | None = None
    """TSDF voxel edge as a fraction of the bounds diagonal (None: the --fusion preset's, the depth maps' pixel
    footprint for `fit`); export: when it meshes the scene (without --mesh)."""
    masks: bool = False
    """Mesh with the source views' object masks when the scene has them: free space carved outside them and the
    mesh cleaned with them (objects only; without them the background, e.g. the ground, is kept); export: when it
    meshes the scene (without --mesh)."""


@dataclass(kw_only=True)
class SourceOcclusion:
    """A command that blends source views at the surface points of a mesh (the mesh path)."""

    visibility: bool = True
    """Blend at each surface point only the sources that see it: the mesh renderer's occlusion test against each
    source's rasterized depth (``MeshRenderOptions.visibility``; fill points keep every source). Without it a source
    that sees the ground behind an object paints the object with the ground. export: the viewer's starting state
    (it can toggle it); lift and edit: with --path mesh."""


@dataclass(kw_only=True)
class MeshBlend(SourceOcclusion):
    """A command that renders through the mesh path with sources, a blend and a fill of its choosing (finetune,
    export)."""

    views: tuple[int, ...] | None = None
    """Source view indices, never a held-out view: the views the mesh path may blend. Default: finetune, every
    training view with --nearest (the validation views too), with --nearest 0 DTU's 23 24 33, else --num-views evenly
    spaced train views; export, --finetune's sources, else every train view (as the real-time mesh path blends)."""
    blend: Literal["auto", "network", "angle"] = "auto"
    """How each pixel mixes its sources' colours: `network`, the appearance branch's weights over the view's nearest
    sources (the paper; finetune: --nearest of them, export: 6); `angle`, each point's --angle-sources nearest sources
    by viewing angle among those that see it, weighted by angle alone (:func:`omnirecon.mesh.kernel.angle_weights`;
    finetune then tunes nothing, --seconds only scores); `auto`: per scene kind (:func:`omnirecon.mesh.ibr.scene_blend`:
    `angle` for real object captures, `network` for procedural and forward-facing scenes); export: --finetune's
    first, and the viewer can switch."""
    fill: Literal["auto", "far", "nearest", "background"] = "auto"
    """Pixels the mesh misses: `far`, the mesh renderer's background layer shaded by the same blend (finetune tunes on
    its pixels too); `nearest`, the z-depth of the nearest pixel of the same view that the mesh covers (its own
    rendered depth), shaded like mesh points with the occlusion test, `far` where the view misses the mesh entirely;
    `background`, the scene's background colour; `auto`: per scene kind (:func:`omnirecon.mesh.ibr.scene_blend`:
    `background` for scenes that declare their background colour, `nearest` for real object captures, else `far`);
    export: --finetune's first, and the viewer can switch."""


@dataclass(kw_only=True)
class ViewLimit:
    """A command that reads real scenes and may read a subset of their views (train, inspect)."""

    max_views: int | None = None
    """Read at most this many views of each real scene, evenly spaced (default: every view)."""


@dataclass(kw_only=True)
class QuickRun:
    """A command with a reduced run for tests (demo, bench)."""

    quick: bool = False
    """A reduced run for tests: demo, 4 frames at 48 px, one target, a coarse mesh; bench, 128x128, 3 frames, a
    64-ray volumetric batch."""


@dataclass(kw_only=True)
class Resumes:
    """A command whose interrupted run can be continued (train, reconstruct)."""

    resume: bool = False
    """Continue an interrupted run: train, exactly from the latest checkpoint in --out; reconstruct (on unless
    --no-resume), from the stages (poses, mesh, fine-tune, export) a failed or interrupted run kept in OUT.partial,
    each when the input's files and the options it depends on are unchanged."""


@dataclass(kw_only=True)
class Steps:
    """A command that optimises for a number of steps (train, pet)."""

    steps: int = 1000
    """Optimisation steps: train, the learning-rate schedule spans them; pet, Adam steps, each on one labelled view
    (cycling). The default is the command's own."""


@dataclass(kw_only=True)
class AdamRate:
    """A command that tunes with Adam at a fixed learning rate (finetune, pet)."""

    lr: float = 5e-4
    """Adam learning rate: finetune, of the encoder and the appearance branch (the appearance branch alone takes a
    larger one); pet, of its adapters. The default is the command's own."""


@dataclass(kw_only=True)
class StepRays:
    """A command that samples rays (pixels) at random each optimisation step (finetune, pet)."""

    rays: int = 256
    """Rays sampled per step: finetune, pixels of the mesh path (the encoder's pass over the source photos dominates
    a step's cost, so more pixels cost little: `python -m bench finetune_levers`); pet, rays of the labelled views.
    The default is the command's own."""


@dataclass(kw_only=True)
class CameraModel:
    """A command that finds camera poses with COLMAP (process, reconstruct)."""

    camera_model: Literal["SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"] = "SIMPLE_RADIAL"
    """COLMAP camera model estimated during mapping (the images are undistorted to PINHOLE afterwards); reconstruct:
    when PATH holds photos or a video."""
