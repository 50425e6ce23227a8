"""The real-time mesh path's level of detail, chosen per mesh by measurement: :func:`choose_level_of_detail`.

Every face the depth pass draws costs CPU time on llvmpipe whether or not it is bigger than a pixel, while how many
faces a mesh can lose before its images change depends on the mesh (a room's walls lose little, a fern's leaves a lot).
So the budget is measured, not fixed: a few of the photos are left out of the sources and rendered from the others
(as novel views), through the mesh at :data:`~omnirecon.mesh.ibr.REALTIME_FACE_BUDGET` faces and
at each smaller candidate budget, and the smallest budget whose PSNR on those photos is at most ``tolerance_db`` below
the ceiling's is kept. The ceiling is the budget the path drew before the choice, so the choice never draws more
faces than that and never loses more than ``tolerance_db`` on the photos it was measured on.

The network blend's work per pixel grows with the sources it blends (each one projected, tested for occlusion, its
features fetched and run through the appearance MLP), so at the chosen budget fewer sources per frame
(:data:`LOD_SOURCES`) are measured the same way, against the same ceiling row, and the fewest that lose nothing there
(:data:`LOD_SOURCES_TOLERANCE_DB`) are blended: the left-out photos judge a source count less surely than a face budget
(their pool is sparser than the path's: BENCHMARKS "Real-time mesh path: level of detail"). Where none does, because the
faces the budget took off cost what fewer sources would not, they are measured once more one budget up, and where they
pass there, that budget is drawn with them: fewer sources save more of a network frame than a rung of faces (fern:
150,000 faces and 6 sources drew slower frames than 200,000 faces and 3 sources with the MLP's stride). The angle blend
ranks each tile's candidates and blends a fixed few already; its sources per frame are left alone, and fewer sources
blended per point (:data:`LOD_ANGLE_SOURCES`, below the setting's ``angle_sources``, the count ``finetune`` scored best
on its validation views) are measured in their place, the same way (at the chosen budget, then one rung up), within
:data:`LOD_ANGLE_TOLERANCE_DB` of the ceiling row: on llvmpipe each pixel's work follows the sources it ranks (each
tile's candidates: those nearest by angle at its grid points, ``angle_sources`` +
:attr:`~omnirecon.render.glblend.GLBlend.PROPOSED` each) and blends, and fewer of them saved more of a frame than a
rung of faces (fox).

Then MeshLab's quadric edge collapse (:data:`LOD_DECIMATORS`) is measured at the chosen budget and below, with the
chosen sources: its checks on the faces' shape and normals keep more of some meshes at the same count and lose more of
others (BENCHMARKS "Real-time mesh path: level of detail and candidate sources": fern against fox), so the smallest of
its levels that is no worse than the chosen one and within ``tolerance_db`` of the ceiling row is drawn instead, and
the steps below start from it.

Then, where the GL pass shades the network blend of few enough sources, the appearance MLP at every second pixel of
each axis only (:data:`LOD_STRIDES`, ``MeshRenderOptions.weight_stride``) is measured the same way, at the chosen budget
and sources, against that row (:data:`LOD_STRIDE_TOLERANCE_DB`).

Last, the chosen level drawn with only the faces the photos see (:func:`~omnirecon.mesh.ibr.photographed_faces`, seen
by the sources alone: a face only a left-out photo sees is left out, as a face no photo sees is from a novel view) is
measured where it leaves out at least :data:`LOD_CULL_MIN_SHARE` of the faces (the depth pass shades every fragment of
the frame's faces, hidden or not), and drawn where it is within ``tolerance_db`` of the ceiling row: one more level of
detail of the surface, held to the same bound as the face budgets.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import torch

LOD_BUDGETS = (150_000, 100_000, 50_000, 25_000)
"""Candidate face budgets below the ceiling (:data:`~omnirecon.mesh.ibr.REALTIME_FACE_BUDGET`), largest first."""
LOD_TOLERANCE_DB = 0.2
"""PSNR (dB) a smaller budget may lose against the ceiling on the left-out photos and still be chosen."""
LOD_SOURCES = (4, 3)
"""Candidate source counts per frame of the network blend below the setting's (``setting["sources"]``), most first."""
LOD_SOURCES_TOLERANCE_DB = 0.0
"""PSNR (dB) fewer sources may lose against the ceiling on the left-out photos and still be chosen: none."""
LOD_STRIDES = (2,)
"""Candidate ``MeshRenderOptions.weight_stride`` of the network blend's GL pass (the MLP at every n-th pixel)."""
LOD_STRIDE_TOLERANCE_DB = 0.05
"""PSNR (dB) a weight stride may lose against the same budget and sources at every pixel and still be chosen."""
LOD_ANGLE_SOURCES = (6, 4)
"""Candidate sources blended per point by the angle blend below the setting's (``setting["angle_sources"]``), most
first."""
LOD_ANGLE_TOLERANCE_DB = LOD_TOLERANCE_DB
"""PSNR (dB) fewer sources per point may lose against the ceiling row and still be chosen: as many as the faces (unlike the
network's sources per frame, no frame's source set is cut to the nearest of the left-out photos' sparser pool)."""
LOD_DECIMATORS = ("meshlab",)
"""Quadric edge collapses measured besides fast-simplification's (:data:`omnirecon.mesh.clean.DECIMATORS`), at the
chosen budget and below, with the chosen sources."""
LOD_CULL_MIN_SHARE = 0.1
"""The share of the chosen level's faces the photos must leave unseen for that cull to be measured."""
LOD_VIEWS = 3
"""Photos left out of the sources and rendered per budget (spread over the capture's order)."""


@dataclass
class LodChoice:
    """What :func:`choose_level_of_detail` measured and chose."""

    face_budget: int
    """The chosen budget (faces drawn at most; the mesh's own count when it has fewer)."""
    faces: int
    """Faces the chosen level of detail draws."""
    sources: int | None = None
    """Sources per frame the network blend takes (None: the setting's, unchanged)."""
    weight_stride: int = 1
    """``MeshRenderOptions.weight_stride`` of the chosen level (1: the MLP at every pixel)."""
    angle_sources: int | None = None
    """Sources the angle blend blends per point (None: the setting's, unchanged)."""
    decimator: str = "fast"
    """The quadric edge collapse of the chosen level (:data:`omnirecon.mesh.clean.DECIMATORS`)."""
    photographed: bool = False
    """Only the faces the photos see are drawn (:func:`~omnirecon.mesh.ibr.level_of_detail` with ``photos``)."""
    rows: list[dict] = field(default_factory=list)
    """Per measured level: ``{"budget", "faces", "sources", "psnr"}`` (PSNR in dB, mean over the left-out photos; sources
    0: every photo; ``"photographed": True`` on the row of only the photographed faces), the ceiling first."""
    views: list[int] = field(default_factory=list)
    """The left-out photos (scene view indices)."""
    seconds: float = 0.0
    """Wall seconds of the choice (decimation and renders)."""
    tolerance_db: float = LOD_TOLERANCE_DB
    """The PSNR (dB) a smaller budget was allowed to lose."""
    level: tuple | None = field(default=None, repr=False, compare=False)
    """``(id(mesh), (vertices, faces))``: the chosen level as the choice decimated it (before the cull), so that
    :meth:`drawn` of the same mesh does not decimate it again (MeshLab's collapse takes seconds)."""

    def setting(self, setting: dict) -> dict:
        """``setting`` (:func:`~omnirecon.mesh.ibr.realtime_setting`) with the chosen sources per frame, weight
        stride and sources per point."""
        out = setting if self.sources is None else {**setting, "sources": self.sources}
        out = out if self.angle_sources is None else {**out, "angle_sources": self.angle_sources}
        return out if self.weight_stride == 1 else {**out, "weight_stride": self.weight_stride}

    def record(self) -> dict:
        """What was chosen and measured, for a run's records (``results.json``, ``metrics.json``)."""
        return {"face_budget": self.face_budget, "faces": self.faces, "sources": self.sources,
                "weight_stride": self.weight_stride, "angle_sources": self.angle_sources,
                "photographed": self.photographed, "decimator": self.decimator, "rows": self.rows, "views": self.views,
                "seconds": self.seconds, "tolerance_db": self.tolerance_db}

    def drawn(self, mesh, photos):
        """The ``(vertices, faces)`` the path draws of ``mesh`` at this level, ``photos`` (the scene's photos,
        :class:`~omnirecon.cameras.Cameras`) deciding which faces are seen (:func:`~omnirecon.mesh.ibr.level_of_detail`);
        draw it with ``MeshRenderOptions.face_budget`` 0."""
        from omnirecon.mesh.ibr import level_of_detail

        if self.level is not None and self.level[0] == id(mesh):  # decimated already, by the choice
            return level_of_detail(self.level[1], 0, photos if self.photographed else None)
        return level_of_detail(mesh, self.face_budget, photos if self.photographed else None, self.decimator)

    def line(self) -> str:
        """One line for a run's output: what is drawn and each measured level's PSNR."""
        if not self.rows:
            return f"level of detail: {self.faces:,} faces drawn (nothing smaller to measure)"
        scores = ", ".join(f"{r['faces']:,} faces{_sources(r)} {r['psnr']:.2f} dB" for r in self.rows)
        blended = f", {self.sources} sources per frame" if self.sources is not None else ""
        blended += f", the MLP every {self.weight_stride} px" if self.weight_stride > 1 else ""
        blended += f", {self.angle_sources} sources per point" if self.angle_sources is not None else ""
        blended += ", only the faces the photos see" if self.photographed else ""
        blended += ", MeshLab's collapse" if self.decimator == "meshlab" else ""
        fewer = ("the fewest sources per point within the same" if any(r.get("angle_sources") for r in self.rows) else
                 "the fewest sources that lose nothing")
        return (f"level of detail: {self.faces:,} faces drawn{blended} (the fewest faces within {self.tolerance_db:g} dB "
                f"of the most, {fewer}, on {len(self.views)} photos left out of the sources: {scores}; "
                f"{self.seconds:.1f} s)")


def _sources(row: dict) -> str:
    stride = f", MLP stride {row['weight_stride']}" if row.get("weight_stride", 1) > 1 else ""
    stride += f", {row['angle_sources']} per point" if row.get("angle_sources") else ""
    seen = ", photographed only" if row.get("photographed") else ""
    method = ", MeshLab" if row.get("decimator") == "meshlab" else ""
    return (f" x {row['sources']} sources" if row.get("sources") else "") + stride + seen + method


def left_out_views(train: list[int], count: int) -> list[int]:
    """``count`` photos of ``train`` spread evenly over its order (all of them when there are fewer)."""
    if len(train) <= count:
        return list(train)[:max(count, 0)]
    step = len(train) / count
    return [train[int(step * (i + 0.5))] for i in range(count)]


def choose_level_of_detail(model, mesh, scene, setting: dict, train: list[int], budgets=LOD_BUDGETS,
                           sources=LOD_SOURCES, tolerance_db: float = LOD_TOLERANCE_DB, views: int = LOD_VIEWS,
                           ceiling: int | None = None,
                           sources_tolerance_db: float = LOD_SOURCES_TOLERANCE_DB, strides=LOD_STRIDES,
                           stride_tolerance_db: float = LOD_STRIDE_TOLERANCE_DB,
                           cull_tolerance_db: float | None = LOD_TOLERANCE_DB,
                           decimators=LOD_DECIMATORS, angle_sources=LOD_ANGLE_SOURCES,
                           angle_tolerance_db: float = LOD_ANGLE_TOLERANCE_DB) -> LodChoice:
    """The smallest face budget of ``budgets`` (and the ceiling), then for the network blend the fewest sources per
    frame of ``sources``, whose mean PSNR on ``views`` left-out photos of ``train`` is within ``tolerance_db`` (fewer
    sources: ``sources_tolerance_db``) of the ceiling's at the setting's sources (where no count passes at the chosen
    budget, one budget up, which is then drawn), then each other collapse of ``decimators`` at that budget and below
    (the smallest level no worse than the chosen one and within ``tolerance_db`` of the ceiling row), then the largest
    weight stride of ``strides`` within
    ``stride_tolerance_db`` of the chosen row, then
    only the faces the sources see within ``cull_tolerance_db`` of the ceiling row (``None``: not measured; module
    docstring). For the angle blend, the fewest sources per point of ``angle_sources`` within ``angle_tolerance_db``
    of the ceiling row take the place of the fewer sources per frame.

    Args:
        model: The model whose appearance the mesh path blends with (as :class:`~omnirecon.mesh.ibr.MeshRenderer`).
        mesh: The scene-frame mesh (``trimesh.Trimesh`` or ``(vertices, faces)``), drawn whole at most at the ceiling.
        setting: The blend the path renders with (:func:`~omnirecon.mesh.ibr.realtime_setting`).
        train: The photos; ``views`` of them are left out of the sources and rendered from the rest (as the path
            picks a frame's sources: ``setting["sources"]`` nearest, or all).
        ceiling: The largest budget (default :data:`~omnirecon.mesh.ibr.REALTIME_FACE_BUDGET`; 0: the full mesh).
        angle_sources: Candidate sources per point of the angle blend (those below ``setting["angle_sources"]``).
    """
    from omnirecon import metrics
    from omnirecon.engine.views import select_sources
    from omnirecon.mesh.frames import ViewCache
    from omnirecon.mesh.ibr import REALTIME_FACE_BUDGET, level_of_detail, video_options
    from omnirecon.render.glblend import GLBlend
    from omnirecon.render.raster import gl_unavailable_reason

    start = time.perf_counter()
    ceiling = REALTIME_FACE_BUDGET if ceiling is None else ceiling
    n_faces = len(mesh.faces) if hasattr(mesh, "faces") else len(mesh[1])
    top = n_faces if ceiling <= 0 else min(ceiling, n_faces)
    chosen = LodChoice(face_budget=ceiling, faces=top, tolerance_db=tolerance_db)
    left = left_out_views(train, min(views, len(train) - 1))  # at least one photo stays a source
    pool = [t for t in train if t not in left]  # no left-out photo is a source: one source set (one encoding) for all
    k0 = min(setting["sources"] or len(pool), len(pool))
    smaller = [b for b in budgets if 0 < b < top]
    fewer = [k for k in sources if k < k0] if setting["blend"] == "network" and setting["sources"] else []
    ka0 = min(setting.get("angle_sources") or k0, k0)  # sources per point the angle blend ranks (0: every source)
    per_point = [k for k in angle_sources if k < ka0] if setting["blend"] == "angle" else []
    if not left or not (smaller or fewer or per_point):
        chosen.seconds = round(time.perf_counter() - start, 2)
        return chosen  # nothing to measure against, or nothing smaller to try
    bg = tuple(scene.background) if scene.background is not None else (1.0, 1.0, 1.0)
    encodings: dict = {}  # each set of sources encoded once, for every budget

    def score(drawn, k: int, stride: int = 1, ka: int | None = None) -> float:  # mean PSNR of the left-out photos,
        scores = []  # from the k nearest (ka: the angle blend's sources per point)
        opts = video_options({**setting, "weight_stride": stride, **({"angle_sources": ka} if ka else {})}, bg,
                             face_budget=0)
        with ViewCache(model, drawn, scene, opts, encodings) as cache:
            for v in left:
                with cache.renderer(sorted(select_sources(scene, scene.cameras[v], pool, k))) as r, \
                        torch.inference_mode():
                    rgb = r.render(scene.cameras[v].to(dtype=torch.float32), extras=False)["rgb"].float().clamp(0, 1)
                scores.append(metrics.psnr(rgb, scene.images[v].float()))
        return round(sum(scores) / len(scores), 3)

    meshes = {}
    for budget in [ceiling, *smaller]:
        meshes[budget] = level_of_detail(mesh, budget)
        chosen.rows.append({"budget": budget, "faces": int(len(meshes[budget][1])), "sources": setting["sources"],
                            "psnr": score(meshes[budget], k0)})
    best = chosen.rows[0]["psnr"]
    for row in chosen.rows[1:]:
        if row["psnr"] >= best - tolerance_db:
            chosen.face_budget, chosen.faces = row["budget"], row["faces"]
    order = [ceiling, *smaller]
    at = order.index(chosen.face_budget)
    network = setting["blend"] == "network"
    key, counts = ("sources", fewer) if network else ("angle_sources", sorted(per_point, reverse=True))
    allowed = sources_tolerance_db if network else angle_tolerance_db
    for budget in order[max(at - 1, 0):at + 1][::-1] if counts else ():  # the chosen budget, then one rung up
        for k in counts:  # against the same ceiling row
            row = {"budget": budget, "faces": int(len(meshes[budget][1])),
                   **({"sources": k} if network else {"sources": setting["sources"], "angle_sources": k}),
                   "psnr": score(meshes[budget], k, ka=None) if network else score(meshes[budget], k0, ka=k)}
            chosen.rows.append(row)
            if row["psnr"] >= best - allowed:
                setattr(chosen, key, k)
        if getattr(chosen, key) is not None:  # the rung that lost faces may lose what fewer sources gain back: one
            chosen.face_budget, chosen.faces = budget, int(len(meshes[budget][1]))  # rung up
            break
    k1, ka1, picked = chosen.sources or k0, chosen.angle_sources, getattr(chosen, key)
    base = next(r["psnr"] for r in (chosen.rows[len(meshes):] if picked else chosen.rows[:len(meshes)])
                if r["budget"] == chosen.face_budget and (not picked or r.get(key) == picked))
    drawn = meshes[chosen.face_budget]
    fast = base  # the other collapses must not lose against the fast one's chosen row
    for method in decimators:  # at the chosen budget, then down while each level passes
        for budget in [b for b in order if 0 < b <= chosen.face_budget and b < n_faces]:
            other = level_of_detail(mesh, budget, decimator=method)
            row = {"budget": budget, "faces": int(len(other[1])), "sources": k1, "decimator": method,
                   **({"angle_sources": ka1} if ka1 else {}), "psnr": score(other, k1, ka=ka1)}
            chosen.rows.append(row)
            if row["psnr"] < max(fast, best - tolerance_db):
                break
            chosen.face_budget, chosen.faces, chosen.decimator = budget, row["faces"], method
            drawn, base = other, row["psnr"]
    if network and k1 <= GLBlend.STRIDE_SOURCES and gl_unavailable_reason() is None:
        for stride in sorted(strides):  # only the GL pass takes a stride (where it shades these sources)
            row = {"budget": chosen.face_budget, "faces": chosen.faces, "sources": k1, "weight_stride": stride,
                   "psnr": score(drawn, k1, stride)}
            chosen.rows.append(row)
            if row["psnr"] >= base - stride_tolerance_db:
                chosen.weight_stride = stride
    chosen.level = (id(mesh), drawn)
    if cull_tolerance_db is not None:
        seen = level_of_detail(drawn, 0, scene.cameras[pool])  # seen by the sources alone
        if len(seen[1]) <= (1 - LOD_CULL_MIN_SHARE) * chosen.faces:
            row = {"budget": chosen.face_budget, "faces": int(len(seen[1])), "sources": k1,
                   "weight_stride": chosen.weight_stride, "photographed": True, "decimator": chosen.decimator,
                   **({"angle_sources": ka1} if ka1 else {}), "psnr": score(seen, k1, chosen.weight_stride, ka1)}
            chosen.rows.append(row)
            if row["psnr"] >= best - cull_tolerance_db:  # against the ceiling, as the face budgets
                chosen.photographed, chosen.faces = True, row["faces"]
    chosen.views = left
    chosen.seconds = round(time.perf_counter() - start, 2)
    return chosen
