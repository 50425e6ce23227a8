"""COLMAP sparse models: parsers and writers for the text and binary formats.

Formats as documented by COLMAP (``cameras``, ``images``, ``points3D`` with ``.txt`` or ``.bin``).
Poses are world-to-camera ``(qvec = (w, x, y, z), tvec)`` in the OpenCV camera frame; COLMAP puts
pixel centres at +0.5, like this library.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from omnirecon.errors import InputError

# id: (name, number of params)
MODELS = {
    0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
    4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
}
MODEL_IDS = {name: (i, n) for i, (name, n) in MODELS.items()}


@dataclass
class Camera:
    id: int
    model: str
    width: int
    height: int
    params: np.ndarray  # [P] float64


@dataclass
class Image:
    id: int
    qvec: np.ndarray  # [4] (w, x, y, z), world-to-camera
    tvec: np.ndarray  # [3]
    camera_id: int
    name: str
    xys: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # [K, 2]
    point3D_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # [K], -1 = none


@dataclass
class Points:
    ids: np.ndarray  # [P] int64
    xyz: np.ndarray  # [P, 3] float64
    rgb: np.ndarray  # [P, 3] uint8
    error: np.ndarray  # [P] float64
    tracks: list  # per point [T, 2] int (image_id, point2D_idx)


@dataclass
class Model:
    cameras: dict[int, Camera]
    images: list[Image]
    points: Points
    folder: Path
    ext: str  # ".bin" or ".txt"


def qvec_to_rotmat(q: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(w, x, y, z)`` (normalised here) -> rotation matrix. ``# [3, 3]``"""
    w, x, y, z = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def rotmat_to_qvec(R: np.ndarray) -> np.ndarray:
    """Rotation matrix -> unit quaternion ``(w, x, y, z)`` with ``w >= 0``."""
    R = np.asarray(R, np.float64)
    K = np.array([
        [R[0, 0] - R[1, 1] - R[2, 2], 0, 0, 0],
        [R[1, 0] + R[0, 1], R[1, 1] - R[0, 0] - R[2, 2], 0, 0],
        [R[2, 0] + R[0, 2], R[2, 1] + R[1, 2], R[2, 2] - R[0, 0] - R[1, 1], 0],
        [R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1], R[0, 0] + R[1, 1] + R[2, 2]],
    ]) / 3.0
    vals, vecs = np.linalg.eigh(K)
    q = vecs[[3, 0, 1, 2], np.argmax(vals)]
    return -q if q[0] < 0 else q


def find_model(path: Path) -> tuple[Path, str] | None:
    """``(folder, ext)`` of the sparse model under ``path``: ``sparse/0``, ``sparse`` or ``path`` itself."""
    for folder in (path / "sparse" / "0", path / "sparse", path):
        for ext in (".bin", ".txt"):
            if (folder / f"cameras{ext}").is_file() and (folder / f"images{ext}").is_file():
                return folder, ext
    return None


def read_model(folder: Path, ext: str) -> Model:
    """Parse ``cameras``, ``images`` and (when present) ``points3D`` in ``folder``."""
    reader = _BinReader if ext == ".bin" else _TextReader
    pts_file = folder / f"points3D{ext}"
    points = reader.points(pts_file) if pts_file.is_file() else Points(
        np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0), [])
    return Model(reader.cameras(folder / f"cameras{ext}"), reader.images(folder / f"images{ext}"), points, folder, ext)


def _malformed(path: Path, err: Exception) -> InputError:
    return InputError(f"malformed COLMAP file ({type(err).__name__}: {err})", path,
                      "re-export the model with colmap model_converter")


def _model_name(path: Path, model_id: int) -> tuple[str, int]:
    if model_id not in MODELS:
        raise InputError(f"unknown COLMAP camera model id {model_id}", path,
                         "re-export the model with a current COLMAP")
    return MODELS[model_id]


class _TextReader:
    @staticmethod
    def _lines(path: Path) -> list[str]:
        try:
            return [ln.rstrip("\r\n") for ln in path.read_text().splitlines() if not ln.lstrip().startswith("#")]
        except (UnicodeDecodeError, OSError) as e:
            raise _malformed(path, e) from e

    @classmethod
    def cameras(cls, path: Path) -> dict[int, Camera]:
        out = {}
        for ln in cls._lines(path):
            if not ln.strip():
                continue
            tok = ln.split()
            try:
                name = tok[1]
                if name not in MODEL_IDS:
                    raise InputError(f"unknown COLMAP camera model {name}", path, "re-export with a current COLMAP")
                params = np.array(tok[4:], np.float64)
                if len(params) != MODEL_IDS[name][1]:
                    raise ValueError(f"{name} takes {MODEL_IDS[name][1]} parameters, got {len(params)}")
                if not (0 < int(tok[2]) < 2**31 and 0 < int(tok[3]) < 2**31):
                    raise ValueError(f"image size {tok[2]}x{tok[3]} is not positive or too large")
                out[int(tok[0])] = Camera(int(tok[0]), name, int(tok[2]), int(tok[3]), params)
            except (ValueError, IndexError, OverflowError) as e:
                raise _malformed(path, e) from e
        return out

    @classmethod
    def images(cls, path: Path) -> list[Image]:
        lines, out, i = cls._lines(path), [], 0
        try:
            while i < len(lines):
                if not lines[i].strip():
                    i += 1
                    continue
                tok = lines[i].split(maxsplit=9)
                pts = np.array(lines[i + 1].split() if i + 1 < len(lines) else [], np.float64).reshape(-1, 3)
                out.append(Image(int(tok[0]), np.array(tok[1:5], np.float64), np.array(tok[5:8], np.float64),
                                 int(tok[8]), tok[9], pts[:, :2], pts[:, 2].astype(np.int64)))
                i += 2
        except (ValueError, IndexError, OverflowError) as e:
            raise _malformed(path, e) from e
        return out

    @classmethod
    def points(cls, path: Path) -> Points:
        ids, xyz, rgb, err, tracks = [], [], [], [], []
        try:
            for ln in cls._lines(path):
                tok = ln.split()
                if not tok:
                    continue
                ids.append(int(tok[0]))
                xyz.append([float(t) for t in tok[1:4]])
                rgb.append([int(t) for t in tok[4:7]])
                err.append(float(tok[7]))
                tracks.append(np.array(tok[8:], np.int64).reshape(-1, 2))
            return Points(np.array(ids, np.int64), np.array(xyz, np.float64).reshape(-1, 3),
                          np.array(rgb, np.uint8).reshape(-1, 3), np.array(err, np.float64), tracks)
        except (ValueError, IndexError, OverflowError) as e:  # also ids/colours out of range
            raise _malformed(path, e) from e


class _BinReader:
    @staticmethod
    def _data(path: Path) -> bytes:
        try:
            return path.read_bytes()
        except OSError as e:
            raise _malformed(path, e) from e

    @classmethod
    def cameras(cls, path: Path) -> dict[int, Camera]:
        data, out = cls._data(path), {}
        try:
            (n,), pos = struct.unpack_from("<Q", data, 0), 8
            for _ in range(n):
                cid, mid, w, h = struct.unpack_from("<iiQQ", data, pos)
                name, k = _model_name(path, mid)
                if not (0 < w < 2**31 and 0 < h < 2**31):
                    raise ValueError(f"image size {w}x{h} is not positive or too large")
                params = np.frombuffer(data, "<f8", k, pos + 24).copy()
                out[cid] = Camera(cid, name, w, h, params)
                pos += 24 + 8 * k
        except (struct.error, ValueError, OverflowError) as e:
            raise _malformed(path, e) from e
        return out

    @classmethod
    def images(cls, path: Path) -> list[Image]:
        data, out = cls._data(path), []
        try:
            (n,), pos = struct.unpack_from("<Q", data, 0), 8
            for _ in range(n):
                vals = struct.unpack_from("<i7di", data, pos)
                pos += 64
                end = data.index(b"\0", pos)
                name = data[pos:end].decode("utf-8")
                (k,) = struct.unpack_from("<Q", data, end + 1)
                pos = end + 9
                pts = np.frombuffer(data, np.dtype([("x", "<f8"), ("y", "<f8"), ("id", "<i8")]), k, pos)
                pos += 24 * k
                out.append(Image(vals[0], np.array(vals[1:5]), np.array(vals[5:8]), vals[8], name,
                                 np.stack([pts["x"], pts["y"]], -1), pts["id"].astype(np.int64)))
        except (struct.error, ValueError, OverflowError, UnicodeDecodeError) as e:
            raise _malformed(path, e) from e
        return out

    @classmethod
    def points(cls, path: Path) -> Points:
        data = cls._data(path)
        ids, xyz, rgb, err, tracks = [], [], [], [], []
        try:
            (n,), pos = struct.unpack_from("<Q", data, 0), 8
            for _ in range(n):
                v = struct.unpack_from("<Q3d3BdQ", data, pos)
                pos += 51
                ids.append(v[0])
                xyz.append(v[1:4])
                rgb.append(v[4:7])
                err.append(v[7])
                tracks.append(np.frombuffer(data, "<i4", 2 * v[8], pos).reshape(-1, 2).astype(np.int64))
                pos += 8 * v[8]
            return Points(np.array(ids, np.int64), np.array(xyz, np.float64).reshape(-1, 3),
                          np.array(rgb, np.uint8).reshape(-1, 3), np.array(err, np.float64), tracks)
        except (struct.error, ValueError, OverflowError) as e:  # also ids/colours out of range
            raise _malformed(path, e) from e


def write_model(model: Model, folder: Path, ext: str) -> None:
    """Write ``model`` to ``folder`` as ``.txt`` or ``.bin`` files."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    (_write_text if ext == ".txt" else _write_binary)(model, folder)


def _write_text(m: Model, folder: Path) -> None:
    g = lambda a: " ".join(f"{v:.17g}" for v in np.asarray(a).ravel())  # noqa: E731
    (folder / "cameras.txt").write_text("# Camera list\n" + "".join(
        f"{c.id} {c.model} {c.width} {c.height} {g(c.params)}\n" for c in m.cameras.values()))
    lines = ["# Image list"]
    for im in m.images:
        lines.append(f"{im.id} {g(im.qvec)} {g(im.tvec)} {im.camera_id} {im.name}")
        lines.append(" ".join(f"{x:.17g} {y:.17g} {int(p)}" for (x, y), p in zip(im.xys, im.point3D_ids)))
    (folder / "images.txt").write_text("\n".join(lines) + "\n")
    p = m.points
    (folder / "points3D.txt").write_text("# 3D point list\n" + "".join(
        f"{p.ids[i]} {g(p.xyz[i])} {' '.join(map(str, p.rgb[i]))} {p.error[i]:.17g} "
        f"{' '.join(map(str, np.asarray(p.tracks[i]).ravel()))}\n" for i in range(len(p.ids))))


def _write_binary(m: Model, folder: Path) -> None:
    out = [struct.pack("<Q", len(m.cameras))]
    for c in m.cameras.values():
        mid, k = MODEL_IDS[c.model]
        out.append(struct.pack("<iiQQ", c.id, mid, c.width, c.height) + np.asarray(c.params, "<f8")[:k].tobytes())
    (folder / "cameras.bin").write_bytes(b"".join(out))
    out = [struct.pack("<Q", len(m.images))]
    for im in m.images:
        pts = np.zeros(len(im.point3D_ids), np.dtype([("x", "<f8"), ("y", "<f8"), ("id", "<i8")]))
        pts["x"], pts["y"], pts["id"] = im.xys[:, 0], im.xys[:, 1], im.point3D_ids
        out.append(struct.pack("<i7di", im.id, *im.qvec, *im.tvec, im.camera_id) + im.name.encode() + b"\0"
                   + struct.pack("<Q", len(pts)) + pts.tobytes())
    (folder / "images.bin").write_bytes(b"".join(out))
    p = m.points
    out = [struct.pack("<Q", len(p.ids))]
    for i in range(len(p.ids)):
        t = np.asarray(p.tracks[i], "<i4").reshape(-1, 2)
        out.append(struct.pack("<Q3d3BdQ", p.ids[i], *p.xyz[i], *p.rgb[i], p.error[i], len(t)) + t.tobytes())
    (folder / "points3D.bin").write_bytes(b"".join(out))
