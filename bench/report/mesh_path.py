"""BENCHMARKS.md section: Real-time mesh path (`python -m bench mesh_fps`, `python -m bench mesh_path`)."""

from __future__ import annotations

import json
from pathlib import Path

from bench.report.common import VOLUMETRIC_ONLY, num, prov, stale_note


def section(results: Path) -> str | None:
    fps_file, q_file = results / "mesh_fps.json", results / "mesh_path.json"
    if not fps_file.is_file() and not q_file.is_file():
        return None
    out = ["## Real-time mesh path (`python -m bench mesh_fps`, `python -m bench mesh_path`)", ""]
    if fps_file.is_file():
        r = json.loads(fps_file.read_text())
        c, m, v = r["config"], r["mesh"], r["volumetric"]
        w, h = m["resolution"]
        out += [f"Speed: one model ({r['model']['preset']}; {r['model']['weights']}), a procedural scene with "
                f"{r['scene']['faces']:,} faces, {c['source_views']} source views at {c['source_resolution'][0]}², "
                f"device {c['device']}, {c['torch_threads']} torch thread(s), rasterizer `{c['rasterizer']}`. Mesh path: "
                f"median of {c['frames']} full frames after {c['warmup']} warm-up frames, camera moving. Volumetric: "
                f"`render_rays` on {v['rays_per_batch']}-ray batches of the same view, FPS extrapolated from rays/s.", "",
                "| path | resolution | FPS (wall) | FPS from CPU time | ms / frame | notes |", "|---|---|---|---|---|---|",
                f"| mesh (rasterize + appearance branch) | {w}x{h} | {m['fps']:.1f} | {m['fps_from_cpu_time']:.1f} | "
                f"{m['median_ms']:.1f} | " + (f"depth pass {m['depth_pass_ms']:.1f} ms; no visibility test (the renderer's "
                "default) |" if "depth_pass_ms" in m else f"G-buffer surface pass {m['surface_pass_ms']:.1f} ms |"),
                f"| mesh + visibility test | {w}x{h} | {m['visibility_fps']:.1f} | – | {m['visibility_median_ms']:.1f} | "
                "the web viewer's default |",
                f"| volumetric (coarse + fine, geometry branch) | {w}x{h} | {v['fps_equivalent']:.4f} | – | "
                f"{1000 / v['fps_equivalent']:.0f} | {v['rays_per_s']:.0f} rays/s |", "",
                f"Ratio mesh / volumetric: **{r['ratio']:.0f}x** (goal >= {r['goals']['ratio']:.0f}x: "
                f"{'met' if r['ratio'] >= r['goals']['ratio'] else 'not met'}). Goal >= {r['goals']['cpu_fps_512']:.0f} FPS "
                f"at 512x512 on this CPU: {m['fps']:.1f} FPS wall, {m['fps_from_cpu_time']:.1f} from CPU time "
                f"({'met' if m['fps'] >= r['goals']['cpu_fps_512'] else 'not met'}). No GPU was lent: the 800x600 GPU goal "
                "is unmeasured.", "", prov(r["provenance"]), ""]
    out += _photo_sizes(results / "mesh_fps_runs")
    out += _capture_meshes(results / "mesh_fps_runs")
    if q_file.is_file():
        r = json.loads(q_file.read_text())
        # the mesh path reads no volumetric render option: only the weights and the other config keys count
        out += stale_note("omnirecon-tiny", r.get("checkpoint"), "mesh_path", ignore=VOLUMETRIC_ONLY)
        times = sorted({t for row in r["rows"] for t in row["curve"]}, key=float)
        out += [f"Quality: held-out PSNR of the mesh path (images at {r['resolution']} px, at most 4 targets per scene, "
                "3 source views, the mesh of `python -m bench geometry`, cleaned with the source masks so it holds the objects "
                "only), before fine-tuning and after `omnirecon finetune` for the given seconds of optimisation "
                f"({r['rows'][0]['clock'] if r['rows'] else 'cpu'} clock: this process's CPU time, 1 thread). "
                "*Covered*: PSNR over the target pixels the mesh covers (inside the object mask): the appearance that "
                "fine-tuning can change. *Mask* and *image*: PSNR over the object mask and over the whole image, where "
                "pixels the mesh misses take the background colour, so they mostly measure the mesh's missing parts. "
                "Visibility: the object-mask PSNR before tuning without / with the per-source occlusion test.", "",
                "| scene | " + " | ".join(f"covered {t} s" for t in times) + " | covered gain 60 s | mask 0 -> 60 s | "
                "image 0 -> 60 s | no visibility test | visibility test | curve |", "|---|" + "---|" * (len(times) + 6)]
        gains = []
        for row in r["rows"]:
            c, cm, cc = row["curve"], row.get("curve_masked") or {}, row.get("curve_covered") or {}
            ref = cc or cm or c
            gain = ref.get("60", float("nan")) - ref["0"]
            gains.append(gain)
            v = row["visibility"]
            out.append(f"| {row['name']} | " + " | ".join(num(ref.get(t), 2) for t in times) + f" | {gain:+.2f} | "
                       + (f"{num(cm.get('0'), 2)} -> {num(cm.get('60'), 2)}" if cm else "–") + " | "
                       f"{num(c.get('0'), 2)} -> {num(c.get('60'), 2)} | "
                       f"{num(v.get('without_masked', v['without']), 2)} | {num(v.get('with_masked', v['with']), 2)} | "
                       f"[png](bench/results/{row['pictures']['curve']}) |")
        if gains:
            mean_gain = sum(gains) / len(gains)
            out += ["", f"Mean gain after 60 s (covered pixels): {mean_gain:+.2f} dB (goal +{r['goal_gain_db_60s']:.0f} dB: "
                    f"{'met' if mean_gain >= r['goal_gain_db_60s'] else 'not met'}).", "", prov(r["provenance"]), ""]
    return "\n".join(out)


# goals at the photos' own sizes (issue: >= 30 FPS at 504x378, >= 60 FPS at 336x252 on 2 cores)
PHOTO_GOALS = {(504, 378): 30.0, (336, 252): 60.0}


def _photo_sizes(runs: Path) -> list[str]:
    """Rows of the `quiet_*` runs of `python -m bench mesh_fps --size W H --threads 2 --out ...` (a quiet machine)."""
    files = sorted(runs.glob("quiet_*.json")) if runs.is_dir() else []
    if not files:
        return []
    out = ["At the photos' sizes on 2 cores, measured on a quiet machine (`python -m bench mesh_fps --size W H --threads 2 "
           "[--ckpt TUNED] --out bench/results/mesh_fps_runs/quiet_*.json`; TUNED is a `finetune --save` checkpoint). "
           "These rows draw the procedural scene's exact mesh, not a capture's own mesh: the goals are met for that mesh "
           "only (a capture's completed mesh, next table, has 20x the faces and renders several times slower):", "",
           "| weights | mesh | resolution | FPS (wall) | ms / frame | CPU ms / frame | with visibility test | goal | "
           "load (1 min) |", "|---|---|---|---|---|---|---|---|---|"]
    for f in files:
        r = json.loads(f.read_text())
        m = r["mesh"]
        w, h = m["resolution"]
        goal = PHOTO_GOALS.get((w, h))
        verdict = "–" if goal is None else (f">= {goal:.0f}: " + ("met" if min(m["fps"], m["visibility_fps"]) >= goal
                                                                   else "met without the visibility test"
                                                                   if m["fps"] >= goal else "not met"))
        sc = r["scene"]
        what = f"{sc.get('mesh', '?')}, {sc['faces']:,} faces" if "faces" in sc else sc.get("mesh", "?")
        out.append(f"| {r['model']['weights']} | {what} | {w}x{h} | {m['fps']:.1f} | {m['median_ms']:.1f} | "
                   f"{m['cpu_ms']:.1f} | {m['visibility_fps']:.1f} | {verdict} (this mesh) | "
                   f"{r['provenance'].get('loadavg_1min', '?')} |")
    out += ["", prov(json.loads(files[-1].read_text())["provenance"]), ""]
    return out


def _capture_meshes(runs: Path) -> list[str]:
    """Rows of the `mesh_*` runs of `python -m bench mesh_fps --scene S --mesh M --threads 1 --out ...`: a capture's
    own completed mesh (fills and backdrop included) at its photos' size, one core, beside other jobs (and the
    procedural exact mesh at the same size, `--size W H`, for scale)."""
    files = sorted(runs.glob("mesh_*.json")) if runs.is_dir() else []
    if not files:
        return []
    out = ["A capture's own mesh at its photos' size (`python -m bench mesh_fps --scene S --mesh M --threads 1 --frames 10 "
           "--out bench/results/mesh_fps_runs/mesh_*.json`; 1 thread, measured beside other jobs: compare the CPU ms "
           "within this table, not with the quiet rows above):", "",
           "| scene | mesh | faces | resolution | ms / frame | CPU ms / frame | depth pass CPU ms | with visibility test "
           "(ms) | load (1 min) |", "|---|---|---|---|---|---|---|---|---|"]
    for f in files:
        r = json.loads(f.read_text())
        m, sc = r["mesh"], r["scene"]
        w, h = m["resolution"]
        where = Path(sc["path"]).name if "path" in sc else f"procedural seed {sc.get('seed')}"
        what = f"{Path(sc['mesh']).parent.name}/{Path(sc['mesh']).name}" if "path" in sc else sc["mesh"]
        out.append(f"| {where} | {what} | "
                   f"{sc['faces']:,} | {w}x{h} | {m['median_ms']:.1f} | {m['cpu_ms']:.1f} | {m['depth_pass_cpu_ms']:.1f} | "
                   f"{m['visibility_median_ms']:.1f} | {r['provenance'].get('loadavg_1min', '?')} |")
    return out + ["", prov(json.loads(files[-1].read_text())["provenance"]), ""]
