"""Property-based fuzzing (hypothesis) of every scene reader and of checkpoint loading: whatever the bytes,
reading either succeeds or raises :class:`InputError` (one line); any other exception is a failure.

Targets: Blender ``transforms_train.json``, instant-ngp ``transforms.json``, LLFF ``poses_bounds.npy``,
NeuS ``cameras_sphere.npz``, DTU-MVSNet ``cams/*_cam.txt``, COLMAP text and binary models, a checkpoint's
``meta.json`` and ``model.safetensors``. Each case mutates one valid file (random truncation, byte
flips and insertions, and format-aware edits: NaN/Inf, wrong shapes and types, missing keys, huge
counts, path tricks such as ``../outside``, absolute paths and NUL bytes), reads the scene or
checkpoint, and restores the file.

``OMNIRECON_FUZZ_EXAMPLES`` sets the cases per target (default 40: about 360 in all, a few seconds);
``OMNIRECON_FUZZ_EXAMPLES=10000`` is the long run. The counts of cases, InputErrors, successful reads
and failures are printed per target (``pytest -s``) and, with ``OMNIRECON_FUZZ_REPORT=path.json``,
written as JSON (bench/reliability.py uses that).
"""

from __future__ import annotations

import io
import json
import math
import os
import shutil
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
import torch

from omnirecon.data import load_scene
from omnirecon.errors import InputError
from tests.data.test_bad_input import blender_scene, colmap_scene, llff_scene, ring_gl, tiny_image

hypothesis = pytest.importorskip("hypothesis", reason="hypothesis is in the test extra: pip install -e '.[test]'")
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

EXAMPLES = int(os.environ.get("OMNIRECON_FUZZ_EXAMPLES", "40"))
LONG = EXAMPLES > 200
SETTINGS = settings(max_examples=EXAMPLES, deadline=None, database=None, derandomize=not LONG, print_blob=False,
                    suppress_health_check=list(HealthCheck))
TINY_GPNR = {"num_samples": 8, "dim": 32, "mlp_dim": 32, "heads": 1, "layers": [1, 1, 1], "point_freqs": 4}


@dataclass
class Tally:
    cases: int = 0
    input_errors: int = 0
    loaded: int = 0
    failures: list[str] = field(default_factory=list)
    gaps: dict[str, int] = field(default_factory=dict)
    """InputError messages without a file or without a fix clause (message -> count)."""


TALLIES: dict[str, Tally] = {}


def run_case(target: str, load, what: str) -> None:
    """Call ``load()``; count an InputError (one line) or a success; record anything else as a failure."""
    t = TALLIES.setdefault(target, Tally())
    t.cases += 1
    try:
        load()
        t.loaded += 1
    except InputError as e:
        t.input_errors += 1
        if "\n" in str(e):
            t.failures.append(f"multi-line InputError after {what}: {str(e)[:200]!r}")
        if e.path is None or not e.fix:
            key = e.what[:60]
            t.gaps[key] = t.gaps.get(key, 0) + 1
    except Exception as e:  # the point of the test: any other exception is a failure
        t.failures.append(f"{type(e).__name__} after {what}: {str(e)[:200]}")


def finish(target: str) -> None:
    t = TALLIES.get(target, Tally())
    print(f"fuzz {target}: {t.cases} cases, {t.input_errors} InputError, {t.loaded} read fine, "
          f"{len(t.failures)} failures, {sum(t.gaps.values())} messages without a file or fix "
          f"{sorted(t.gaps.items(), key=lambda kv: -kv[1])[:8]}")
    report = os.environ.get("OMNIRECON_FUZZ_REPORT")
    if report:
        path = Path(report)
        data = json.loads(path.read_text()) if path.is_file() else {}
        data[target] = {"cases": t.cases, "input_errors": t.input_errors, "loaded": t.loaded,
                        "failures": len(t.failures), "examples": t.failures[:5],
                        "without_file_or_fix": sum(t.gaps.values())}
        path.write_text(json.dumps(data, indent=1))
    assert not t.failures, "\n".join(t.failures[:10])
    assert not t.gaps, f"InputErrors without a file or a fix clause: {t.gaps}"


# ---------------------------------------------------------------------- mutations
NASTY_NUMBERS = [math.nan, math.inf, -math.inf, 0, -1, 0.0, -0.0, 1e-300, 1e300, 10**30, -(10**30), 2**63, 1e-9]
NASTY_STRINGS = ["", "five", "../outside", "../../etc/passwd", "/etc/passwd", "a\x00b", "~/x", "C:\\x.png",
                 "train/../../x", "./train/r_0", "x" * 300, "\u00e9\u0301", "nan", "inf", "1e400"]
nasty_leaf = st.one_of(st.sampled_from(NASTY_NUMBERS), st.sampled_from(NASTY_STRINGS), st.none(), st.booleans(),
                       st.integers(-(10**6), 10**6), st.floats(allow_nan=True, allow_infinity=True))
nasty_value = st.recursive(nasty_leaf, lambda kids: st.one_of(st.lists(kids, max_size=5),
                                                               st.dictionaries(st.text(max_size=5), kids, max_size=3)),
                           max_leaves=12)


@st.composite
def byte_mutation(draw, data: bytes):
    """Truncation, byte flips or an inserted chunk of ``data``; returns ``(bytes, description)``."""
    kind = draw(st.sampled_from(["truncate", "flip", "insert", "zero_tail"]))
    n = len(data)
    if kind == "truncate":
        k = draw(st.integers(0, max(0, n - 1)))
        return data[:k], f"truncate to {k} of {n} bytes"
    if kind == "flip":
        b = bytearray(data)
        flips = draw(st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, 255)), min_size=1, max_size=8))
        for i, v in flips:
            b[i] = v
        return bytes(b), f"set bytes {flips}"
    if kind == "insert":
        i = draw(st.integers(0, n))
        chunk = draw(st.binary(min_size=1, max_size=16))
        return data[:i] + chunk + data[i:], f"insert {chunk!r} at {i}"
    k = draw(st.integers(0, n - 1))
    return data[:k] + b"\x00" * (n - k), f"zero from byte {k}"


def _paths(obj, prefix=()):
    """Every path into a JSON tree (dict keys and list indices)."""
    yield prefix
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _paths(v, (*prefix, k))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _paths(v, (*prefix, i))


@st.composite
def json_mutation(draw, text: str):
    """Replace or delete one node of the JSON document ``text`` (or mutate its bytes)."""
    if draw(st.integers(0, 3)) == 0:
        data, what = draw(byte_mutation(text.encode()))
        return data, what
    obj = json.loads(text)
    paths = [p for p in _paths(obj) if p]
    path = draw(st.sampled_from(paths))
    parent = obj
    for k in path[:-1]:
        parent = parent[k]
    if isinstance(parent, dict) and draw(st.booleans()):
        del parent[path[-1]]
        what = f"delete {path}"
    else:
        value = draw(nasty_value)
        parent[path[-1]] = value
        what = f"set {path} = {json.dumps(value)[:60]}"
    return json.dumps(obj).encode(), what


@st.composite
def array_mutation(draw, arr: np.ndarray):
    """NaN/Inf/extreme entries, a different shape or dtype, or an empty array; saved as .npy bytes."""
    kind = draw(st.sampled_from(["values", "shape", "dtype", "empty", "bytes"]))
    a = arr.copy()
    if kind == "values":
        flat = a.reshape(-1)
        for i, v in draw(st.lists(st.tuples(st.integers(0, flat.size - 1),
                                            st.sampled_from([math.nan, math.inf, -math.inf, 0.0, -1.0, 1e300, 1e-300])),
                                  min_size=1, max_size=6)):
            flat[i] = v
        what = "set entries"
    elif kind == "shape":
        shape = tuple(draw(st.lists(st.integers(0, 20), min_size=0, max_size=3)))
        size = int(np.prod(shape)) if shape else 1
        a = np.resize(a.reshape(-1), size).reshape(shape)
        what = f"shape {shape}"
    elif kind == "dtype":
        dt = draw(st.sampled_from(["float16", "int8", "uint8", "bool", "complex64", "<U3", "int64"]))
        a = a.astype(dt)
        what = f"dtype {dt}"
    elif kind == "empty":
        a = np.zeros((0, a.shape[1] if a.ndim == 2 else 0))
        what = "empty"
    else:
        buf = io.BytesIO()
        np.save(buf, a)
        return draw(byte_mutation(buf.getvalue()))
    buf = io.BytesIO()
    np.save(buf, a)
    return buf.getvalue(), what


@st.composite
def text_mutation(draw, text: str):
    """Replace, delete or duplicate tokens and lines of a whitespace-separated text file (or its bytes)."""
    if draw(st.integers(0, 3)) == 0:
        return draw(byte_mutation(text.encode()))
    lines = text.split("\n")
    kind = draw(st.sampled_from(["token", "delete_line", "duplicate_line", "truncate_line"]))
    i = draw(st.integers(0, len(lines) - 1))
    if kind == "token" and lines[i].split():
        tokens = lines[i].split()
        j = draw(st.integers(0, len(tokens) - 1))
        tokens[j] = draw(st.sampled_from(["nan", "inf", "-inf", "abc", "1e400", "-1", "0", "99999999999999999999",
                                          "../outside.png", "/etc/passwd", "", "1.5", "-0"]))
        lines[i] = " ".join(tokens)
        what = f"line {i} token {j} -> {tokens[j]!r}"
    elif kind == "delete_line":
        del lines[i]
        what = f"delete line {i}"
    elif kind == "duplicate_line":
        lines.insert(i, lines[i])
        what = f"duplicate line {i}"
    else:
        lines[i] = lines[i][: draw(st.integers(0, len(lines[i])))]
        what = f"truncate line {i}"
    return "\n".join(lines).encode(), what


@st.composite
def npz_mutation(draw, arrays: dict[str, np.ndarray]):
    """Drop a key, change one array (values, shape, dtype), add a non-array; saved as .npz bytes."""
    a = {k: v.copy() for k, v in arrays.items()}
    key = draw(st.sampled_from(sorted(a)))
    kind = draw(st.sampled_from(["drop", "values", "shape", "dtype", "string", "bytes"]))
    if kind == "drop":
        del a[key]
    elif kind == "values":
        a[key].reshape(-1)[draw(st.integers(0, a[key].size - 1))] = draw(st.sampled_from([math.nan, math.inf, 0.0, 1e300]))
    elif kind == "shape":
        shape = tuple(draw(st.lists(st.integers(0, 5), max_size=3)))
        a[key] = np.resize(a[key].reshape(-1), int(np.prod(shape)) if shape else 1).reshape(shape)
    elif kind == "dtype":
        a[key] = a[key].astype(draw(st.sampled_from(["int8", "bool", "complex64", "<U2", "float16"])))
    elif kind == "string":
        a[key] = np.array("not a matrix")
    buf = io.BytesIO()
    np.savez(buf, **a)
    if kind == "bytes":
        return draw(byte_mutation(buf.getvalue()))
    return buf.getvalue(), f"{kind} {key}"


# ---------------------------------------------------------------------- targets
@pytest.fixture(scope="module")
def targets(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("fuzz")
    tiny_image(root / "outside.png")  # what a "../outside" path would reach
    t = {"blender": blender_scene(root / "blender")}
    ngp = root / "ngp"
    for i in range(3):
        tiny_image(ngp / "images" / f"{i}.png", seed=i)
    (ngp / "transforms.json").write_text(json.dumps({
        "fl_x": 10, "fl_y": 10, "cx": 4, "cy": 4, "w": 8, "h": 8, "aabb_scale": 4,
        "frames": [{"file_path": f"images/{i}.png", "transform_matrix": m} for i, m in enumerate(ring_gl().tolist())]}))
    t["ngp"] = ngp
    t["llff"] = llff_scene(root / "llff")
    neus = root / "neus"
    P = np.eye(4)
    P[:3, :3] = [[10, 0, 4], [0, 10, 4], [0, 0, 1]]
    c2w = ring_gl().numpy() @ np.diag([1.0, -1, -1, 1])  # OpenCV camera-to-world
    for i in range(3):
        tiny_image(neus / "image" / f"{i:06d}.png", seed=i)
    np.savez(neus / "cameras_sphere.npz", **{f"world_mat_{i}": P @ np.linalg.inv(c2w[i]) for i in range(3)},
             **{f"scale_mat_{i}": np.diag([1.5, 1.5, 1.5, 1.0]) for i in range(3)})
    t["dtu_neus"] = neus
    mvs = root / "mvsnet"
    for i in range(3):
        tiny_image(mvs / "images" / f"{i:08d}.png", seed=i)
        (mvs / "cams").mkdir(parents=True, exist_ok=True)
        w2c = np.linalg.inv(c2w[i])
        (mvs / "cams" / f"{i:08d}_cam.txt").write_text(
            "extrinsic\n" + "\n".join(" ".join(f"{v:.6f}" for v in row) for row in w2c)
            + "\n\nintrinsic\n10 0 4\n0 10 4\n0 0 1\n\n2.0 0.05\n")
    t["dtu_mvsnet"] = mvs
    t["colmap_text"] = colmap_scene(root / "colmap_text")
    t["colmap_binary"] = colmap_scene(root / "colmap_binary", ext=".bin")
    from omnirecon.engine.checkpoint import save_checkpoint
    from omnirecon.models.registry import build_model

    torch.manual_seed(0)
    save_checkpoint(root / "ckpt", build_model("gpnr-tiny", TINY_GPNR), "gpnr-tiny")
    t["checkpoint"] = root / "ckpt"
    for name in ("blender", "ngp", "llff", "dtu_neus", "dtu_mvsnet", "colmap_text", "colmap_binary"):
        load_scene(t[name])  # every seed scene is valid: failures come from the mutation
    return t


def _swap(file: Path, data: bytes, load, target: str, what: str) -> None:
    original = file.read_bytes()
    try:
        file.write_bytes(data)
        run_case(target, load, f"{file.name}: {what}")
    finally:
        file.write_bytes(original)


def _fuzz_file(target: str, folder: Path, file: Path, strategy, load=None) -> None:
    load = load or (lambda: load_scene(folder))

    @SETTINGS
    @given(mutation=strategy)
    def case(mutation):
        data, what = mutation
        _swap(file, data, load, target, what)

    case()
    finish(target)


def test_fuzz_blender(targets):
    f = targets["blender"] / "transforms_train.json"
    _fuzz_file("blender", targets["blender"], f, json_mutation(f.read_text()))


def test_fuzz_ngp(targets):
    f = targets["ngp"] / "transforms.json"
    _fuzz_file("ngp", targets["ngp"], f, json_mutation(f.read_text()))


def test_fuzz_llff(targets):
    f = targets["llff"] / "poses_bounds.npy"
    _fuzz_file("llff", targets["llff"], f, array_mutation(np.load(f)))


def test_fuzz_dtu_neus(targets):
    f = targets["dtu_neus"] / "cameras_sphere.npz"
    with np.load(f) as z:
        arrays = {k: z[k] for k in z.files}
    _fuzz_file("dtu_neus", targets["dtu_neus"], f, npz_mutation(arrays))


def test_fuzz_dtu_mvsnet(targets):
    f = targets["dtu_mvsnet"] / "cams" / "00000001_cam.txt"
    _fuzz_file("dtu_mvsnet", targets["dtu_mvsnet"], f, text_mutation(f.read_text()))


def _fuzz_model(target: str, folder: Path, names: list[str], strategy_of) -> None:
    files = {n: folder / "sparse" / "0" / n for n in names}
    strategies = {n: strategy_of(f.read_bytes()) for n, f in files.items()}

    @SETTINGS
    @given(name=st.sampled_from(names), data=st.data())
    def case(name, data):
        mutated, what = data.draw(strategies[name])
        _swap(files[name], mutated, lambda: load_scene(folder), target, what)

    case()
    finish(target)


def test_fuzz_colmap_text(targets):
    _fuzz_model("colmap_text", targets["colmap_text"], ["cameras.txt", "images.txt", "points3D.txt"],
                lambda b: text_mutation(b.decode()))


@st.composite
def count_mutation(draw, data: bytes):
    """Byte mutations, or a huge/negative 8-byte count or 4-byte id written at a random aligned offset."""
    if draw(st.booleans()):
        return draw(byte_mutation(data))
    off = draw(st.integers(0, max(0, len(data) - 8)))
    value = draw(st.sampled_from([2**63 - 1, 2**40, 10**9, 0, 1, 2**32 - 1]))
    b = bytearray(data)
    b[off:off + 8] = struct.pack("<Q", value)
    return bytes(b), f"uint64 {value} at {off}"


def test_fuzz_colmap_binary(targets):
    _fuzz_model("colmap_binary", targets["colmap_binary"], ["cameras.bin", "images.bin", "points3D.bin"],
                count_mutation)


def test_fuzz_checkpoint_meta(targets):
    from omnirecon.engine.checkpoint import load_checkpoint

    folder = targets["checkpoint"]
    f = folder / "meta.json"
    _fuzz_file("checkpoint_meta", folder, f, json_mutation(f.read_text()), lambda: load_checkpoint(folder))


@st.composite
def safetensors_mutation(draw, data: bytes):
    """Byte mutations of the whole file, edits of its JSON header (dtype, shape, offsets), or NaN/Inf written
    into a tensor's data."""
    (n,) = struct.unpack("<Q", data[:8])
    header = json.loads(data[8:8 + n])
    kind = draw(st.sampled_from(["bytes", "header", "nonfinite"]))
    if kind == "bytes":
        return draw(byte_mutation(data))
    key = draw(st.sampled_from(sorted(k for k in header if k != "__metadata__")))
    if kind == "header":
        field_ = draw(st.sampled_from(["dtype", "shape", "data_offsets"]))
        header[key][field_] = draw(st.one_of(nasty_value, st.sampled_from(["F16", "I64", "BOOL", "F64", "U8"]),
                                             st.lists(st.integers(-2, 10**6), max_size=4)))
        h = json.dumps(header).encode()
        return struct.pack("<Q", len(h)) + h + data[8 + n:], f"header {key}.{field_}"
    start, end = header[key]["data_offsets"]
    b = bytearray(data)
    pos = 8 + n + start + 4 * draw(st.integers(0, max(0, (end - start) // 4 - 1)))
    b[pos:pos + 4] = struct.pack("<f", draw(st.sampled_from([math.nan, math.inf, -math.inf])))
    return bytes(b), f"non-finite value in {key}"


def test_fuzz_checkpoint_weights(targets):
    from omnirecon.engine.checkpoint import load_checkpoint

    folder = targets["checkpoint"]
    f = folder / "model.safetensors"
    _fuzz_file("checkpoint_weights", folder, f, safetensors_mutation(f.read_bytes()), lambda: load_checkpoint(folder))


def test_fuzz_seed_files_are_restored(targets):
    """The fuzzed files were restored after every case (so each case mutated one valid file)."""
    for name in ("blender", "ngp", "llff", "dtu_neus", "dtu_mvsnet", "colmap_text", "colmap_binary"):
        load_scene(targets[name])
    shutil.rmtree(targets["checkpoint"].parent / "nothing", ignore_errors=True)


# Cases the long runs found (each raised something other than InputError before its fix), kept as examples.
REGRESSIONS = [
    ("dtu_neus", "cameras_sphere.npz", [(411, 121), (288, 142), (158, 14), (1526, 166), (653, 56), (1932, 141),
                                        (2046, 168), (156, 238)]),  # zipfile NotImplementedError (zip version)
    ("dtu_neus", "cameras_sphere.npz", [(1993, 84), (617, 117), (255, 179), (838, 227), (582, 186)]),
]


@pytest.mark.parametrize("target, name, flips", REGRESSIONS)
def test_fuzz_regressions(targets, target, name, flips):
    f = targets[target] / name
    b = bytearray(f.read_bytes())
    for i, v in flips:
        if i < len(b):
            b[i] = v
    _swap(f, bytes(b), lambda: load_scene(targets[target]), f"regression_{target}", f"flips {flips}")
    t = TALLIES[f"regression_{target}"]
    assert not t.failures, t.failures


def test_colmap_colour_out_of_range_is_an_input_error(targets, tmp_path):
    """points3D.txt with a colour of -1 (found by the fuzzer: OverflowError in NumPy before the fix)."""
    f = targets["colmap_text"] / "sparse" / "0" / "points3D.txt"
    lines = f.read_text().split("\n")
    i = next(k for k, ln in enumerate(lines) if ln and not ln.startswith("#"))
    tok = lines[i].split()
    tok[4] = "-1"
    lines[i] = " ".join(tok)
    _swap(f, "\n".join(lines).encode(), lambda: load_scene(targets["colmap_text"]), "regression_colmap", "rgb -1")
    assert not TALLIES["regression_colmap"].failures and TALLIES["regression_colmap"].input_errors == 1
