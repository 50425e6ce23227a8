"""pymeshlab's hole closing in a child process under a CPU-time limit (:func:`omnirecon.mesh.clean.close_holes`).

``meshing_close_holes`` is native code that a Python thread cannot interrupt, and it has run for more than ten
CPU-minutes without finishing on a fused mesh of a procedural scene (seed 900997 with the free-space check on),
where the whole mesh otherwise takes about one. So it runs here, in ``python -m omnirecon.mesh.meshlab_holes IN
OUT SECONDS``: the child caps its own CPU time (``RLIMIT_CPU``: the kernel ends it at the limit whatever the
machine's load), and the parent also stops waiting after a generous wall-clock multiple of it. This module
imports only numpy and pymeshlab (no torch), so the child starts in well under a second.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

WALL_FACTOR = 8.0
"""The parent waits at most this many times the CPU limit in wall seconds (a loaded machine) ..."""
WALL_SLACK = 30.0
"""... plus this many (the child's start)."""


def close_in_child(vertices: np.ndarray, faces: np.ndarray, max_edges: int, cpu_seconds: float,
                   record: dict | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """pymeshlab's non-manifold edge repair and hole closing (holes of at most ``max_edges`` boundary edges)
    of ``vertices # [V, 3]``, ``faces # [F, 3]`` in a child process limited to ``cpu_seconds`` of CPU time.
    Returns the closed mesh's vertices and faces, or ``None`` when the child ran out of time or failed;
    ``record`` (optional) gets ``outcome`` (``"closed"``, ``"out of time"`` or ``"failed: <its last words>"``)
    and the child's ``cpu_seconds``."""
    record = {} if record is None else record
    with tempfile.TemporaryDirectory(prefix="omnirecon-holes-") as tmp:
        src, dst = Path(tmp) / "in.npz", Path(tmp) / "out.npz"
        np.savez(src, vertices=np.asarray(vertices, np.float64), faces=np.asarray(faces, np.int32),
                 max_edges=np.int64(max_edges))
        cmd = [sys.executable, "-m", "omnirecon.mesh.meshlab_holes", str(src), str(dst), repr(float(cpu_seconds))]
        root = str(Path(__file__).resolve().parents[2])  # the child imports this very package, however it was found
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")]))}
        before = os.times()
        try:
            done = subprocess.run(cmd, capture_output=True, env=env, timeout=WALL_FACTOR * cpu_seconds + WALL_SLACK)
        except subprocess.TimeoutExpired:  # subprocess.run has killed the child
            record["outcome"] = "out of time"
            return None
        finally:
            after = os.times()
            record["cpu_seconds"] = round(after.children_user + after.children_system - before.children_user
                                          - before.children_system, 2)
        if done.returncode == -signal.SIGXCPU or done.returncode == -signal.SIGKILL:  # the CPU limit ended it
            record["outcome"] = "out of time"
            return None
        if done.returncode != 0 or not dst.is_file():
            words = done.stderr.decode(errors="replace").strip().splitlines()
            record["outcome"] = f"failed: {words[-1] if words else f'exit status {done.returncode}'}"
            return None
        record["outcome"] = "closed"
        with np.load(dst) as out:
            return out["vertices"], out["faces"].astype(np.int64)


def main(argv: list[str]) -> int:
    """The child: ``IN.npz OUT.npz CPU_SECONDS``."""
    import resource

    src, dst, seconds = Path(argv[0]), Path(argv[1]), float(argv[2])
    limit = max(1, int(np.ceil(seconds)))
    _, hard = resource.getrlimit(resource.RLIMIT_CPU)
    soft = limit if hard == resource.RLIM_INFINITY else min(limit, hard)
    resource.setrlimit(resource.RLIMIT_CPU, (soft, hard))  # SIGXCPU ends the process at the soft limit
    import pymeshlab

    with np.load(src) as data:
        vertices, faces, max_edges = data["vertices"], data["faces"], int(data["max_edges"])
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertices, faces))
    ms.meshing_repair_non_manifold_edges()
    ms.meshing_close_holes(maxholesize=max_edges, selfintersection=False)
    m = ms.current_mesh()
    tmp = dst.with_name("partial.npz")  # written whole, then renamed: the parent never reads half a file
    np.savez(tmp, vertices=m.vertex_matrix(), faces=m.face_matrix())
    tmp.replace(dst)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
