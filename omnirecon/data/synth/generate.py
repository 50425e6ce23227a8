"""Generate one procedural scene: layout -> exact triangle mesh -> rendered views -> files on disk.

Layout of a scene folder (the Blender / NeRF-synthetic layout, extended)::

    scene_00042/
      transforms_train.json   all other views
      transforms_val.json     views with i % 8 == 4
      transforms_test.json    views with i % 8 == 0 (none when the scene has a single view)
      train/r_1.png           RGB (background colour baked in)
      train/r_1_depth.png     16-bit camera z: z = value * depth_scale (scene units), 0 = no surface
      train/r_1_normal.png    world normal, round((n * 0.5 + 0.5) * 255); 0,0,0 = no surface
      train/r_1_label.png     8-bit ids: 0 = background, 1..254 objects, 255 = ground / backdrop
      train/r_1_mask.png      255 where an object (not ground, not background) is seen
      test/r_0.png, val/r_4.png ...  the same for test and val views (names keep the view index)
      scene.json              primitives (type, params, pose, texture, id), light, rig, options
      mesh.ply                the exact triangles that were rendered (scene frame, float32
                              vertices, per-face ``object_id``)

Every transforms file carries the shared header: ``camera_angle_x``, ``fl_x, fl_y, cx, cy, w, h``
(pixels, pixel centres at +0.5), ``near``/``far`` (z-depth bounds over every surface seen in any
view and every object vertex in every view, with 5 % margins), ``aabb`` (all mesh vertices,
ground patch included), ``rig`` (``object`` for the object and frontal rigs, ``forward``),
``background``, ``mesh_path``, ``depth_scale``, ``ground_label`` (255), ``seed`` and
``generator_version``; ``transform_matrix`` is the OpenGL camera-to-world matrix.

A split file is left out when it would hold no frames (scenes of fewer than 5 views have no val
split). The folder is written under a hidden temporary name and renamed when complete, so an
interrupted run never leaves a half-written scene.

The RGB images are anti-aliased by ``antialias x antialias`` supersampling (box filter); depth,
normals, labels and masks are the single sample at each pixel centre, so they stay exact.
"""

from __future__ import annotations

import json
import math
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import trimesh

from omnirecon.data.io import write_image, write_json
from omnirecon.data.synth import rigs
from omnirecon.data.synth.layout import GROUND_ID, Layout, make_layout
from omnirecon.data.synth.photo import camera_effects, options_record, scene_light
from omnirecon.data.synth.primitives import corner_normals, face_normals
from omnirecon.data.synth.render import Mesh, render_view
from omnirecon.data.synth.textures import make_atlas, make_texture
from omnirecon.errors import InputError
from omnirecon.options import ImageSize, check_options
from omnirecon.outputs import swap_in

GENERATOR_VERSION = "omnirecon-synth/1"
OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])
TEST_EVERY = 8
"""View i is a test view when i % 8 == 0 and a val view when i % 8 == 4."""


@dataclass
class SynthOptions(ImageSize):
    """What each generated scene looks like.

    Rigs: ``object`` puts the cameras on a sphere around the objects (upper hemisphere when there
    is a ground), all looking at the centre; ``frontal`` on rows of a +-40 degree arc at similar
    distances, facing the objects (DTU-like); ``forward`` on a small grid of parallel cameras
    looking into a layered scene (LLFF-like).
    """

    rig: Literal["object", "frontal", "forward"] = "object"
    """object: 360 degrees around the objects; frontal: DTU-like +-40 degree arc; forward: LLFF-like grid."""
    views: int = 40
    """Views per scene: view i is test when i % 8 == 0, val when i % 8 == 4, else train."""
    aspect: float = 1.0
    """Image height over width (1: square; 0.75: 4:3 landscape, DTU's 1600x1200). The long side stays
    ``resolution`` and the horizontal field of view the layout's, so a landscape aspect crops the top and bottom."""
    ground: bool = True
    """Add a textured ground patch (plus a backdrop wall in forward scenes), label 255."""
    min_objects: int = 2
    """Fewest primitives per scene."""
    max_objects: int = 6
    """Most primitives per scene."""
    antialias: int = 2
    """RGB samples per pixel side (1 = off); depth, normals and labels use the pixel centre only."""
    detail: int = 1
    """Tessellation of curved primitives: 0 coarse, 1 (3 degrees between sphere facets), 2 fine."""
    # Realism (omnirecon.data.synth.photo): all off by default, each deterministic by seed.
    specular: float = 0.0
    """View-dependent shading: strength of a white Blinn-Phong highlight (e.g. 0.4; 0 = Lambertian only)."""
    shininess: float = 32.0
    """Blinn-Phong exponent of the highlight (larger: smaller, sharper highlights)."""
    light_variation: float = 0.0
    """Lighting that varies between scenes: spread of a random light colour, intensity and ambient share
    per scene (e.g. 1; 0 = the layout's white light)."""
    noise: float = 0.0
    """Sensor noise: std of the shot noise at full intensity, plus a read-noise floor of a quarter of it
    (e.g. 0.02; 0 = none)."""
    exposure: float = 0.0
    """Exposure differences between views: std in stops of a random gain per view (e.g. 0.3; 0 = none)."""
    white_balance: float = 0.0
    """White-balance differences between views: std of a random log gain per channel and view (e.g. 0.05)."""
    vignetting: float = 0.0
    """Corner darkening: gain ``1 - vignetting * r^2``, r = 1 at the corners (e.g. 0.3; 0 = none)."""
    blur: float = 0.0
    """Slight lens blur: Gaussian std in pixels (e.g. 0.6; 0 = none)."""

    def check(self) -> None:
        """Raise :class:`InputError` for out-of-range options."""
        if self.rig not in ("object", "frontal", "forward"):
            raise InputError(f"unknown rig {self.rig!r}", None, "use --rig object, frontal or forward")
        if self.min_objects > self.max_objects:
            raise InputError(f"need --min-objects <= --max-objects, got {self.min_objects} and "
                             f"{self.max_objects}", None, "fix the object counts")
        check_options("synth", self, memory=False)  # every number's range: omnirecon/options.py


def image_size(options: SynthOptions) -> tuple[int, int]:
    """``(width, height)`` in pixels of a scene's images: the long side ``resolution``, the other from ``aspect``."""
    res, aspect = options.resolution, options.aspect
    return (res, max(1, round(res * aspect))) if aspect <= 1 else (max(1, round(res / aspect)), res)


def view_split(i: int, views: int) -> str:
    """Split of view ``i`` of ``views``: ``test`` (i % 8 == 0), ``val`` (i % 8 == 4) or ``train``."""
    if views == 1:
        return "train"
    return {0: "test", TEST_EVERY // 2: "val"}.get(i % TEST_EVERY, "train")


def scene_name(seed: int) -> str:
    return f"scene_{seed:05d}"


def generate_scene(out: Path, seed: int, options: SynthOptions, overwrite: bool = False) -> Path:
    """Generate the scene of ``seed`` into ``out/scene_{seed:05d}`` and return that folder.

    The same seed and options always give byte-identical files. An existing complete scene is
    kept when its ``scene.json`` records the same seed, options and generator version (a cache);
    it is regenerated when any differs, or when ``overwrite``.
    """
    options.check()
    final = Path(out) / scene_name(seed)
    if final.exists() and not overwrite and same_scene(final, seed, options):
        return final
    tmp = Path(out) / f".{final.name}.tmp{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        write_scene(tmp, seed, options)
        swap_in(tmp, final)  # an interrupt leaves the previous scene or the new one, never neither
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return final


def same_scene(folder: Path, seed: int, options: SynthOptions) -> bool:
    """Whether ``folder`` holds the scene of ``seed`` and ``options`` from this generator version."""
    try:
        meta = json.loads((folder / "scene.json").read_text())
    except (OSError, ValueError):
        return False
    return (meta.get("seed") == seed and meta.get("generator_version") == GENERATOR_VERSION
            and meta.get("options") == json.loads(json.dumps(options_record(options))))


def build_mesh(layout: Layout, texture_size: int) -> Mesh:
    """Concatenate the primitives and ground into one :class:`Mesh` in the world frame.

    Vertices are rounded to float32 first, so the renderer draws exactly the triangles that the
    PLY file (float32) stores.
    """
    parts = []  # (world vertices, faces, label, local vertices, local corner normals, texture, tile)
    for prim, mesh in zip(layout.primitives, layout.local_meshes):
        local = np.asarray(mesh.vertices)
        faces = np.asarray(mesh.faces, dtype=np.int64)
        world = local @ prim.pose[:3, :3].T + prim.pose[:3, 3]
        parts.append((world, faces, prim.id, local, corner_normals(local, faces), prim.texture,
                      prim.texture_scale, prim.pose[:3, :3]))
    if layout.ground_vertices is not None:
        g = layout.ground_vertices
        gf = layout.ground_faces
        parts.append((g, gf, GROUND_ID, g, np.broadcast_to(face_normals(g, gf)[:, None], (len(gf), 3, 3)),
                      layout.ground_texture, layout.ground_tile, np.eye(3)))
    vertices, faces, label, corner, texture, tile = [], [], [], [], [], []
    offset = 0
    for i, (world, f, lab, loc, cn, _, scale, rot) in enumerate(parts):
        vertices.append(world.astype(np.float32).astype(np.float64))
        faces.append(f + offset)
        offset += len(world)
        label.append(np.full(len(f), lab, dtype=np.uint8))
        corner.append(np.concatenate([cn @ rot.T, loc[f], cn], axis=2))  # world normal, local pos, local normal
        texture.append(np.full(len(f), i))
        tile.append(np.full(len(f), scale, dtype=np.float32))
    vertices = np.concatenate(vertices)
    faces = np.concatenate(faces)
    atlas = make_atlas([make_texture(p[5], texture_size) for p in parts])
    return Mesh(vertices, faces, np.concatenate(label), face_normals(vertices, faces),
                np.concatenate(corner).astype(np.float32), np.concatenate(texture), np.concatenate(tile), atlas)


def write_scene(folder: Path, seed: int, options: SynthOptions) -> None:
    """Lay out, render and write the scene of ``seed`` into ``folder`` (created)."""
    rng = np.random.default_rng(seed)
    layout = make_layout(rng, options.rig, options.views, options.ground,
                         (options.min_objects, options.max_objects), options.detail)
    res = options.resolution
    width, height = image_size(options)
    mesh = build_mesh(layout, texture_size=int(np.clip(2 ** math.ceil(math.log2(res)), 64, 512)))
    K = rigs.intrinsics(layout.fov, width, height)
    background = np.asarray(layout.background, dtype=np.float32)
    light = scene_light(layout.light, options, seed)
    views = []
    for i, c2w in enumerate(layout.c2w):
        view = render_view(mesh, K, np.linalg.inv(c2w), width, height, light, background, options.antialias)
        view["rgb"] = camera_effects(view["rgb"], options, seed, i)
        views.append(view)

    # Depth bounds over everything seen, and over every object vertex in every view.
    obj = mesh.vertices[np.unique(mesh.faces[mesh.face_label != GROUND_ID])]
    w2c = np.linalg.inv(layout.c2w)
    z_obj = (obj @ w2c[:, 2, :3].T + w2c[:, 2, 3]).ravel() if len(obj) else np.zeros(0)
    z_seen = np.concatenate([v["depth"][v["depth"] > 0] for v in views] + [z_obj])
    near, far = 0.95 * float(z_seen.min()), 1.05 * float(z_seen.max())
    depth_scale = far / 65000.0

    folder.mkdir(parents=True)
    splits = {"train": [], "val": [], "test": []}
    for i, (c2w, v) in enumerate(zip(layout.c2w, views)):
        split = view_split(i, len(layout.c2w))
        stem = f"{split}/r_{i}"
        _write_view(folder / stem, v, depth_scale)
        splits[split].append({
            "file_path": f"./{stem}",
            "transform_matrix": (c2w @ OPENCV_TO_OPENGL).tolist(),
            "depth_file_path": f"{stem}_depth.png",
            "normal_file_path": f"{stem}_normal.png",
            "label_file_path": f"{stem}_label.png",
            "mask_file_path": f"{stem}_mask.png",
        })
    header = {
        "camera_angle_x": layout.fov,
        "fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "w": width, "h": height,
        "near": near, "far": far,
        "aabb": [mesh.vertices.min(0).tolist(), mesh.vertices.max(0).tolist()],
        "rig": "forward" if layout.rig == "forward" else "object",
        "background": [float(c) for c in layout.background],
        "mesh_path": "mesh.ply",
        "depth_scale": depth_scale,
        "ground_label": GROUND_ID,
        "seed": seed,
        "generator_version": GENERATOR_VERSION,
    }
    for split, frames in splits.items():
        if frames:
            write_json(folder / f"transforms_{split}.json", {**header, "frames": frames})
    write_json(folder / "scene.json", {
        "generator_version": GENERATOR_VERSION, "seed": seed, "options": options_record(options),
        "rig": layout.rig, "rig_params": layout.extras, "fov_x": layout.fov,
        "primitives": [p.to_json() for p in layout.primitives],
        "ground": None if layout.ground_vertices is None else {
            "id": GROUND_ID, "vertices": layout.ground_vertices.tolist(), "faces": layout.ground_faces.tolist(),
            "texture": layout.ground_texture, "texture_scale": layout.ground_tile},
        "light": {"direction": light.direction.tolist(), "ambient": light.ambient, "intensity": light.intensity,
                  **({"color": list(light.color)} if light.color != (1.0, 1.0, 1.0) else {}),
                  **({"specular": light.specular, "shininess": light.shininess} if light.specular > 0 else {})},
        "background": layout.background,
        "near": near, "far": far, "aabb": header["aabb"],
        "splits": {k: [int(f["file_path"].rsplit("_", 1)[1]) for f in v] for k, v in splits.items()},
    })
    ply = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    ply.face_attributes["object_id"] = mesh.face_label
    (folder / "mesh.ply").write_bytes(ply.export(file_type="ply"))


def render_cameras(folder: Path, c2w: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
    """The exact images of the generated scene in ``folder`` at any cameras: its layout rebuilt from the seed and
    options in ``scene.json``, rendered as :func:`write_scene` renders its views (anti-aliased), without the per-view
    camera effects (noise, exposure, ...): the clean image a perfect camera takes there. ``c2w # [N, 4, 4]``: OpenCV camera-to-world in the scene file's
    frame (``Scene.to_input`` maps a loaded scene's frame there); ``K # [3, 3]`` pixels, pixel centres at +0.5.
    ``# [N, height, width, 3]`` float32 in [0, 1]"""
    meta = json.loads((Path(folder) / "scene.json").read_text())
    if meta.get("generator_version") != GENERATOR_VERSION:
        raise InputError(f"scene made by {meta.get('generator_version')!r}, not {GENERATOR_VERSION}", folder,
                         "regenerate it with this version (omnirecon synth)")
    options = SynthOptions(**meta["options"])
    seed = int(meta["seed"])
    layout = make_layout(np.random.default_rng(seed), options.rig, options.views, options.ground,
                         (options.min_objects, options.max_objects), options.detail)
    res = options.resolution
    mesh = build_mesh(layout, texture_size=int(np.clip(2 ** math.ceil(math.log2(res)), 64, 512)))
    light = scene_light(layout.light, options, seed)
    background = np.asarray(layout.background, dtype=np.float32)
    out = []
    for pose in np.asarray(c2w, dtype=np.float64):
        view = render_view(mesh, np.asarray(K, np.float64), np.linalg.inv(pose), width, height, light, background,
                           options.antialias)
        out.append(view["rgb"])
    return np.stack(out).astype(np.float32)


def _write_view(stem: Path, view: dict, depth_scale: float) -> None:
    """PNG files of one rendered view (see the module docstring for the encodings)."""
    hit = view["face"] >= 0
    depth = np.where(hit, np.round(view["depth"] / depth_scale), 0).astype(np.uint16)
    normal = np.where(hit[..., None], np.round((view["normal"] * 0.5 + 0.5) * 255), 0).astype(np.uint8)
    label = view["label"]
    mask = np.where((label > 0) & (label != GROUND_ID), 255, 0).astype(np.uint8)
    write_image(stem.with_name(stem.name + ".png"), view["rgb"])
    write_image(stem.with_name(stem.name + "_depth.png"), depth)
    write_image(stem.with_name(stem.name + "_normal.png"), normal)
    write_image(stem.with_name(stem.name + "_label.png"), label)
    write_image(stem.with_name(stem.name + "_mask.png"), mask)
