"""The static viewer bundle: everything the browser needs to reproduce ``MeshRenderer``'s real-time frames.

A bundle is a self-contained folder (serve it with ``omnirecon view`` or any static file server)::

    index.html, viewer.js,      the viewer (``omnirecon/viewer/static``)
    shaders.js
    lib/three/...               three.js, copied from the npm package (``omnirecon/viewer/node_modules``)
    bundle.json                 cameras, MLP weights, the real-time setting, sizes (below)
    mesh.glb                    the mesh with baked vertex colours, input frame
    sources/NN_<name>.png       the source images (for people; the shader reads images.bin)
    images.bin                  uint8 ``[K, H, W, 4]``: source RGB, and in alpha the object mask as
                                ``min(d^2, 255)``, ``d`` the distance in pixels from each pixel to the nearest pixel
                                off the source's object mask (0 off the mask; 255 everywhere without masks), from
                                which the shader takes ``mask_falloff``'s ``clip(d / reach, floor, 1)`` exactly
    features.bin                float32 ``[K, C4, h + 2, w + 2, 4]``: the appearance projection folded
                                into the stride-4 features, ``W F_k + b`` (channel ``4 j + i`` in layer
                                ``j``, zero channels up to a multiple of 4), with a one-texel border of
                                ``b``: exactly the table of ``MeshRenderer``'s fused shader (the K sources encoded
                                together)
    depth.bin                   float32 ``[K, H + 1, W + 1]``: the visibility test's largest rasterized
                                source depth per 2x2 pixel block (``MeshRenderer.source_depth_max``;
                                1e30 = background / outside)
    cameras.bin                 float32 ``[K, 4, 4]``: rows 0-2 the source projection ``K_k [R_k | t_k]`` (model
                                frame; a point ``p`` projects to ``(u z, v z, z)``), row 3 the centre ``(c_k, 1)``

All binary files are little-endian, C order. ``bundle.json`` holds ``to_model`` / ``to_input`` (the
similarity between the input frame of ``mesh.glb`` and the normalised model frame the shader works
in), ``mesh_box`` (model frame, for near/far as ``MeshRasterizer.depth_range``), the sources' scene ``views``,
``proj`` and ``centers`` (as ``cameras.bin``), the MLP weights (``w1 # [h1, C + 3]``, ``b1``, ``w2 # [h2, h1]``,
``b2``, ``w3 # [1, h2]``, ``b3``), the background colour, the visibility tolerance and default, and what
:func:`omnirecon.mesh.ibr.realtime_setting` gives (``setting``) as the viewer starts: ``blend`` (``network`` or
``angle``; ``sources``, the angle blend's per point; ``frame_sources``, the network blend's per frame, the nearest to
the frame's camera by ``metric`` around ``center``, as :func:`omnirecon.engine.views.select_sources`; 0: all),
``fill`` (``far``, ``nearest`` or ``background``; the far layer's box and z-depth, :mod:`omnirecon.mesh.fill`, the
nearest fill's ``reach``), ``cracks`` (the crack fill's radius) and ``source_masks`` (``reach``, ``floor`` of
:func:`omnirecon.mesh.kernel.mask_falloff`, or null without masks), and a default camera in the input frame. Its
``version`` is :data:`omnirecon.viewer.format.VERSION`; ``omnirecon view`` and the page refuse another.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import torch

from omnirecon.data.io import write_image
from omnirecon.errors import InputError
from omnirecon.mesh.fill import NEAREST_FILL_REACH, layer_box
from omnirecon.mesh.kernel import MASK_FLOOR, MASK_REACH
from omnirecon.viewer.format import FORMAT, VERSION

STATIC = Path(__file__).resolve().parent / "static"
"""Where the viewer's own files are."""
STATIC_FILES = ("index.html", "viewer.js", "shaders.js")
"""The viewer's own files, copied into each bundle."""
THREE_FILES = ("LICENSE", "build/three.module.js", "build/three.core.js", "examples/jsm/controls/OrbitControls.js",
               "examples/jsm/loaders/GLTFLoader.js", "examples/jsm/utils/BufferGeometryUtils.js",
               "examples/jsm/utils/SkeletonUtils.js")
"""The parts of the ``three`` npm package the viewer imports."""
FAR_AWAY = 1e30
"""Stands for an infinite source depth (background) in ``depth.bin``."""


def three_candidates() -> list[Path]:
    """Where the ``three`` npm package is looked for, in order: ``$OMNIRECON_THREE``, the package's
    ``node_modules`` (``npm install`` in ``omnirecon/viewer``, done by ``make setup``), the working
    directory's ``node_modules``."""
    out = []
    if os.environ.get("OMNIRECON_THREE"):
        out.append(Path(os.environ["OMNIRECON_THREE"]))
    out += [Path(__file__).resolve().parent / "node_modules" / "three", Path.cwd() / "node_modules" / "three"]
    return out


def find_three() -> Path | None:
    """The ``three`` package folder, or ``None`` when it is not installed."""
    for p in three_candidates():
        if all((p / f).is_file() for f in THREE_FILES):
            return p
    return None


def three_unavailable_reason() -> str | None:
    if find_three() is None:
        return ("three.js is not installed (looked in " + ", ".join(str(p) for p in three_candidates())
                + "); run `npm install` in omnirecon/viewer (make setup does) or set OMNIRECON_THREE")
    return None


# ---------------------------------------------------------------------- appearance tables
def appearance_tables(renderer) -> dict:
    """What the WebGL shader needs of the model, from a :class:`~omnirecon.mesh.ibr.MeshRenderer`
    (Omni-Recon's appearance branch): the folded feature table, the MLP weights, the source projections.
    Returns NumPy arrays and plain lists."""
    model = renderer.model
    app = model.appearance if model.capabilities.appearance else None
    linears = [m for m in getattr(app, "mlp", []) if isinstance(m, torch.nn.Linear)]
    if app is None or not hasattr(app, "proj") or len(linears) != 3:
        raise InputError(f"{type(model).__name__} has no Omni-Recon appearance branch (Linear + 3-layer MLP)", None,
                         "export a checkpoint of an omnirecon-* preset")
    with torch.inference_mode():
        W, b = app.proj.weight.float().cpu(), app.proj.bias.float().cpu()  # [C, C], [C]
        maps = renderer.features.maps.float().cpu()  # [K, C, h, w]
        folded = torch.einsum("dc,kchw->kdhw", W, maps) + b[:, None, None]
        folded = torch.nn.functional.pad(folded - b[:, None, None], (1, 1, 1, 1)) + b[:, None, None]
        K, C, hp, wp = folded.shape
        C4 = -(-C // 4)
        folded = torch.nn.functional.pad(folded, (0, 0, 0, 0, 0, 4 * C4 - C))  # zero channels
        features = folded.reshape(K, C4, 4, hp, wp).permute(0, 1, 3, 4, 2).contiguous().numpy()
        cams = renderer.sources.cameras.to(device="cpu", dtype=torch.float32)
        proj = torch.zeros(K, 4, 4)
        proj[:, :3] = cams.K @ cams.w2c[:, :3, :]  # as MeshRenderer (float32)
        proj[:, 3, 3] = 1
        table = proj.clone()  # [K, 4, 4] cameras.bin: the projection's rows 0-2, then (centre, 1)
        table[:, 3, :3] = cams.centers
        mlp = {"feature_dim": C, "hidden": [linears[0].out_features, linears[1].out_features]}
        for i, lin in enumerate(linears, 1):
            mlp[f"w{i}"] = lin.weight.float().cpu().tolist()
            mlp[f"b{i}"] = lin.bias.float().cpu().tolist()
        if linears[0].in_features != C + 3 or linears[2].out_features != 1:
            raise InputError(f"unexpected appearance MLP shape {[tuple(m.weight.shape) for m in linears]}", None,
                             "export a checkpoint of an omnirecon-* preset")
    return {"features": features, "proj": proj.tolist(), "centers": cams.centers.tolist(), "mlp": mlp,
            "cameras": table.numpy().astype("<f4")}


def source_depth_table(renderer) -> np.ndarray:
    """``MeshRenderer.source_depth_max`` with infinity replaced by :data:`FAR_AWAY`. ``# [K, H + 1, W + 1]``"""
    d = renderer.source_depth_max
    if d is None:
        raise ValueError("the bundle needs a MeshRenderer built with MeshRenderOptions(visibility=True)")
    d = d.float().cpu().numpy()
    return np.where(np.isfinite(d), d, FAR_AWAY).astype("<f4")


def mask_table(masks: torch.Tensor | None, shape: tuple[int, int, int]) -> np.ndarray:
    """The images' alpha channel: per source pixel ``min(d^2, 255)``, ``d`` its distance in pixels to the nearest
    pixel off the object mask ``masks # [K, H, W]`` (the Euclidean distance transform of
    :func:`omnirecon.mesh.kernel.mask_falloff`: 0 off the mask, and for a source whose mask is empty); 255 everywhere
    without masks. ``d^2`` is an integer, so the shader's ``clip(sqrt(a) / reach, floor, 1)`` is ``mask_falloff``'s
    value for any reach below 15.9 px. ``# [K, H, W]`` uint8"""
    if masks is None:
        return np.full(shape, 255, np.uint8)
    from scipy.ndimage import distance_transform_edt

    m = masks.bool().cpu().numpy()
    d = np.stack([distance_transform_edt(k) if k.any() else np.zeros(k.shape) for k in m])  # [K, H, W] px
    return np.minimum(np.rint(d * d), 255).astype(np.uint8)


# ---------------------------------------------------------------------- writing
def _camera_dict(cam) -> dict:
    return {"fx": float(cam.fx[0]), "fy": float(cam.fy[0]), "cx": float(cam.cx[0]), "cy": float(cam.cy[0]),
            "width": cam.width, "height": cam.height, "c2w": cam.c2w[0].double().tolist()}


def _box(points: np.ndarray) -> list[list[float]]:
    if len(points) == 0:
        return [[-1.0] * 3, [1.0] * 3]
    return [points.min(0).tolist(), points.max(0).tolist()]


def write_bundle(folder: Path, renderer, glb: bytes, vertices, faces, to_input, background, names=None,
                 visibility: bool = True, extra: dict | None = None, setting: dict | None = None,
                 views: list[int] | None = None, selection: dict | None = None) -> Path:
    """Write a viewer bundle to ``folder`` (replaced as a whole: built beside it, then swapped in).

    Args:
        renderer: The :class:`~omnirecon.mesh.ibr.MeshRenderer` of the mesh (model frame) with
            ``MeshRenderOptions(visibility=True)`` over every source the viewer may blend: its encoded sources (their
            object masks too), model and source depths.
        glb: ``mesh.glb``'s bytes (input frame, baked vertex colours).
        vertices, faces: The mesh in the model frame (for the near/far box). ``# [V, 3]``, ``# [F, 3]``
        to_input: Similarity model frame -> input frame. ``# [4, 4]``
        background: Colour where no triangle (RGB in [0, 1]).
        names: Source view names (file names of ``sources/``).
        visibility: Whether the viewer starts with the visibility test on (it can toggle it).
        extra: More JSON-serialisable entries for ``bundle.json`` (model, bake statistics, ...).
        setting: What the viewer starts with, a :func:`omnirecon.mesh.ibr.realtime_setting` (blend, fill, sources per
            frame (0: all), angle sources per point, source masks, cracks); default: ``renderer``'s options with
            every source in every frame.
        views: The sources' scene view indices (for the record).
        selection: How the network blend picks each frame's sources: ``{"metric": "angle" | "distance",
            "center": [3] model frame}`` (:func:`omnirecon.engine.views.select_sources`); default: by distance.

    Returns:
        ``folder``.
    """

    three = find_three()
    if three is None:
        raise InputError(three_unavailable_reason(), None, "or pass --no-viewer to write only mesh.ply and mesh.glb")
    folder = Path(folder)
    o = renderer.options
    setting = setting or {"blend": o.blend, "fill": o.fill, "sources": 0, "angle_sources": o.angle_sources,
                          "source_masks": o.source_masks, "cracks": o.cracks}
    selection = selection or {"metric": "distance", "center": None}
    tables = appearance_tables(renderer)
    depth = source_depth_table(renderer)
    sources = renderer.sources
    K, H, W = sources.images.shape[:3]
    names = list(names) if names is not None else [f"view_{i}" for i in range(K)]
    T = torch.as_tensor(to_input, dtype=torch.float64)
    to_model = torch.linalg.inv(T)
    verts = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    used = verts[np.unique(faces)] if len(faces) else verts[:0]
    used_in = used @ T[:3, :3].numpy().T + T[:3, 3].numpy()
    cams_in = sources.cameras.to(device="cpu", dtype=torch.float64).transformed(T)
    up = -cams_in.R[:, :, 1].mean(0)
    up = up / up.norm().clamp_min(1e-12)
    rgb = (sources.images.float().clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)  # [K, H, W, 3]
    rgba = np.concatenate([rgb, mask_table(sources.masks, (K, H, W))[..., None]], -1)  # [K, H, W, 4]
    files = [f"sources/{i:02d}_{Path(str(n)).stem}.png" for i, n in enumerate(names)]
    box = layer_box(sources.rig, sources.bounds)
    meta = {
        "format": FORMAT, "version": VERSION, "mesh": "mesh.glb",
        "vertices": int(len(verts)), "faces": int(len(faces)),
        "to_input": T.tolist(), "to_model": to_model.tolist(), "mesh_box": _box(used), "mesh_box_input": _box(used_in),
        "background": [float(c) for c in background], "up": up.tolist(),
        "visibility": {"default": bool(visibility), "tol": float(o.visibility_tol)},
        "setting": dict(setting),
        "blend": {"default": setting["blend"], "sources": int(setting["angle_sources"]),
                  "frame_sources": int(setting["sources"]), "metric": selection["metric"],
                  "center": None if selection.get("center") is None else [float(c) for c in selection["center"]]},
        "fill": {"default": setting["fill"], "far": float(sources.far), "reach": NEAREST_FILL_REACH,
                 "box": None if box is None else sources.bounds.double().cpu().tolist()},
        "cracks": int(setting.get("cracks", 0)),
        "source_masks": None if sources.masks is None else {
            "default": bool(setting.get("source_masks")), "reach": MASK_REACH, "floor": MASK_FLOOR},
        "camera": _camera_dict(cams_in[0]),
        "sources": {"count": K, "width": W, "height": H, "names": [str(n) for n in names], "images": files,
                    "views": None if views is None else [int(v) for v in views],
                    "proj": tables["proj"], "centers": tables["centers"],
                    "cameras_input": [_camera_dict(cams_in[i]) for i in range(K)]},
        "textures": {
            "images": {"file": "images.bin", "dtype": "uint8", "shape": list(rgba.shape),
                       "content": "RGB; alpha min(d^2, 255), d the distance in px to the nearest pixel off the mask"},
            "features": {"file": "features.bin", "dtype": "float32", "shape": list(tables["features"].shape),
                         "content": "W F_k + b (appearance projection folded in), one-texel border of b"},
            "depth": {"file": "depth.bin", "dtype": "float32", "shape": list(depth.shape),
                      "content": f"max rasterized z-depth per 2x2 pixel block, {FAR_AWAY:g} = none"},
            "cameras": {"file": "cameras.bin", "dtype": "float32", "shape": list(tables["cameras"].shape),
                        "content": "rows 0-2: K [R | t] (model frame), row 3: (centre, 1)"},
        },
        "mlp": tables["mlp"],
        **(extra or {}),
    }
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.pid{os.getpid()}.", dir=folder.parent))
    try:
        for name in STATIC_FILES:
            shutil.copyfile(STATIC / name, tmp / name)
        for rel in THREE_FILES:
            (tmp / "lib/three" / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(three / rel, tmp / "lib/three" / rel)
        (tmp / "mesh.glb").write_bytes(glb)
        (tmp / "images.bin").write_bytes(rgba.tobytes())
        (tmp / "features.bin").write_bytes(tables["features"].astype("<f4").tobytes())
        (tmp / "depth.bin").write_bytes(depth.tobytes())
        (tmp / "cameras.bin").write_bytes(tables["cameras"].tobytes())
        for i, f in enumerate(files):
            write_image(tmp / f, rgb[i])
        (tmp / "bundle.json").write_text(json.dumps(meta, indent=1))
        os.chmod(tmp, 0o755)
        old = None
        if folder.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{folder.name}.old.", dir=folder.parent))
            os.replace(folder, old / folder.name)
        os.replace(tmp, folder)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return folder
