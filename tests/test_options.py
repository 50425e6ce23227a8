"""The one place numeric options are checked (omnirecon/options.py): every numeric field of every command
has a rule, non-finite and out-of-range values are refused, and sizes are solved against the memory."""

from __future__ import annotations

import pytest

from omnirecon.cli import COMMANDS, _load
from omnirecon.errors import InputError
from omnirecon.option_memory import check_sizes
from omnirecon.options import RULES, check_options, option_fields, rule_for


def test_every_numeric_option_of_every_command_has_a_rule():
    missing = [(name, f) for name, spec in COMMANDS.items() for f in option_fields(_load(spec))
               if rule_for(name, f) is None]
    assert not missing, missing


def test_every_default_passes_its_rule():
    """The shipped defaults, nested groups' too, are inside their own rules (a rule that refuses a default is wrong)."""
    for name, spec in COMMANDS.items():
        config = _default(_load(spec))
        for f in option_fields(_load(spec)):
            value = _get(config, f) if config is not None else None
            if value is not None:
                values = value if isinstance(value, tuple) else (value,)
                rule = rule_for(name, f)
                assert all(rule.ok(v) for v in values), (name, f, value, rule)


def _default(cls):
    """``cls`` with its defaults, the required fields given any value (``None`` when that fails)."""
    import dataclasses

    required = {f.name: "x" for f in dataclasses.fields(cls) if f.default is dataclasses.MISSING
                and f.default_factory is dataclasses.MISSING}
    try:
        return cls(**required)
    except Exception:  # noqa: BLE001 - a config that checks its inputs on construction: tested by its own tests
        return None


def _get(config, dotted: str):
    for part in dotted.split("."):
        config = getattr(config, part)
    return config


def test_unused_rules_are_few():
    """Rules name real fields (a renamed option must not leave a dead rule behind)."""
    used = {f for spec in COMMANDS.values() for f in option_fields(_load(spec))}
    used |= {f.rsplit(".", 1)[-1] for f in used}
    dead = [k for k in RULES if k.split(".", 1)[-1] not in used and k not in used]
    assert not dead, dead


@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_is_refused_with_the_flag(value):
    import pathlib

    from omnirecon.workflows.finetune import FinetuneConfig

    cfg = FinetuneConfig(scene=pathlib.Path("s"), ckpt=pathlib.Path("c"), seconds=value)
    with pytest.raises(InputError, match="--seconds must be .* finite number.*got"):
        check_options("finetune", cfg)


def test_memory_limit_is_solved_for():
    with pytest.raises(InputError) as e:
        check_sizes([("--frames", "5000", 5000, lambda v: v * 1000.0)], available=2_000_000)
    assert "--frames 5000" in e.value.what and "--frames 1000 or less" in e.value.fix  # 50 % of 2 MB / 1 kB
    check_sizes([("--frames", "1000", 1000, lambda v: v * 1000.0)], available=2_000_000)


def test_notes_printed_while_parsing_reach_stderr(tmp_path, capsys):
    """MachineConfig's note on a --chunk above the memory ceiling is printed while tyro parses (whose stderr the
    CLI captures for its error box): it must still reach the user."""
    from omnirecon.chunk import ceiling
    from omnirecon.cli import main

    rc = main(["render", "--scene", str(tmp_path / "nope"), "--model", "floor", "--chunk", str(ceiling() + 1),
               "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert rc == 2 and "omnirecon: note: --chunk" in err and str(tmp_path / "nope") in err.splitlines()[-1], err


@pytest.mark.parametrize("group, value, flag", [("guided", {"band": 2.0}, "--guided.band must be in [0, 1]"),
                                                ("options", {"rank": 0}, "--options.rank must be in [1, 1024]"),
                                                ("options", {"lr": float("nan")}, "--options.lr must be")])
def test_nested_groups_are_checked_with_their_dotted_flag(group, value, flag):
    import dataclasses
    import pathlib

    from omnirecon.workflows.pet import PETConfig
    from omnirecon.workflows.render import RenderConfig

    config = (RenderConfig(scene=pathlib.Path("s"), model="floor") if group == "guided"
              else PETConfig(ckpt=pathlib.Path("c")))
    config = dataclasses.replace(config, **{group: dataclasses.replace(getattr(config, group), **value)})
    with pytest.raises(InputError) as e:
        check_options("render" if group == "guided" else "pet", config)
    assert flag in e.value.one_line(), e.value.one_line()


def test_mesh_rules_are_one_place():
    """``MeshOptions.check`` (the library) and the CLI refuse ``trunc`` with the same rule and message."""
    import pathlib

    from omnirecon.mesh.build import MeshOptions
    from omnirecon.workflows.mesh import MeshConfig

    with pytest.raises(InputError) as lib:
        MeshOptions(trunc=0.5).check()
    with pytest.raises(InputError) as cli:
        check_options("mesh", MeshConfig(scene=pathlib.Path("s"), trunc=0.5))
    assert lib.value.one_line() == cli.value.one_line() and "[1, 100] voxels" in lib.value.one_line()


def test_mesh_options_follow_the_preset_and_every_given_flag():
    """``omnirecon mesh``'s options reach :class:`MeshOptions` by name (no hand copy): a flag left at its default
    yields to the preset (``--fusion reference``: no face budget, no completion), a given one wins."""
    import dataclasses
    import pathlib

    from omnirecon.mesh.build import PRESETS, MeshOptions
    from omnirecon.workflows.mesh import MESH_FIELDS, MeshConfig

    base = dict(scene=pathlib.Path("s"), depth="model", surface="fusion", depth_pass="fine")
    ref = MeshConfig(**base, fusion="reference").mesh_options()
    assert (ref.max_faces, ref.complete, ref.trunc) == (0, False, PRESETS["reference"]["trunc"])
    assert MeshConfig(**base, fusion="reference", max_faces=5000).mesh_options().max_faces == 5000
    assert MeshConfig(**base).mesh_options().max_faces == MeshOptions().max_faces
    given = {"shifts": (0.01,), "voxel": 0.01, "trunc": 5.0, "weights": False, "max_faces": 1234, "min_acc": 0.25,
             "min_views": 3, "min_component": 0.01, "cull_hidden": False, "complete": False}
    made = MeshConfig(**base, **given).mesh_options()
    fields = {f.name for f in dataclasses.fields(MeshConfig)} & MESH_FIELDS
    assert fields == set(given) | {"depth", "surface", "depth_pass", "chunk"}, fields  # a new shared field: add it here
    assert all(getattr(made, k) == v for k, v in given.items()), made


SAME_NAME = {
    # name: {classes allowed to declare it}: one word for different things (a shared concept is declared once in an
    # option group, a command's own default of it given by ``command_defaults``), each with why
    "ckpt": {"ModelChoice", "CheckpointInput", "ShippedCheckpoint"},  # optional beside --model / required / shipped
    "out": {"OutFolder", "OutPath", "MeshConfig", "BenchConfig"},  # a folder named after the input (None) / a folder
    # of a fixed default name / mesh files (several) / a JSON file
    "scene": {"SceneInput", "ProtocolScenes", "BenchConfig"},  # a required folder / also synth:eval names / optional,
    # instead of bench's procedural scene
    "num_views": {"SourceViews", "EvalCommand", "ExportConfig", "TrainConfig"},  # K / the list of K evaluated / how
    # many train views export keeps (not K) / K per training step, None: the model's
    "model": {"ModelChoice", "TrainConfig"},  # the floor instead of a checkpoint / the preset to train
    "protocol_set": {"ProtocolScenes", "EvalCommand"},  # eval has more protocols (cpu256, ...) and defaults to full
    "resolution": {"ImageSize", "PhotoSize"},  # a size the command renders at / None: the photos' own, at most 512
    "frames": {"CameraPath", "BenchConfig"},  # a video's frames / frames timed
    "views": {"BenchConfig", "MeshConfig", "MeshBlend", "SynthOptions"},  # K / depth views or `all` / the mesh path's
    # sources / views generated
    "path": {"LiftedTargets", "RenderConfig", "ReconstructConfig", "InspectConfig"},  # blend path / camera path / input
    "mesh": {"LiftedTargets", "MeshFile"},  # gt, model, auto or a file / a file
    "masks": {"CaptureInput", "Meshing"},  # a folder of masks for pose finding / mesh with the scene's masks
    "rays": {"StepRays", "BenchConfig", "TrainConfig"},  # per tuning step / per timed batch / per training step and
    # process (None: the preset's)
    "lr": {"AdamRate", "TrainConfig"},  # a fixed rate / the schedule's peak (None: 5e-4)
    "fps": {"CaptureInput", "RenderConfig"},  # frames sampled from a video / of the written video
    "threads": {"ThreadsConfig", "SfmOptions"},  # torch's / COLMAP's
    "fill": {"MeshBlend", "EditConfig"},  # the mesh path's uncovered pixels / a removed object's pixels
    "cracks": {"FinetuneConfig", "ExportConfig"},  # the radius tuned and scored with / None: --finetune's, else 2
    "angle_sources": {"FinetuneConfig", "ExportConfig"},  # candidates the validation views choose from / the one
    # the viewer starts with (None: --finetune's choice)
    "precision": {"FinetuneConfig", "RenderConfig"},  # the tuning steps' arithmetic / rendering's, `auto` per model
    "noise": {"LiftConfig", "SynthOptions"},  # the share of wrong source labels / sensor noise
    "data": {"DemoConfig", "TrainConfig"},  # a scene instead of the demo's own / the training sources
    "warmup": {"BenchConfig", "TrainConfig"},  # untimed frames / the learning rate's warm-up steps
    "workers": {"BenchConfig", "SynthConfig"},  # shading threads / generating processes
    "val_every": {"TrainConfig", "FinetuneConfig"},  # steps / seconds between validations
    "val_views": {"TrainConfig", "FinetuneConfig"},  # test views rendered per validation scene / training views held
    # out of tuning to choose the returned state
    "quiet": {"ViewCommand", "ProcessCommand"},  # no request log / no progress bars
    "geometry": {"EvalCommand", "EditConfig"},  # also mesh and score / also edit the mesh
}
"""Field names more than one class of the command tree declares, each with the classes allowed to."""


def config_tree() -> set[type]:
    """Every dataclass a command's options are made of: the commands, their bases and nested option groups."""
    import dataclasses
    import typing

    seen: set[type] = set()

    def walk(cls: type) -> None:
        for k in cls.__mro__:
            if dataclasses.is_dataclass(k) and k not in seen:
                seen.add(k)
                for hint in typing.get_type_hints(k).values():
                    for t in (hint, *typing.get_args(hint)):
                        if isinstance(t, type) and dataclasses.is_dataclass(t):
                            walk(t)

    for spec in COMMANDS.values():
        walk(_load(spec))
    return seen


def test_no_config_field_is_declared_twice():
    """A flag shared by several commands is declared once (an option group they inherit: omnirecon/options.py,
    omnirecon/engine/machine.py); the same word meaning different things is listed in ``SAME_NAME``."""
    import collections
    import dataclasses

    declared = collections.defaultdict(set)
    for cls in config_tree():
        own = {f.name for f in dataclasses.fields(cls)} & set(cls.__dict__.get("__annotations__", {}))
        own -= set(cls.__dict__.get("COMMAND_DEFAULTS", {}))  # a command's default of a group's field
        for name in own:
            declared[name].add(cls.__name__)
    twice = {n: sorted(c - SAME_NAME.get(n, set())) for n, c in declared.items()
             if len(c) > 1 and c - SAME_NAME.get(n, set())}
    assert not twice, f"declared in more than one class (declare it once in an option group): {twice}"
    stale = {n: sorted(c - declared.get(n, set())) for n, c in SAME_NAME.items() if c - declared.get(n, set())}
    assert not stale, f"SAME_NAME lists classes that no longer declare the field: {stale}"


def test_a_command_default_keeps_its_groups_type_and_help(capsys):
    """``command_defaults`` changes a group field's default only: the type and the help stay the group's, the library
    (the dataclass) and the CLI (``--help``) show the command's default, and a field no group declares is refused."""
    import dataclasses
    import typing

    from omnirecon.cli import main
    from omnirecon.options import SourceViews, command_defaults

    for cls in config_tree():
        for name, value in cls.__dict__.get("COMMAND_DEFAULTS", {}).items():
            group = next(b for b in cls.__mro__[1:] if name in b.__dict__.get("__annotations__", {}))
            assert typing.get_type_hints(cls)[name] == typing.get_type_hints(group)[name], (cls, name)
            assert {f.name: f.default for f in dataclasses.fields(cls)}[name] == value, (cls, name)
    with pytest.raises(SystemExit):
        main(["render", "--help"])
    flag = " ".join(capsys.readouterr().out.replace("│", " ").split("--num-views INT", 1)[1].split()).split(" --")[0]
    assert flag.startswith("Source views K") and flag.endswith("(default: 10)"), flag  # SourceViews' help, render's 10
    with pytest.raises(TypeError, match="option group"):
        command_defaults(nearest=2)(type("X", (SourceViews,), {}))


def test_mesh_library_defaults_are_the_clis():
    """Each ``omnirecon mesh`` option that sets a :class:`MeshOptions` field defaults to the library's value or to
    ``None`` (the preset's), and ``auto`` is resolved the same way in both (``surface``, ``depth``, ``depth_pass``)."""
    import dataclasses
    import pathlib

    from omnirecon.mesh.build import MeshOptions, resolved
    from omnirecon.workflows.mesh import MESH_FIELDS, MeshConfig

    lib = {f.name: f.default for f in dataclasses.fields(MeshOptions)}
    cli = {("neighbours" if f.name == "num_views" else f.name): f.default for f in dataclasses.fields(MeshConfig)}
    differ = {k: (v, lib[k]) for k, v in cli.items() if k in MESH_FIELDS and v is not None and v != lib[k]}
    assert not differ, differ
    made = MeshConfig(scene=pathlib.Path("s")).mesh_options(None, has_model=True)
    assert resolved(MeshOptions(), None, True, False) == dataclasses.replace(made, chunk=MeshOptions().chunk)


@pytest.mark.parametrize("args, line", [
    (["--surface", "poisson"], "--surface poisson needs --masks"),
    (["--fusion", "reference", "--complete"], "--complete works only with --fusion fit"),
    (["--shifts", "1.5"], "--shifts must be in (-1, 1), got 1.5"),
    (["--voxel", "0.5"], "--voxel must be in (0, 0.1], got 0.5")])
def test_mesh_refuses_flags_that_cannot_work(args, line, tmp_path, capsys):
    """One line, exit 2, before the scene is read (the scene here does not exist)."""
    from omnirecon.cli import main

    rc = main(["mesh", "--scene", str(tmp_path / "nope"), "--model", "floor", *args])
    err = capsys.readouterr().err
    assert rc == 2 and line in err and len(err.strip().splitlines()) == 1, err


def test_reference_fusion_keeps_its_sources_per_depth_map():
    """``--fusion reference`` renders each depth map from every view (its preset) unless --num-views is given."""
    import pathlib

    from omnirecon.mesh.build import PRESETS
    from omnirecon.workflows.mesh import MeshConfig

    s = pathlib.Path("s")
    assert MeshConfig(scene=s, fusion="reference").mesh_options().neighbours == PRESETS["reference"]["neighbours"]
    assert MeshConfig(scene=s, fusion="reference", num_views=5).mesh_options().neighbours == 5
    assert MeshConfig(scene=s).mesh_options().neighbours == 3


@pytest.mark.parametrize("name, value", [("shifts", (1.0,)), ("max_edge", 1e-5), ("visibility_tol", 1.0)])
def test_library_checks_use_the_one_rule(name, value):
    """The library's own checks (``MeshOptions.check``, ``ExportOptions.check``) refuse with the CLI's message."""
    import dataclasses
    import pathlib

    from omnirecon.mesh.build import MeshOptions
    from omnirecon.viewer.export import ExportOptions
    from omnirecon.workflows.export import ExportConfig
    from omnirecon.workflows.mesh import MeshConfig

    lib = MeshOptions(shifts=value) if name == "shifts" else dataclasses.replace(ExportOptions(), **{name: value})
    with pytest.raises(InputError) as a:
        lib.check()
    command = "mesh" if name == "shifts" else "export"
    config = (MeshConfig if name == "shifts" else ExportConfig)(scene=pathlib.Path("s"), ckpt=pathlib.Path("c"),
                                                                 **{name: value})
    with pytest.raises(InputError) as b:
        check_options(command, config)
    assert a.value.one_line() == b.value.one_line(), (a.value.one_line(), b.value.one_line())


def test_help_text_reads_as_paragraphs(capsys, monkeypatch):
    """A field's multi-line docstring is one paragraph of ``--help``: its indented continuation lines are joined (tyro
    alone starts a new help line at each), blank lines and list items still break."""
    from omnirecon.cli import main, reflow_help

    assert reflow_help("First line\n    goes on.\n\n    - item one\n    - item\n      two") == (
        "First line goes on.\n\n- item one\n- item two")
    # Sphinx roles and literal backquotes read as plain text
    assert reflow_help("Relaxed (:data:`omnirecon.capture.RELAXED`), :func:`~omnirecon.models.guided.grid_units`,\n"
                       "    ``band``; see :ref:`the notes <notes>`.") == (
        "Relaxed (omnirecon.capture.RELAXED), grid_units, band; see the notes.")
    monkeypatch.setenv("COLUMNS", "400")  # each help entry on one terminal line
    with pytest.raises(SystemExit):
        main(["mesh", "--help"])
    out = capsys.readouterr().out
    chunk = next(line for line in out.splitlines() if "--chunk" in line)
    assert "at most 4096; a one-line note when a given value" in chunk, chunk
    with pytest.raises(SystemExit):
        main(["process", "--help"])
    out = capsys.readouterr().out
    assert "--retrieval" in out and not any(r in out for r in (":mod:", ":data:", ":func:", "``")), out
