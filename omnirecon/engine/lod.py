"""The real-time mesh path's level of detail, chosen per mesh by measurement: :func:`choose_face_budget`.

Every face the depth pass draws costs CPU time on llvmpipe whether or not it is bigger than a pixel, while how many
faces a mesh can lose before its images change depends on the mesh (a room's walls lose little, a fern's leaves a lot).
So the budget is measured, not fixed: a few of the photos are left out of the sources and rendered from the others
(as novel views), through the mesh at :data:`~omnirecon.mesh.ibr.REALTIME_FACE_BUDGET` faces and
at each smaller candidate budget, and the smallest budget whose PSNR on those photos is at most ``tolerance_db`` below
the ceiling's is kept. The ceiling is the budget the path drew before the choice, so the choice never draws more
faces than that and never loses more than ``tolerance_db`` on the photos it was measured on.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import torch

LOD_BUDGETS = (100_000, 50_000)
"""Candidate face budgets below the ceiling (:data:`~omnirecon.mesh.ibr.REALTIME_FACE_BUDGET`), largest first."""
LOD_TOLERANCE_DB = 0.2
"""PSNR (dB) a smaller budget may lose against the ceiling on the left-out photos and still be chosen."""
LOD_VIEWS = 3
"""Photos left out of the sources and rendered per budget (spread over the capture's order)."""


@dataclass
class LodChoice:
    """What :func:`choose_face_budget` measured and chose."""

    face_budget: int
    """The chosen budget (faces drawn at most; the mesh's own count when it has fewer)."""
    faces: int
    """Faces the chosen level of detail draws."""
    rows: list[dict] = field(default_factory=list)
    """Per measured budget: ``{"budget", "faces", "psnr"}`` (dB, mean over the left-out photos), the ceiling first."""
    views: list[int] = field(default_factory=list)
    """The left-out photos (scene view indices)."""
    seconds: float = 0.0
    """Wall seconds of the choice (decimation and renders)."""
    tolerance_db: float = LOD_TOLERANCE_DB
    """The PSNR (dB) a smaller budget was allowed to lose."""

    def line(self) -> str:
        """One line for a run's output: the chosen budget and each measured budget's PSNR."""
        scores = ", ".join(f"{r['faces']:,} faces {r['psnr']:.2f} dB" for r in self.rows)
        return (f"level of detail: {self.faces:,} faces drawn (the smallest within {self.tolerance_db:g} dB of the largest "
                f"on {len(self.views)} photos left out of the sources: {scores}; {self.seconds:.1f} s)")


def left_out_views(train: list[int], count: int) -> list[int]:
    """``count`` photos of ``train`` spread evenly over its order (all of them when there are fewer)."""
    if len(train) <= count:
        return list(train)[:max(count, 0)]
    step = len(train) / count
    return [train[int(step * (i + 0.5))] for i in range(count)]


def choose_face_budget(model, mesh, scene, setting: dict, train: list[int], budgets=LOD_BUDGETS,
                       tolerance_db: float = LOD_TOLERANCE_DB, views: int = LOD_VIEWS,
                       ceiling: int | None = None) -> LodChoice:
    """The smallest face budget of ``budgets`` (and the ceiling) whose mean PSNR on ``views`` left-out photos of
    ``train`` is within ``tolerance_db`` of the ceiling's (module docstring).

    Args:
        model: The model whose appearance the mesh path blends with (as :class:`~omnirecon.mesh.ibr.MeshRenderer`).
        mesh: The scene-frame mesh (``trimesh.Trimesh`` or ``(vertices, faces)``), drawn whole at most at the ceiling.
        setting: The blend the path renders with (:func:`~omnirecon.mesh.ibr.realtime_setting`).
        train: The photos; ``views`` of them are left out of the sources and rendered from the rest (as the path
            picks a frame's sources: ``setting["sources"]`` nearest, or all).
        ceiling: The largest budget (default :data:`~omnirecon.mesh.ibr.REALTIME_FACE_BUDGET`; 0: the full mesh).
    """
    from omnirecon import metrics
    from omnirecon.engine.views import select_sources
    from omnirecon.mesh.frames import ViewCache
    from omnirecon.mesh.ibr import REALTIME_FACE_BUDGET, level_of_detail, video_options

    start = time.perf_counter()
    ceiling = REALTIME_FACE_BUDGET if ceiling is None else ceiling
    n_faces = len(mesh.faces) if hasattr(mesh, "faces") else len(mesh[1])
    top = n_faces if ceiling <= 0 else min(ceiling, n_faces)
    chosen = LodChoice(face_budget=ceiling, faces=top, tolerance_db=tolerance_db)
    left = left_out_views(train, min(views, len(train) - 1))  # at least one photo stays a source
    smaller = [b for b in budgets if 0 < b < top]
    if not left or not smaller:
        chosen.seconds = round(time.perf_counter() - start, 2)
        return chosen  # nothing to measure against, or nothing smaller to try
    pool = [t for t in train if t not in left]  # no left-out photo is a source: one source set (one encoding) for all
    k = min(setting["sources"] or len(pool), len(pool))
    picks = {v: sorted(select_sources(scene, scene.cameras[v], pool, k)) for v in left}
    bg = tuple(scene.background) if scene.background is not None else (1.0, 1.0, 1.0)
    encodings: dict = {}  # each left-out photo's sources encoded once, for every budget
    for budget in [ceiling, *smaller]:
        drawn = level_of_detail(mesh, budget)
        scores = []
        with ViewCache(model, drawn, scene, video_options(setting, bg, face_budget=0), encodings) as cache:
            for v in left:
                with cache.renderer(picks[v]) as r, torch.inference_mode():
                    rgb = r.render(scene.cameras[v].to(dtype=torch.float32), extras=False)["rgb"].float().clamp(0, 1)
                scores.append(metrics.psnr(rgb, scene.images[v].float()))
        chosen.rows.append({"budget": budget, "faces": int(len(drawn[1])), "psnr": round(sum(scores) / len(scores), 3)})
    best = chosen.rows[0]["psnr"]
    for row in chosen.rows[1:]:
        if row["psnr"] >= best - tolerance_db:
            chosen.face_budget, chosen.faces = row["budget"], row["faces"]
    chosen.views = left
    chosen.seconds = round(time.perf_counter() - start, 2)
    return chosen
