"""The mesh-file boundary: round trip through the input frame, one-line errors for bad files."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from omnirecon.errors import InputError
from omnirecon.mesh.files import read_mesh, to_scene_frame, write_mesh


def similarity() -> torch.Tensor:
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = 2.5 * torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    T[:3, 3] = torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
    return T


@pytest.mark.parametrize("suffix", ["ply", "obj", "glb"])
def test_round_trip_through_the_input_frame(tmp_path, suffix):
    sphere = trimesh.creation.icosphere(2)
    T = similarity()
    (path,) = write_mesh(sphere, [tmp_path / f"m.{suffix}"], T)
    stored = trimesh.load(path, force="mesh", process=False)
    assert np.allclose(stored.bounds.mean(0), [1.0, -2.0, 0.5], atol=1e-5)  # the file is in the input frame
    back = read_mesh(path, T)  # and comes back into the scene frame
    assert len(back.faces) == len(sphere.faces)
    assert np.allclose(np.sort(back.vertices, 0), np.sort(sphere.vertices, 0), atol=1e-5)
    assert back.volume == pytest.approx(sphere.volume, rel=1e-4)  # winding kept outward
    assert np.allclose(to_scene_frame(stored, T).vertices, back.vertices)


def test_bad_files_are_one_line_errors(tmp_path):
    text = tmp_path / "notes.ply"
    text.write_text("this is not a mesh\n")
    nan = trimesh.Trimesh(np.array([[0.0, 0, 0], [1, 0, 0], [np.nan, 1, 0]]), np.array([[0, 1, 2]]), process=False)
    nan_path = tmp_path / "nan.ply"
    nan_path.write_bytes(nan.export(file_type="ply"))
    empty_path = tmp_path / "empty.ply"
    empty_path.write_bytes(trimesh.Trimesh(np.zeros((3, 3)), np.zeros((0, 3), dtype=np.int64)).export(file_type="ply"))
    cases = [(tmp_path / "missing.ply", "not found"), (tmp_path, "folder"), (text, "mesh"),
             (nan_path, "non-finite"), (empty_path, "no")]
    for path, words in cases:
        with pytest.raises(InputError) as e:
            read_mesh(path)
        msg = str(e.value)
        assert "\n" not in msg and words in msg and str(path.name) in msg, msg
    with pytest.raises(InputError, match="cannot write a mesh"):
        write_mesh(trimesh.creation.box(), [tmp_path / "m.stl"])
