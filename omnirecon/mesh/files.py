"""The one boundary between a scene's mesh and a mesh file.

Meshes live in the normalised *scene frame* inside the package; files hold them in the user's
*input frame* (``Scene.to_input``, a similarity). Every verb that reads or writes a mesh file goes
through here:

* :func:`read_mesh`: a file (PLY, OBJ, GLB, ...) -> a validated ``trimesh.Trimesh``, moved into the
  scene frame when ``to_input`` is given. Bad files give one-line :class:`InputError` s naming the file
  (missing, a folder, unreadable or not a mesh, no triangles, non-finite vertices, faces pointing at
  vertices that do not exist).
* :func:`write_mesh`: a scene-frame mesh -> files in the input frame (PLY binary, OBJ, GLB by suffix),
  all written, then renamed (complete or absent).
* :func:`to_input_frame` / :func:`to_scene_frame`: the similarity and its inverse (winding flipped when
  it mirrors, so normals keep pointing at the cameras).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import trimesh
from torch import Tensor

from omnirecon.errors import InputError

MESH_FORMATS = (".ply", ".obj", ".glb")
"""File types :func:`write_mesh` writes (chosen by the suffix)."""
READ_HINT = "pass a mesh written by `omnirecon mesh` (.ply, .obj or .glb)"
"""The fix clause of every read error."""


# ---------------------------------------------------------------------- frames
def to_input_frame(mesh: trimesh.Trimesh, to_input: Tensor | np.ndarray) -> trimesh.Trimesh:
    """``mesh`` moved by the similarity ``to_input # [4, 4]`` (winding flipped if it mirrors); vertex
    colours are kept."""
    T = torch.as_tensor(to_input).double().numpy()
    verts = np.asarray(mesh.vertices, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]
    faces = np.asarray(mesh.faces)
    if np.linalg.det(T[:3, :3]) < 0:
        faces = faces[:, ::-1]
    out = trimesh.Trimesh(verts, faces, process=False)
    if mesh.visual.kind == "vertex":
        out.visual = trimesh.visual.ColorVisuals(out, vertex_colors=np.asarray(mesh.visual.vertex_colors))
    return out


def to_scene_frame(mesh: trimesh.Trimesh, to_input: Tensor | np.ndarray) -> trimesh.Trimesh:
    """``mesh`` (input frame) moved into the scene frame: :func:`to_input_frame` by the inverse."""
    return to_input_frame(mesh, np.linalg.inv(torch.as_tensor(to_input).double().numpy()))


# ---------------------------------------------------------------------- reading
def read_mesh(path: str | Path, to_input: Tensor | np.ndarray | None = None) -> trimesh.Trimesh:
    """The triangle mesh in ``path`` as one ``trimesh.Trimesh``, validated; in the scene frame when the
    scene's ``to_input # [4, 4]`` is given (the file is in the input frame), else as stored."""
    path = Path(path)
    if path.is_dir():
        raise InputError("the mesh path is a folder", path, READ_HINT)
    if not path.is_file():
        raise InputError("mesh file not found", path, READ_HINT)
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as e:  # noqa: BLE001 - trimesh raises many types for bad files
        raise InputError(f"cannot read the mesh ({type(e).__name__})", path, READ_HINT) from e
    if not isinstance(mesh, trimesh.Trimesh):
        raise InputError("the file holds no triangle mesh", path, READ_HINT)
    verts, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    if len(faces) == 0:
        raise InputError("the mesh has no faces", path, "pass a triangle mesh with at least one face")
    if not np.isfinite(verts).all():
        raise InputError(f"the mesh has {int((~np.isfinite(verts).all(1)).sum())} non-finite (NaN/inf) vertices",
                         path, "repair or re-export the mesh")
    if faces.min() < 0 or faces.max() >= len(verts):
        raise InputError("the mesh's faces point at vertices it does not have", path, "repair or re-export the mesh")
    return mesh if to_input is None else to_scene_frame(mesh, to_input)


# ---------------------------------------------------------------------- writing
def check_mesh_paths(paths) -> list[Path]:
    """``paths`` as :class:`Path` objects; :class:`InputError` for an unknown suffix or a folder."""
    out = [Path(p) for p in paths]
    for p in out:
        if p.suffix.lower() not in MESH_FORMATS:
            raise InputError(f"cannot write a mesh as {p.suffix or 'a file without suffix'}", p,
                             f"end --out with one of {', '.join(MESH_FORMATS)}")
        if p.is_dir():
            raise InputError("output path is a folder", p, "pass a file name such as mesh.ply")
    return out


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """The sRGB transfer function inverted (IEC 61966-2-1), ``c`` in [0, 1]."""
    c = np.asarray(c, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(c: np.ndarray) -> np.ndarray:
    """The sRGB transfer function (IEC 61966-2-1), ``c`` in [0, 1]."""
    c = np.asarray(c, dtype=np.float64)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.clip(c, 0.0031308, None) ** (1 / 2.4) - 0.055)


def gltf_mesh(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """``mesh`` as glTF wants it: vertex colours (sRGB bytes, as in our images and PLY files) converted
    to *linear* RGB, since glTF defines ``COLOR_0`` as linear and viewers encode it to sRGB for display
    (sRGB bytes stored as-is show washed out). 8-bit linear is coarse in the shadows: sRGB values
    0-0.1 get only 4 codes (0-3)."""
    if mesh.visual.kind != "vertex":
        return mesh
    rgba = np.asarray(mesh.visual.vertex_colors)
    lin = np.round(srgb_to_linear(rgba[:, :3] / 255.0) * 255).astype(np.uint8)
    out = mesh.copy()
    out.visual = trimesh.visual.ColorVisuals(out, vertex_colors=np.concatenate([lin, rgba[:, 3:]], 1))
    return out


def write_mesh(mesh: trimesh.Trimesh, paths, to_input: Tensor | np.ndarray | None = None,
               extra: dict | None = None) -> list[Path]:
    """Write ``mesh`` to every path (PLY binary, OBJ or GLB by suffix), atomically: moved into the input
    frame first when the scene's ``to_input`` is given (``mesh`` is then in the scene frame). Vertex
    colours are sRGB bytes in PLY and OBJ and linear in GLB (:func:`gltf_mesh`). ``extra``:
    ``{path: write(tmp_path)}``, files of the same set (metrics, preview) written with the meshes and
    renamed with them."""
    from omnirecon.outputs import atomic_files  # all written, then renamed: complete or absent

    written = check_mesh_paths(paths)
    extra = extra or {}
    if to_input is not None:
        mesh = to_input_frame(mesh, to_input)
    with atomic_files([*written, *extra]) as tmps:
        for (_, write), tmp in zip(extra.items(), tmps[len(written):]):
            write(Path(tmp))
        for p, tmp in zip(written, tmps):
            kind = p.suffix.lower().lstrip(".")
            m = gltf_mesh(mesh) if kind == "glb" else mesh
            data = m.export(file_type=kind, **({"include_normals": False} if kind == "obj" else {}))
            Path(tmp).write_bytes(data if isinstance(data, bytes) else data.encode())
    return written
