"""One scene kind (issue 45 item 2): the defaults per kind of scene come from :class:`SceneKind`, decided once by
:func:`scene_kind`, and the library's mesh defaults are the command line's."""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import pytest

from omnirecon.data.synth.generate import SynthOptions, generate_scene
from omnirecon.engine.scenes import load_at_resolution
from omnirecon.scene_kind import SceneKind, scene_kind
from tests.engine.test_extrapolation import walk

PACKAGE = Path(__file__).resolve().parents[1] / "omnirecon"
RIG_TESTS = re.compile(r"""\brig\s*(==|!=|in\s)""")
"""A comparison on a rig: scene-kind policy belongs in :mod:`omnirecon.scene_kind`."""
NOT_POLICY = {
    "scene_kind.py": "the one place",
    "data/synth/layout.py": "the procedural rigs' camera layouts (generation, not a default)",
    "data/synth/generate.py": "writes the generated scene's rig",
    "models/ibrnet.py": "samples a ray bundle's depth (Sources.rig: inverse depth on forward-facing rigs)",
    "models/guided.py": "as above",
    "models/sampler.py": "as above",
    "models/floor.py": "as above",
    "models/omnirecon.py": "as above (and its scene box on forward-facing rigs)",
    "models/feature_volume.py": "the feature volume's box on forward-facing rigs (a ray bundle's Sources.rig)",
    "mesh/fill.py": "layer_box reads a ray bundle's rig (Sources.rig)",
}


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("kinds")
    return {rig: load_at_resolution(generate_scene(tmp / rig, 0, SynthOptions(rig=rig, views=6, resolution=32)), 32)
            for rig in ("object", "forward")}


def test_the_kind_is_read_from_the_scene(scenes):
    obj, fwd = scenes["object"], scenes["forward"]
    assert scene_kind(obj) == SceneKind("object", masks=True, background=True, walk=False)
    assert scene_kind(obj, masks=False).masks is False
    assert scene_kind(replace(obj, masks=None), masks=True).masks is False  # asked for, but the scene has none
    assert scene_kind(fwd, masks=False) == SceneKind("forward", masks=False, background=True, walk=False)
    assert scene_kind(SimpleNamespace(rig="object", cameras=walk())).walk
    assert scene_kind(None) == SceneKind()


def test_defaults_per_kind():
    """The table the benches chose (BENCHMARKS "Depth sources", "Away from the photos")."""
    fern, dtu, photos, synth = (SceneKind("forward"), SceneKind("object", masks=True),
                                SceneKind("object"), SceneKind("object", background=True))
    street = SceneKind("object", walk=True)
    assert [k.depth() for k in (fern, dtu, photos, synth)] == ["stereo", "stereo", "stereo+model", "stereo+model"]
    assert photos.depth(has_model=False) == "stereo"
    assert [(k.blend, k.fill) for k in (fern, dtu, photos, synth)] == [
        ("network", "far"), ("angle", "nearest"), ("angle", "nearest"), ("network", "background")]
    assert [k.source_masks for k in (fern, dtu, photos, synth)] == [False, True, False, False]
    assert (street.surface, photos.surface, fern.surface) == ("coherent", "fusion", "fusion")
    assert not fern.occlusion and dtu.occlusion and SceneKind().occlusion
    assert [k.object_without_masks for k in (fern, dtu, photos, SceneKind())] == [False, False, True, True]
    assert (fern.rank_by, dtu.rank_by, SceneKind().rank_by) == ("distance", "angle", "distance")


def test_the_library_meshes_with_the_command_lines_defaults(scenes):
    """``MeshOptions()`` (finetune without --mesh, export) and ``omnirecon mesh`` pick the same depth source and
    pass for a scene."""
    from omnirecon.mesh.build import MeshOptions, resolved
    from omnirecon.workflows.mesh import MeshConfig

    for scene in scenes.values():
        for masks in (False, True):
            for has_model in (False, True):
                cli = MeshConfig(scene=Path("x"), masks=masks).mesh_options(scene, has_model)
                lib = resolved(MeshOptions(), scene, has_model, masks)
                assert (lib.depth, lib.depth_pass) == (cli.depth, cli.depth_pass)
    assert MeshOptions().depth == MeshConfig.depth == "auto"
    assert resolved(MeshOptions(depth="model"), scenes["object"], True, False).depth == "model"


def test_no_rig_comparison_outside_the_scene_kind():
    found = []
    for path in PACKAGE.rglob("*.py"):
        rel = path.relative_to(PACKAGE).as_posix()
        if rel in NOT_POLICY or "node_modules" in path.parts:
            continue
        for i, line in enumerate(path.read_text().splitlines(), 1):
            if RIG_TESTS.search(line.split("#")[0]) and not line.lstrip().startswith(("\"", "'", "``", "*")):
                found.append(f"{rel}:{i}: {line.strip()}")
    assert not found, "compare a SceneKind's property instead:\n" + "\n".join(found)
