"""BENCHMARKS.md section: the real-time mesh path's level of detail and candidate sources (`python -m bench mesh_lod`)."""

from __future__ import annotations

from pathlib import Path

from bench.report.common import prov, read


def _main(row: dict) -> str:
    return f"{row['frame_main_cpu_ms']:.0f}" if "frame_main_cpu_ms" in row else "–"  # rows measured before it was


def _stream(row: dict) -> str:
    return f"{row['stream_fps']:.1f} ({row['stream_cpu_ms']:.0f})" if "stream_fps" in row else "–"


def _line(scene: dict, row: dict) -> str:
    what = ("reference (full mesh, every source)" if row["face_budget"] == 0 and row["frame_grid"] == 0 else
            f"budget {row['face_budget'] or 'none'}, grid {row['frame_grid']}")
    what += f", {row['shader']} shader" if "shader" in row else ""
    what += f", {row['sources']} sources per frame" if row.get("sources") else ""
    what += f", MLP every {row['weight_stride']} px" if row.get("weight_stride", 1) > 1 else ""
    what += f", {row['angle_sources']} sources per point" if row.get("angle_sources") else ""
    what += ", only the faces the photos see" if row.get("photographed") else ""
    what += ", MeshLab's collapse" if row.get("decimator") == "meshlab" else ""
    what += f", {row['proposed']} candidates proposed per grid point" if "proposed" in row and \
        row.get("frame_grid") and scene["setting"]["blend"] == "angle" else ""
    w, h = scene["resolution"]
    return (f"| {scene['scene']} | {w}x{h} | {what} | {row['faces']:,} | {row['frame_ms']:.0f} | {row['fps']:.1f} | "
            f"{row['frame_cpu_ms']:.0f} | {_main(row)} | {_stream(row)} | {row['depth_pass_cpu_ms']:.0f} | {row['decimate_s']:.1f} | {row['psnr']:.2f} | "
            f"{0.0 - row['psnr_loss_db']:+.2f} | {row['loadavg_1min']:.1f} | `{scene.get('commit', '–')}` |")


def section(results: Path) -> str | None:
    r = read(results, "mesh_lod.json")
    if not r or not r.get("scenes"):
        return None
    out = ["## Real-time mesh path: level of detail and candidate sources (`python -m bench mesh_lod`)", "",
           "The mesh `reconstruct` builds (`omnirecon mesh --views all`, omnirecon-tiny, untuned) rendered by the "
           "real-time frame path at the photos' size (the demo scene timed at the demo's 256 px, scored at its 128-px images) with the blend the videos "
           "use (`realtime_setting`, occlusion test on), "
           f"{r['threads']} shading threads and llvmpipe threads; median of {r['frames']} frames over the held-out "
           "views" + (f", each timing the median of {r['rounds']} rounds (each round times every row of the scene in "
                      "turn, so that the machine's drift over minutes falls on every row alike; FPS per round in "
                      "`rounds_fps` of the results file)" if r.get("rounds", 1) > 1 else "") + ". Rows: the reference path (full mesh, every source ranked at every point), then face budgets "
           "(`MeshRenderOptions.face_budget`, once at load: the mesh's coincident vertices welded, then quadric "
           "decimation) with each chunk's candidate sources "
           "(`frame_grid`) and the frame's shader (`MeshRenderOptions.shader`: the GL pass or the torch shader); "
           "rows `N candidates proposed per grid point` (angle blend, `--proposed`): the chosen level with each tile's "
           "candidates from N sources per grid point beyond the point's own (`GLBlend.PROPOSED`; the other rows the "
           "shipped count, `candidates_proposed` in the results file where recorded). "
           "Main-thread CPU: the calling thread's share of the frame's CPU (the serial part: the passes' front end, "
           "the fill, the candidates, the blur at depth edges; the rest runs on llvmpipe's and the shading workers' "
           "threads), below which the wall time cannot fall on idle cores. Streamed: the same frames as the videos "
           "render them (`MeshRenderer.frames`, a frame ahead: each frame's GL pass shaded beside the next one's depth "
           "pass), FPS and CPU ms per frame. "
           "PSNR: held-out whole image through the same blend; the change is against the reference row. "
           f"Shipped: at most {r['realtime_face_budget']:,} faces (fewer where the choice below allows), grid "
           f"{r['realtime_frame_grid']}. "
           f"{r['machine_note']}.", "",
           "| scene | size | path | faces | wall ms | FPS | CPU ms | main-thread CPU ms | streamed FPS (CPU ms) | "
           "depth pass CPU ms | decimate s | PSNR | dB vs reference | load | commit |", "|" + "---|" * 15]
    out += [_line(s, row) for s in r["scenes"] for row in s["rows"]]
    chosen = [_chosen(s) for s in r["scenes"] if "lod" in s]
    if chosen:
        out += ["", "What `reconstruct` and `demo` draw, chosen per mesh (`omnirecon.engine.lod`): three training "
                "photos left out of the sources and rendered at each face budget, then (network blend) with fewer "
                "sources per frame at the chosen budget (where none passes there, once more one budget up, which "
                "is then drawn with them), or (angle blend) with fewer sources blended per point (6 and 4, below the "
                "count finetune chose; rows `, N per point`) the same way but within 0.2 dB of the ceiling row, as "
                "the faces; the fewest faces within the tolerance of the ceiling row "
                "and the fewest sources that lose nothing against it are drawn (PSNR in dB on those photos, not the "
                "held-out views of the table). Fewer sources lose nothing there because a first rule, within the "
                "same 0.2 dB as the faces, let the demo blend 4 sources: -0.05 dB on the left-out photos, -0.54 dB on "
                "the held-out views (26.21 against 26.75, 3 views; measured 2026-12-02, the run before this table's). "
                "Next, MeshLab's quadric edge collapse (pymeshlab) is measured at the chosen budget and below with "
                "the chosen sources (rows `, MeshLab`), and its smallest level that scores no worse than the chosen "
                "level and within 0.2 dB of the ceiling row is drawn instead (rows `MeshLab's collapse`; "
                "fast-simplification's elsewhere): on fern it kept more of the surface at the same count, on fox and "
                "lund less. "
                "Last, where the GL pass blends at most 3 sources with the network, its MLP at every second pixel of "
                "each axis only (`MeshRenderOptions.weight_stride`, the weights interpolated on each pixel's own "
                "surface) is measured at the chosen budget and sources and kept within 0.05 dB of them. Then, where "
                "the sources (the photos not left out) leave at least 10 % of the chosen level's faces unseen "
                "(`photographed_faces`: not the nearest face at any of 4 x 4 samples per pixel of any source, and "
                "large enough in some source to be judged), the chosen level drawing only the faces they see is "
                "measured and kept within 0.2 dB of the ceiling row, as the face budgets (rows `, photographed "
                "only`; the table's rows `only the faces the photos see`: the training views decide):",
                "", *chosen]
        culled = [_culled(s) for s in r["scenes"] if any(x.get("photographed") for x in s["rows"])]
        if culled:
            out += ["", "Only the faces the photos see against the same level with all its faces (the two rows of each "
                    "scene above, timed in the same rounds; held-out PSNR, whole image):", "",
                    "| scene | faces | FPS | streamed FPS | CPU ms | depth pass CPU ms | PSNR |", "|---|---|---|---|---|---|---|",
                    *culled]
        out += ["", "Issue 43's goal (at least 30 FPS at the photos' size on 2 cores, within 0.2 dB of the full mesh), "
                "from each scene's last row (what the videos draw):", "", *[_goal(s) for s in r["scenes"] if "lod" in s]]
    out += ["", prov(r["provenance"])]
    before, weld = read(results, "mesh_lod_before_weld.json"), read(results, "mesh_lod_weld.json")
    if before and weld:
        out += ["", *_before_after(before, weld, WELD)]
    return "\n".join([*out, ""])


WELD = ("The same bench at commit `{commit}` (before the level of detail welded coincident vertices, with the face "
        "budgets 100,000 to 25,000 below the ceiling and fewer sources measured at the chosen budget only), beside the "
        "run at commit `{after}` (`bench/results/mesh_lod_weld.json`: after the weld, before the choice drew only the "
        "faces the photos see), run on the same machine in the same session within about 20 minutes of each other (`python -m bench mesh_lod --scenes fox fern lund --out bench/results/mesh_lod_before_weld.json` in a "
        "checkout of that commit), each scene's chosen level of detail. Decimated as given, completion's pixel fills "
        "(each pixel's quad with corners of its own) were borders the collapse deleted: on a 48 x 48 fill 13 % of the "
        "pixels stayed covered at 576 faces (`tests/mesh/test_complete.py`). "
        "Runs of one setting minutes apart differed by up to about 30 % in FPS here, so read the FPS loosely and the "
        "CPU ms and PSNR (held-out, whole image) more firmly:")
"""The before/after paragraph of the weld (``mesh_lod_before_weld.json``: the bench at the commit before it)."""


def _chosen_row(scene: dict) -> dict:
    """The row of what the videos draw (the last row: the chosen level, else the chosen budget's; not the rows of
    other candidate counts, ``--proposed``)."""
    lod = scene["lod"]
    rows = [x for x in scene["rows"] if x["face_budget"] == lod["face_budget"] and x["frame_grid"] > 0
            and "proposed" not in x]
    return rows[-1]


def _culled(scene: dict) -> str:
    """The table row of a scene's photographed level beside the same level with all its faces: ``a -> b`` per column."""
    b = next(x for x in scene["rows"] if x.get("photographed"))
    a = next(x for x in reversed(scene["rows"]) if not x.get("photographed") and x["face_budget"] == b["face_budget"]
             and x["frame_grid"] == b["frame_grid"] and x.get("sources") == b.get("sources")
             and x.get("weight_stride", 1) == b.get("weight_stride", 1)
             and x.get("decimator", "fast") == b.get("decimator", "fast"))
    cols = [f"{a['faces']:,} -> {b['faces']:,}"] + [f"{a[k]:{f}} -> {b[k]:{f}}" for k, f in (
        ("fps", ".1f"), ("stream_fps", ".1f"), ("frame_cpu_ms", ".0f"), ("depth_pass_cpu_ms", ".0f"), ("psnr", ".2f"))]
    return f"| {scene['scene']} | " + " | ".join(cols) + " |"


def _goal(scene: dict) -> str:
    row = _chosen_row(scene)
    fps = max(row["fps"], row.get("stream_fps", 0.0))  # frame by frame or streamed, as the videos render
    ok = fps >= 30 and row["psnr_loss_db"] <= 0.2
    streamed = f", streamed {row['stream_fps']:.1f} FPS" if "stream_fps" in row else ""
    blend = ""
    if scene.get("record"):  # measured with a finetune record's blend, as reconstruct draws it
        st = scene["setting"]
        per = f"{st['angle_sources']} sources per point" if st["blend"] == "angle" else f"{st['sources']} sources per frame"
        per += f", drawn with {row['angle_sources']}" if row.get("angle_sources") else ""
        blend = f"; finetune's record: {st['blend']} blend, {per}"
    return (f"- {scene['scene']}: {row['fps']:.1f} FPS{streamed}, {0.0 - row['psnr_loss_db']:+.2f} dB against the full "
            f"mesh ({'met' if ok else 'short'}{blend})")


def _level(row: dict) -> str:
    return f"{row['faces']:,} faces" + (f", {row['sources']} sources" if row.get("sources") else "") + \
        (f", MLP every {row['weight_stride']} px" if row.get("weight_stride", 1) > 1 else "") + \
        (f", {row['angle_sources']} sources per point" if row.get("angle_sources") else "") + \
        (", photographed only" if row.get("photographed") else "") + \
        (", MeshLab's collapse" if row.get("decimator") == "meshlab" else "")


def _before_after(before: dict, after: dict, text: str) -> list[str]:
    """Each scene's chosen level measured by the code before a change (``text``, its commit filled in), the same
    session and machine, beside this table's."""
    now = {s["scene"]: s for s in after["scenes"]}
    lines = [text.format(commit=before["provenance"]["commit"][:12], after=after["provenance"]["commit"][:12]), "",
             "| scene | chosen level before -> after | FPS before -> after | streamed FPS before -> after | "
             "CPU ms before -> after | PSNR before -> after | dB vs the full mesh before -> after |",
             "|---|---|---|---|---|---|---|"]
    for old in before["scenes"]:
        if old["scene"] not in now:
            continue
        a, b = _chosen_row(old), _chosen_row(now[old["scene"]])
        lines.append(f"| {old['scene']} | {_level(a)} -> {_level(b)} | {a['fps']:.1f} -> {b['fps']:.1f} | "
                     f"{a['stream_fps']:.1f} -> {b['stream_fps']:.1f} | {a['frame_cpu_ms']:.0f} -> "
                     f"{b['frame_cpu_ms']:.0f} | {a['psnr']:.2f} -> {b['psnr']:.2f} | {0.0 - a['psnr_loss_db']:+.2f} -> "
                     f"{0.0 - b['psnr_loss_db']:+.2f} |")
    return [*lines, "", prov(before["provenance"])]


def _chosen(scene: dict) -> str:
    lod = scene["lod"]
    scores = ", ".join(f"{x['faces']:,} faces{_sources(x)} {x['psnr']:.2f}" for x in lod["rows"]) or \
        "nothing smaller to measure"
    drawn = f"{lod['faces']:,} faces" + (f", {lod['sources']} sources per frame" if lod.get("sources") else "")
    drawn += f", the MLP every {lod['weight_stride']} px" if lod.get("weight_stride", 1) > 1 else ""
    drawn += f", {lod['angle_sources']} sources per point" if lod.get("angle_sources") else ""
    drawn += ", only the faces the photos see" if lod.get("photographed") else ""
    drawn += ", MeshLab's collapse" if lod.get("decimator") == "meshlab" else ""
    return f"- {scene['scene']}: **{drawn}** (within {lod['tolerance_db']:g} dB; {scores}; {lod['seconds']:.1f} s)"


def _sources(row: dict) -> str:
    stride = f", MLP every {row['weight_stride']} px" if row.get("weight_stride", 1) > 1 else ""
    stride += f", {row['angle_sources']} per point" if row.get("angle_sources") else ""
    seen = ", photographed only" if row.get("photographed") else ""
    method = ", MeshLab" if row.get("decimator") == "meshlab" else ""
    return (f" x {row['sources']} sources" if row.get("sources") else "") + stride + seen + method
