"""Away from the photos: meshes made from the views a user would photograph, scored beyond them (issue 42).

    python -m bench extrapolation                                  # every scene, both surfaces (an hour or more)
    python -m bench extrapolation --scenes demo fox --surfaces coherent
    python -m bench extrapolation --tiny                           # the demo scene at 48 px (tests)

Per scene, the extrapolation split (:func:`omnirecon.engine.protocols.extrapolation_split`): the training views lie
within one arc of azimuth (at most 100 degrees; a walk: its first stretch), the test views 10-30 degrees beyond it (a
walk: its last stretch). The mesh is made from the training views alone with ``omnirecon mesh``'s defaults for the
scene kind (the depth maps are made once per scene and cached; each surface row meshes them), then rendered by the
real-time mesh path as ``reconstruct``'s video renders it (each frame's nearest training views, the scene kind's
blend and fill) at:

* the test views: PSNR against the photo (whole image; DTU also over the object mask), coverage, and the defect
  shares of :mod:`omnirecon.mesh.defects` (fill faces, faces no training view sees, fragments);
* the camera path a user watches (:func:`omnirecon.engine.extrapolation.user_path`: the photos' arc and 15 degrees
  past each end, 24 frames): defect shares, and on procedural scenes PSNR against the generator's exact images at
  those poses (:func:`omnirecon.data.synth.generate.render_cameras`).

Scenes: the demo's procedural scene (seed 900999) and three ``synth:eval`` seeds (48 views at 128 px pooled, no
masks, beside the exact mesh scored the same way); fox (no masks), ethiopianHead (without its masks), lego (its 100
training views, white background), dtu_scan24 (with its masks, as ``reconstruct`` meshes it) at the photos' size;
lund (29 street photos, walked out and back, posed by ``omnirecon process`` (:func:`posed_lund`) into ``outputs/cache/extrapolation/lund_scene`` on first use, at
a 512-px long side). Surfaces: ``fusion`` (the TSDF with completion's fills, the pipeline before this issue) and
``coherent`` (:mod:`omnirecon.mesh.surface`). A picture per row (test view: truth | render | defects; path: first and
worst frame) goes to ``bench/results/figures/extrapolation_<scene>_<surface>.png``.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
CACHE = ROOT / "outputs" / "cache" / "extrapolation"
PROCEDURAL = {"demo": 900_999, "synth_900998": 900_998, "synth_900997": 900_997, "synth_900000": 900_000}
REAL = {"fox": "instant_ngp/fox", "ethiopianHead": "llff/ethiopianHead", "lego": "blender/lego",
        "dtu_scan24": "neus_dtu/dtu_scan24", "lund": "photos/lund"}
SCENES = (*PROCEDURAL, *REAL)
SURFACES = ("fusion", "coherent")
MAX_TEST = 6
PATH_FRAMES = 24


def load(name: str, tiny: bool):
    """``(scene folder, scene, view pool, use masks)`` of a bench scene."""
    from omnirecon.data import detect_format
    from omnirecon.engine.protocols import protocol_for
    from omnirecon.engine.scenes import load_at_resolution, photo_side

    if name in PROCEDURAL:
        from omnirecon.data.synth.generate import SynthOptions, generate_scene

        res = 48 if tiny else 128
        path = generate_scene(CACHE / f"{name}_{res}", PROCEDURAL[name], SynthOptions(rig="object", views=48,
                                                                                      resolution=res))
        return path, load_at_resolution(path, res, None), None, False
    path = SHARED / REAL[name]
    if name == "lund":
        path = posed_lund(path)
    fmt = detect_format(path)
    scene = load_at_resolution(path, photo_side(path, fmt=fmt), protocol_for(path, fmt).background, fmt)
    pool = scene.splits.get("train") if name == "lego" else None
    return path, scene, pool, name.startswith("dtu")


def posed_lund(photos: Path) -> Path:
    """The street photos posed by ``omnirecon process --matcher sequential --max-features 4096`` (once; cached): the
    photos are a walk in capture order (the pose itself is not what this bench measures; "Pose recovery" is)."""
    scene = CACHE / "lund_scene"
    if not (scene / "sparse").is_dir():
        from omnirecon.capture.colmap_sfm import SfmOptions
        from omnirecon.capture.process import process

        process(photos, scene, SfmOptions(matcher="sequential", max_features=4096, threads=2))
    return scene


def cached_maps(name: str, scene, split, options, model, tiny: bool, masks: bool):
    """The depth maps of the split's training views (``options.depth``), cached per scene and split."""
    import hashlib

    from omnirecon.mesh.build import depth_maps

    key = f"{name}_{'tiny' if tiny else 'full'}_{options.depth}_{masks}_{'-'.join(map(str, split.train))}"
    f = CACHE / "maps" / f"{hashlib.sha1(key.encode()).hexdigest()[:16]}.pt"
    if f.is_file():
        blob = torch.load(f, weights_only=False)
        if blob.get("key") == key:
            return blob["maps"], blob["cpu_seconds"]
    cpu = time.process_time()
    maps = depth_maps(options, scene, split.train, model, masks=scene.masks if masks else None)
    cpu = time.process_time() - cpu
    f.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"key": key, "maps": maps, "cpu_seconds": cpu}, f)
    return maps, cpu


def mesh_options(scene, path: Path, surface: str, masks: bool, settings: dict | None = None):
    """``omnirecon mesh``'s options for the scene kind, with ``surface`` (and ``settings`` of the coherent surface:
    ``SurfaceOptions`` fields)."""
    from dataclasses import replace

    from omnirecon.workflows.mesh import MeshConfig

    options = MeshConfig(scene=path, masks=masks).mesh_options(scene, has_model=True)
    return replace(options, surface=surface, coherent=replace(options.coherent, **(settings or {})))


def picture(rows: list[np.ndarray], out: Path) -> str:
    from omnirecon.data.io import write_image

    h = max(r.shape[0] for r in rows)
    padded = [np.pad(r, ((0, h - r.shape[0]), (0, 0), (0, 0))) for r in rows]
    write_image(out, np.concatenate(padded, 1))
    out = Path(out).resolve()
    return str(out.relative_to(ROOT)) if out.is_relative_to(ROOT) else str(out)


def run_row(name: str, surface: str, model, tiny: bool, figures: Path, settings: dict | None = None,
            label: str | None = None) -> dict:
    from omnirecon.engine.extrapolation import procedural_truth, score_frames, user_path
    from omnirecon.engine.protocols import extrapolation_split
    from omnirecon.mesh.build import MeshResult, mesh_from_depths
    from omnirecon.mesh.defects import DefectCounter

    path, scene, pool, masks = load(name, tiny)
    split = extrapolation_split(scene, pool)
    test = split.test
    if len(test) > MAX_TEST:  # evenly over the distance beyond the arc
        order = np.argsort(split.beyond)
        test = [test[i] for i in order[np.unique(np.linspace(0, len(order) - 1, MAX_TEST).round().astype(int))]]
    cpu = time.process_time()
    if surface == "exact":
        from omnirecon.mesh.geometry import ground_truth_mesh

        made, maps_cpu = MeshResult(ground_truth_mesh(scene), {}, scene.cameras, torch.zeros(0)), 0.0
    else:
        options = mesh_options(scene, path, surface, masks, settings)
        maps, maps_cpu = cached_maps(name, scene, split, options, model, tiny, masks)
        made = mesh_from_depths(maps, scene, split.train, options, scene.masks if masks else None)
    mesh_cpu = time.process_time() - cpu
    fill_from = (made.info.get("completion") or {}).get("surface_faces") if surface == "fusion" else None
    truth = scene.images[test]
    held = score_frames(model, made.mesh, scene, split.train, scene.cameras[test], truth,
                        scene.masks[test] if masks else None, fill_from=fill_from, keep_images=True)
    cams, kind = user_path(scene, split.train, 8 if tiny else PATH_FRAMES)
    watched = score_frames(model, made.mesh, scene, split.train, cams,
                           procedural_truth(path, scene, cams), fill_from=fill_from,
                           keep_images=True)
    worst = watched.summary()["worst_frame"]
    with DefectCounter(made.mesh, scene.cameras[split.train], scene.bounds, fill_from) as counter:
        figure = picture([(truth[0].numpy() * 255 + 0.5).astype(np.uint8), held.images[0],
                          counter.picture(scene.cameras[test[0]]), watched.images[0], watched.images[worst],
                          counter.picture(cams[worst])], figures / f"extrapolation_{name}_{label or surface}.png")
    return {"scene": name, "surface": label or surface, "settings": settings or {}, "train": split.train, "test": test,
            "beyond": [split.beyond[split.test.index(v)] for v in test], "arc": split.arc, "kind": split.kind,
            "faces": len(made.mesh.faces), "held_out": held.summary(), "path": {"kind": kind, **watched.summary()},
            "path_frames": [{"defect": d["any"], **({"psnr": p} if p is not None else {})} for d, p in
                            zip(watched.defects, watched.psnr or [None] * len(watched.defects))],
            "cpu_seconds": {"depth_maps": round(maps_cpu, 2), "surface": round(mesh_cpu, 2)},
            "surface_record": made.info.get("surface"), "figure": figure}


def main(argv: list[str] | None = None) -> dict:
    from omnirecon.data.io import write_json
    from omnirecon.engine.checkpoint import load_checkpoint
    from omnirecon.provenance import provenance

    p = argparse.ArgumentParser(prog="python -m bench extrapolation", description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    p.add_argument("--surfaces", nargs="+", default=list(SURFACES), choices=[*SURFACES, "exact"])
    p.add_argument("--tiny", action="store_true", help="the demo scene at 48 px, 8 path frames (tests)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                   help="coherent rows: SurfaceOptions fields (e.g. reach=32); the rows are named coherent[...]")
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    model, _ = load_checkpoint(ROOT / "checkpoints" / "omnirecon-tiny")
    out_file = args.out / ("extrapolation_tiny.json" if args.tiny else "extrapolation.json")
    old = json.loads(out_file.read_text()) if out_file.is_file() else {"rows": []}
    result = {"provenance": provenance(seed=0), "rows": old.get("rows", [])}
    for name in (["demo"] if args.tiny else args.scenes):
        surfaces = [*args.surfaces, *(["exact"] if name in PROCEDURAL and "exact" not in args.surfaces else [])]
        settings = {k: json.loads(v) for k, v in (a.split("=", 1) for a in args.set)}
        for surface in surfaces:
            label = f"coherent[{','.join(args.set)}]" if surface == "coherent" and settings else surface
            row = {**run_row(name, surface, model, args.tiny, args.out / "figures", settings, label),
                   "commit": result["provenance"]["commit"], "loadavg_1min": os.getloadavg()[0]}
            result["rows"] = [r for r in result["rows"] if (r["scene"], r["surface"]) != (name, label)] + [row]
            h, w = row["held_out"], row["path"]
            print(f"{name:14s} {label:9s} held-out {h.get('psnr', float('nan')):6.2f} dB cov {h['coverage']:.2f} "
                  f"defects {h['defect_any']:.3f} | path {w.get('psnr', float('nan')):6.2f} dB defects "
                  f"{w['defect_any']:.3f} (worst {w['worst_defect']:.3f}) | {row['cpu_seconds']}", flush=True)
            write_json(out_file, result)
    return result


if __name__ == "__main__":
    main()
