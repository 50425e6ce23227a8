"""Allocations an option sizes are checked against the memory the machine has (omnirecon.preflight.check_memory),
not against a fixed count: past it, one line naming the option and a value that fits, exit 2, nothing written
(issue 46 item 4: ``finetune --val-every 1e-9`` and ``mesh --voxel`` far below the scene's detail)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from omnirecon.errors import InputError
from omnirecon.preflight import available_memory, check_memory
from tests.data.test_bad_input import blender_scene

CKPT = Path(__file__).resolve().parents[2] / "checkpoints" / "omnirecon-tiny"


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return blender_scene(tmp_path_factory.mktemp("memory") / "scene")


def test_available_memory_is_what_proc_meminfo_says_at_most():
    avail = available_memory()
    meminfo = {ln.split(":")[0]: int(ln.split()[1]) * 1024 for ln in Path("/proc/meminfo").read_text().splitlines()}
    assert 0 < avail <= meminfo["MemTotal"]


def test_check_memory_names_the_option_and_a_value_that_fits():
    check_memory(1024, "--x", lambda share: "unused")  # a kilobyte fits anywhere
    with pytest.raises(InputError) as e:
        check_memory(2.0 ** 60, "--x", lambda share: f"{share:.3g}")
    share = float(re.search(r"use --x (\S+)", str(e.value)).group(1))
    assert share * 2.0 ** 60 <= available_memory() and "--x needs about" in str(e.value)


def test_mesh_refuses_a_voxel_grid_beyond_memory(scene, tmp_path, run_cli):
    out = tmp_path / "m.ply"
    code, _, err = run_cli(["mesh", "--scene", scene, "--model", "floor", "--out", out, "--voxel", "0.00001",
                            "--threads", "1", "--resolution", "16"])
    assert code == 2 and "--voxel needs about" in err and "(fix: use --voxel " in err, err
    assert len(err.strip().splitlines()) == 1 and list(tmp_path.iterdir()) == []


def test_finetune_refuses_validation_times_beyond_memory(scene, tmp_path, run_cli):
    out = tmp_path / "ft"
    code, _, err = run_cli(["finetune", "--scene", scene, "--ckpt", CKPT, "--out", out, "--val-every", "1e-9",
                            "--threads", "1"])
    assert code == 2 and "--val-every needs about" in err and "(fix: use --val-every " in err, err
    assert len(err.strip().splitlines()) == 1 and list(tmp_path.iterdir()) == []


def test_every_reader_of_memory_sees_the_address_space_limit():
    """Under ``ulimit -v`` the chunk default, the option checks and ``available_memory`` read one number (they read
    /proc/meminfo and psutil apart before, and the chunk default ignored the limit)."""
    import subprocess
    import sys

    code = ("import resource; resource.setrlimit(resource.RLIMIT_AS, (6 * 2**30, resource.RLIM_INFINITY))\n"
            "from omnirecon import chunk, memory, preflight\n"
            "total, avail = memory.memory_bytes()\n"
            "assert avail == preflight.available_memory() < 6 * 2**30 <= total, (avail, total)\n"
            "assert chunk.default_chunk() == chunk.default_chunk(available=avail)\n"
            "print(avail)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert 0 < int(out.stdout) < 6 * 2**30
