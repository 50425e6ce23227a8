"""The official IBRNet code against our ``ibrnet-paper`` at the same configuration, in one run.

    python -m bench peer_ibrnet --ibrnet-root ../shared/peer/IBRNet --width 64 --height 48 --rounds 2 --reference-too
    python -m bench peer_ibrnet --ibrnet-root PATH --variant bf16 bf16_render=1   # one more of our sides
    python -m bench peer_ibrnet                                 # no checkout: our side only, the JSON says so
    python -m bench peer_ibrnet --ibrnet-root PATH --width 1008 --height 756 --views 10 --crop 64 32 \
        --train-steps 0 --reference-too --out bench/results/peer_ibrnet_eval.json   # its evaluation configuration
    python -m bench peer_ibrnet --ibrnet-root PATH --width 400 --height 300 --views 10 --crop 32 16 \
        --train-rays 500 --train-steps 1 --out bench/results/peer_ibrnet_train.json   # training: see below

The project never contains IBRNet's code: the user provides a checkout (``git clone
https://github.com/googleinterns/IBRNet``, commit 41807b2; ``pip install '.[bench]'`` for its option parser,
configargparse). The reference side runs that code as its own ``train.py`` and evaluation would: its
``config.py`` parser reads ``configs/eval_llff.txt`` (64 + 64 samples, inverse depth, chunk 4096), its
``IBRNetModel`` builds the networks, Adam and StepLR; a render is ``render_single_image`` on a
``RaySamplerSingleImage``; a training step is ``random_sample`` -> ``feature_net`` -> ``render_rays`` ->
masked MSE on both passes -> backward -> step. Its hard-wired CUDA calls (``.cuda()``, ``.to("cuda:0")`` on
tensors and modules) are mapped to the CPU by a shim active only while its code runs. Both sides get random
weights (speed does not depend on them) and have the same parameter count (8,957,392).

Each side runs in its own fresh child process (so that peak RSS is its own), one thread, alternately
``--rounds`` times; the table keeps each side's best wall and best process-CPU time and its largest peak
RSS. Ratios are of CPU seconds: on the shared cores a process's wall time is mostly the scheduler's.
With ``--reference-too`` our reference twins (every fast path off) run too and each of our sides' render
is scored against theirs (PSNR; bit-identical is recorded as ``None``). Writes
``bench/results/peer_ibrnet.json`` with a provenance header and the load average at start and end.

At the reference's evaluation configuration (``--width 1008 --height 756 --views 10``) a full view costs
hours of CPU per side: ``--crop W H`` renders a centred window of the target (the sources stay whole), each
side's encoder CPU seconds are recorded apart, and the full view is projected as encode + (window - encode)
x pixels / window pixels. ``--train-steps 0`` renders only (the reference's training step there needs more
than 11 GB). Its training configuration (10 sources of its 400x600 LLFF crop, 500 rays) passed 6 GB on the
reference side too; 10 sources of 400x300 (peak 5.3 GB) is the largest measured that fits a 6 GB share.

Size: the reference's driver, our side's driver and the alternating parent are one measurement.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
PEER_FILES = ("ibrnet/mlp_network.py", "ibrnet/feature_network.py", "ibrnet/projection.py", "ibrnet/render_ray.py",
              "ibrnet/render_image.py", "ibrnet/sample_ray.py")


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def scene(views: int, width: int, height: int, seed: int = 0):
    """``views`` source cameras and one target on an arc looking at the origin, random images (OpenCV)."""
    import torch

    from omnirecon.cameras import Cameras, look_at

    ang = torch.linspace(-0.4, 0.4, views + 1)
    eye = torch.stack([3 * torch.sin(ang), -3 * torch.cos(ang), 0.3 + 0 * ang], -1)
    c2w = look_at(eye, torch.zeros(3), torch.tensor([0, 0, 1.0]))
    f = torch.full((views + 1,), 1.1 * width)
    cams = Cameras(f, f, f * 0 + width / 2, f * 0 + height / 2, c2w, width, height)
    g = torch.Generator().manual_seed(seed)
    images = torch.rand(views + 1, height, width, 3, generator=g)
    return cams, images


def crop_target(cams, images, views: int, crop):
    """The target camera and image cut to a centred ``crop = (w, h)`` window (same focal, shifted principal
    point): the rays rendered are a part of the full view, the sources stay whole. ``crop=None``: the full view."""
    from omnirecon.cameras import Cameras

    if not crop:
        return cams[[views]], images[views]
    w, h = crop
    x0, y0 = (cams.width - w) // 2, (cams.height - h) // 2
    i = [views]
    t = Cameras(cams.fx[i], cams.fy[i], cams.cx[i] - x0, cams.cy[i] - y0, cams.c2w[i], w, h)
    return t, images[views, y0:y0 + h, x0:x0 + w]


@contextlib.contextmanager
def cuda_to_cpu():
    """While active: ``Tensor.cuda``/``Module.cuda`` return the CPU object and ``.to("cuda...")`` (a string or a
    ``torch.device``, on tensors and modules) goes to the CPU: the reference's hard-wired CUDA calls run here."""
    import torch

    saved = (torch.Tensor.cuda, torch.nn.Module.cuda, torch.Tensor.to, torch.nn.Module.to)
    real_to, real_module_to = torch.Tensor.to, torch.nn.Module.to

    def _cpu(args, kwargs):
        args = tuple("cpu" if isinstance(a, (str, torch.device)) and str(a).startswith("cuda") else a for a in args)
        if "device" in kwargs and str(kwargs["device"]).startswith("cuda"):
            kwargs = dict(kwargs, device="cpu")
        return args, kwargs

    def to(self, *args, **kwargs):
        args, kwargs = _cpu(args, kwargs)
        return real_to(self, *args, **kwargs)

    def module_to(self, *args, **kwargs):
        args, kwargs = _cpu(args, kwargs)
        return real_module_to(self, *args, **kwargs)

    torch.Tensor.cuda = lambda self, *a, **k: self
    torch.nn.Module.cuda = lambda self, *a, **k: self
    torch.Tensor.to, torch.nn.Module.to = to, module_to
    try:
        yield
    finally:
        torch.Tensor.cuda, torch.nn.Module.cuda, torch.Tensor.to, torch.nn.Module.to = saved


def _camera_vector(cams, i: int):
    """IBRNet's 34-number camera: ``H, W``, the 4x4 intrinsics and the 4x4 camera-to-world, flattened."""
    import torch

    K = torch.eye(4)
    K[0, 0], K[1, 1], K[0, 2], K[1, 2] = cams.fx[i], cams.fy[i], cams.cx[i], cams.cy[i]
    head = torch.tensor([float(cams.height), float(cams.width)])
    return torch.cat([head, K.flatten(), cams.c2w[i].float().flatten()])


def run_peer(root: Path, args) -> dict:
    """Time the official code (in this process): its own option parser reading ``configs/eval_llff.txt``, its
    ``IBRNetModel`` (networks, Adam with its two learning rates, StepLR), ``render_single_image`` for a view and
    its training step (``RaySamplerSingleImage.random_sample`` -> ``render_rays`` -> masked MSE on both passes ->
    backward -> step)."""
    import tempfile

    import numpy as np
    import torch

    sys.path.insert(0, str(root))
    views, w, h = args.views, args.width, args.height
    cams, images = scene(views, w, h)
    target, target_rgb = crop_target(cams, images, views, args.crop)
    base = peak_rss_mb()
    with cuda_to_cpu(), tempfile.TemporaryDirectory() as tmp:
        from config import config_parser
        from ibrnet.model import IBRNetModel
        from ibrnet.projection import Projector
        from ibrnet.render_image import render_single_image
        from ibrnet.render_ray import render_rays
        from ibrnet.sample_ray import RaySamplerSingleImage

        opts = config_parser().parse_args(["--config", str(root / "configs" / "eval_llff.txt"), "--rootdir", tmp,
                                           "--ckpt_path", "", "--no_reload", "--chunk_size", str(args.chunk),
                                           "--N_samples", "64", "--N_importance", "64"])
        torch.manual_seed(0)
        with contextlib.redirect_stdout(sys.stderr):  # it prints "No ckpts found" (stdout carries our JSON)
            model = IBRNetModel(opts, load_opt=False, load_scheduler=False)
        nets = (model.net_coarse, model.net_fine, model.feature_net)
        params = sum(p.numel() for n in nets for p in n.parameters())
        projector = Projector(device="cpu")
        data = {"rgb": target_rgb[None].float(), "camera": _camera_vector(target, 0)[None],
                "rgb_path": ["target"], "depth_range": torch.tensor([[args.near, args.far]]),
                "src_rgbs": images[None, :views].float(),
                "src_cameras": torch.stack([_camera_vector(cams, i) for i in range(views)])[None]}
        rendered = {}

        def render():
            model.switch_to_eval()
            with torch.no_grad():
                sampler = RaySamplerSingleImage(data, "cpu")
                batch = sampler.get_all()
                c0 = time.process_time()
                featmaps = model.feature_net(batch["src_rgbs"].squeeze(0).permute(0, 3, 1, 2))
                rendered["encode_cpu_s"] = time.process_time() - c0
                out = render_single_image(sampler, batch, model, projector, opts.chunk_size, opts.N_samples,
                                          inv_uniform=opts.inv_uniform, N_importance=opts.N_importance, det=True,
                                          white_bkgd=opts.white_bkgd, featmaps=featmaps)
            rendered["rgb"] = out["outputs_fine"]["rgb"]

        np.random.seed(0)

        def mse(out, rgb):  # the training criterion: squared error over the rays the mask keeps, per channel
            m = out["mask"].float()[..., None]
            return ((out["rgb"] - rgb) ** 2 * m).sum() / (m.sum() * 3 + 1e-8)

        def train_step():
            model.switch_to_train()
            sampler = RaySamplerSingleImage(data, "cpu")
            batch = sampler.random_sample(args.train_rays, sample_mode=opts.sample_mode, center_ratio=opts.center_ratio)
            featmaps = model.feature_net(batch["src_rgbs"].squeeze(0).permute(0, 3, 1, 2))
            ret = render_rays(batch, model, featmaps, projector=projector, N_samples=opts.N_samples,
                              inv_uniform=opts.inv_uniform, N_importance=opts.N_importance, det=False,
                              white_bkgd=opts.white_bkgd)
            model.optimizer.zero_grad()
            loss = mse(ret["outputs_coarse"], batch["rgb"]) + mse(ret["outputs_fine"], batch["rgb"])
            loss.backward()
            model.optimizer.step()
            model.scheduler.step()

        out = _time_both(render, train_step, params, base, args, rendered)
    _save_render(args, rendered["rgb"].reshape(target.height, target.width, 3))
    return out


def _save_render(args, rgb) -> None:
    """The rendered image (``--save-render``) for the parent's PSNR between sides."""
    if args.save_render:
        import numpy as np

        np.save(args.save_render, rgb.detach().float().cpu().numpy())


def run_ours(args) -> dict:
    """Time ``ibrnet-paper`` (in this process) at the same configuration; fast-path switches from
    ``OMNIRECON_FAST`` (the parent sets it per side), every reference twin with ``--reference``."""
    import torch

    from omnirecon.engine.losses import LossModule
    from omnirecon.models.fast import FAST, reference
    from omnirecon.models.registry import build_model
    from omnirecon.rays import Rays, Sources

    views = args.views
    cams, images = scene(views, args.width, args.height)
    base = peak_rss_mb()
    ctx = reference() if args.reference else contextlib.nullcontext()
    rendered = {}
    with ctx:
        torch.manual_seed(0)
        model = build_model("ibrnet-paper", {"num_views": views, "coarse_samples": 64, "fine_samples": 64}
                            | ({"render_coarse_samples": args.render_samples[0], "render_fine_samples": args.render_samples[1]}
                               if args.render_samples else {}))
        params = sum(p.numel() for p in model.parameters())
        src = Sources(images[:views], cams[list(range(views))], args.near, args.far, "forward")
        target, target_rgb = crop_target(cams, images, views, args.crop)
        rays = Rays.from_image(target)
        g = torch.Generator().manual_seed(0)
        rgb = target_rgb.reshape(-1, 3)

        def render():
            model.eval()
            with torch.no_grad():
                c0 = time.process_time()
                feats = model.encode(src)
                rendered["encode_cpu_s"] = time.process_time() - c0
            rendered["rgb"] = model.render_view(feats, target, chunk=args.chunk)["rgb"]

        loss_mod = LossModule(model, aux_weight=1.0)
        opt = torch.optim.AdamW(model.parameters(), lr=5e-4)

        def train_step():
            model.train()
            idx = torch.randperm(len(rays), generator=g)[:args.train_rays]
            loss, _, _ = loss_mod(src, rays[idx], rgb[idx])
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()

        out = _time_both(render, train_step, params, base, args, rendered)
        out["fast_paths"] = "reference twins" if args.reference else repr(FAST)
    _save_render(args, rendered["rgb"])
    return out


def _time_both(render, train_step, params: int, base_rss: float, args, rendered: dict) -> dict:
    """Wall and process CPU seconds (one thread: CPU time is what the work costs, whatever else shares the
    cores) of ``--renders`` renders and ``--train-steps`` training steps after a warm-up; best of each kept."""
    renders, renders_cpu, encodes = [], [], []
    for _ in range(args.renders):
        t0, c0 = time.perf_counter(), time.process_time()
        render()
        renders.append(time.perf_counter() - t0)
        renders_cpu.append(time.process_time() - c0)
        encodes.append(rendered["encode_cpu_s"])
    render_rss = peak_rss_mb()
    if args.train_steps == 0:  # render only (e.g. where a training step does not fit in memory)
        return {"params": params, "render_s": round(min(renders), 3), "render_first_s": round(renders[0], 3),
                "render_cpu_s": round(min(renders_cpu), 3),
                "encode_cpu_s": round(encodes[renders_cpu.index(min(renders_cpu))], 3),
                "render_peak_rss_mb": round(render_rss, 1), "peak_rss_mb": round(peak_rss_mb(), 1),
                "baseline_rss_mb": round(base_rss, 1)}
    train_step()  # warm-up
    times, cpu = [], []
    for _ in range(args.train_steps):
        t0, c0 = time.perf_counter(), time.process_time()
        train_step()
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return {"params": params, "render_s": round(min(renders), 3), "render_first_s": round(renders[0], 3),
            "render_cpu_s": round(min(renders_cpu), 3), "encode_cpu_s": round(encodes[renders_cpu.index(min(renders_cpu))], 3),
            "train_step_s": round(min(times), 3),
            "train_step_cpu_s": round(min(cpu), 3), "train_step_s_all": [round(t, 3) for t in times],
            "render_peak_rss_mb": round(render_rss, 1), "peak_rss_mb": round(peak_rss_mb(), 1),
            "baseline_rss_mb": round(base_rss, 1)}


def check_root(root: Path) -> list[str]:
    """The files of the checkout we run; missing ones listed."""
    return [f for f in PEER_FILES if not (root / f).is_file()]


def _psnr(a_path: Path, b_path: Path) -> float | None:
    import numpy as np

    a, b = np.load(a_path), np.load(b_path)
    mse = float(((a.astype(np.float64) - b) ** 2).mean())
    return round(10 * np.log10(1.0 / mse), 2) if mse > 0 else None  # None: bit-identical


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ibrnet-root", type=Path, default=None, help="a checkout of googleinterns/IBRNet")
    parser.add_argument("--views", type=int, default=3, help="source views (eval_llff: 3 in the issue's runs)")
    parser.add_argument("--width", type=int, default=200)
    parser.add_argument("--height", type=int, default=150)
    parser.add_argument("--crop", type=int, nargs=2, default=None, metavar=("W", "H"),
                        help="render only a centred W x H window of the target (sources stay whole); the full "
                             "view's CPU seconds are projected as encode + (render - encode) x pixels / window")
    parser.add_argument("--near", type=float, default=1.5)
    parser.add_argument("--far", type=float, default=4.5)
    parser.add_argument("--chunk", type=int, default=4096)
    parser.add_argument("--train-rays", type=int, default=512, help="rays per training step (IBRNet's N_rand)")
    parser.add_argument("--train-steps", type=int, default=2, help="timed steps after a warm-up (best kept); 0: render only")
    parser.add_argument("--renders", type=int, default=1, help="renders per process (the first is the cold start)")
    parser.add_argument("--rounds", type=int, default=1, help="alternating rounds of child processes")
    parser.add_argument("--reference-too", action="store_true",
                        help="also time our reference twins (fast paths off) in the same run; PSNR of each of our "
                             "sides to it")
    parser.add_argument("--variant", nargs=2, action="append", default=[], metavar=("NAME", "SWITCHES"),
                        help="one more of our sides with OMNIRECON_FAST=SWITCHES (e.g. bf16 bf16_render=1); an item "
                             "samples=C+F renders C + F samples standing for the trained 64 + 64 (render_coarse_samples)")
    parser.add_argument("--render-samples", type=int, nargs=2, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--out", type=Path, default=HERE / "results" / "peer_ibrnet.json")
    parser.add_argument("--child", choices=["peer", "ours"], help=argparse.SUPPRESS)
    parser.add_argument("--reference", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--save-render", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        import torch

        torch.set_num_threads(1)
        res = run_peer(args.ibrnet_root, args) if args.child == "peer" else run_ours(args)
        print(json.dumps(res))
        return res

    import tempfile

    from omnirecon.data.io import write_json
    from omnirecon.errors import InputError
    from omnirecon.provenance import provenance

    root = args.ibrnet_root.expanduser().resolve() if args.ibrnet_root else None
    if root is not None:
        missing = check_root(root)
        if missing:
            raise InputError(f"{root} is not an IBRNet checkout (missing {', '.join(missing)})", None,
                             "pass the folder of `git clone https://github.com/googleinterns/IBRNet`")
    base_env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1",
                    PYTHONPATH=os.pathsep.join([str(HERE.parent), os.environ.get("PYTHONPATH", "")]))
    base_env.pop("OMNIRECON_FAST", None)
    common = ["--views", str(args.views), "--width", str(args.width), "--height", str(args.height),
              "--near", str(args.near), "--far", str(args.far), "--chunk", str(args.chunk),
              "--train-rays", str(args.train_rays), "--train-steps", str(args.train_steps),
              "--renders", str(args.renders)] + (["--crop", *map(str, args.crop)] if args.crop else [])
    # (name, child, extra arguments, OMNIRECON_FAST)
    sides = ([("peer", "peer", ["--ibrnet-root", str(root)], "")] if root else []) + [("ours", "ours", [], "")]
    for name, spec in args.variant:  # samples=C+F is a render option of the model, the rest are switches
        items = [x for x in spec.split(",") if x]
        counts = [x.partition("=")[2].split("+") for x in items if x.startswith("samples=")]
        extra = ["--render-samples", *counts[0]] if counts else []
        sides.append((name, "ours", extra, ",".join(x for x in items if not x.startswith("samples="))))
    if args.reference_too:
        sides.append(("ours_reference", "ours", ["--reference"], ""))
    runs: dict[str, list[dict]] = {name: [] for name, *_ in sides}
    load_start = [round(x, 2) for x in os.getloadavg()]
    renders = Path(tempfile.mkdtemp(prefix="peer_ibrnet_"))
    for _ in range(args.rounds):
        for name, child, extra, spec in sides:
            env = dict(base_env, OMNIRECON_FAST=spec) if spec else base_env
            save = ["--save-render", str(renders / f"{name}.npy")]
            res = subprocess.run([sys.executable, "-m", "bench", "peer_ibrnet", "--child", child, *common, *extra, *save], env=env,
                                 capture_output=True, text=True)
            if res.returncode:
                raise SystemExit(f"{name} failed:\n{res.stderr[-3000:]}")
            label = "reference twins" if "--reference" in extra else \
                " ".join([spec or "defaults", *(extra if child == "ours" else [])])
            runs[name].append(json.loads(res.stdout.strip().splitlines()[-1]) | {"switches": label})
            print(name, runs[name][-1], flush=True)
    best = {name: {"params": rs[0]["params"], "switches": rs[0]["switches"],
                   "render_s": min(r["render_s"] for r in rs),
                   "render_first_s": min(r["render_first_s"] for r in rs),
                   "train_step_s": min((r["train_step_s"] for r in rs if "train_step_s" in r), default=None),
                   "render_cpu_s": min(r["render_cpu_s"] for r in rs),
                   "encode_cpu_s": min(r["encode_cpu_s"] for r in rs),
                   "train_step_cpu_s": min((r["train_step_cpu_s"] for r in rs if "train_step_cpu_s" in r), default=None),
                   "peak_rss_mb": max(r["peak_rss_mb"] for r in rs),
                   "render_peak_rss_mb": max(r["render_peak_rss_mb"] for r in rs)} for name, rs in runs.items()}
    n_full = args.width * args.height
    n_render = args.crop[0] * args.crop[1] if args.crop else n_full
    for name, b in best.items():  # per CPU second (one thread)
        b["render_rays_per_s"] = round((n_render / (b["render_cpu_s"] - b["encode_cpu_s"])) if args.crop
                                       else n_render / b["render_cpu_s"], 1)  # a window: rays past the encoder
        b["full_view_cpu_s"] = (round(b["encode_cpu_s"] + (b["render_cpu_s"] - b["encode_cpu_s"]) * n_full / n_render, 1)
                                if args.crop else b["render_cpu_s"])  # no window: the view itself
        b["train_rays_per_s"] = round(args.train_rays / b["train_step_cpu_s"], 1) if args.train_steps else None
        if "ours_reference" in best and name not in ("peer", "ours_reference"):  # every side of ours
            b["psnr_to_reference_db"] = _psnr(renders / f"{name}.npy", renders / "ours_reference.npy")
    ratios = None
    if "peer" in best:
        p = best["peer"]
        ratios = {name: {"render_speedup": round(p["full_view_cpu_s"] / o["full_view_cpu_s"], 2),
                         "window_render_speedup": round(p["render_cpu_s"] / o["render_cpu_s"], 2),
                         "train_speedup": round(p["train_step_cpu_s"] / o["train_step_cpu_s"], 2) if args.train_steps
                         else None,
                         "render_speedup_wall": round(p["render_s"] / o["render_s"], 2),
                         "train_speedup_wall": round(p["train_step_s"] / o["train_step_s"], 2) if args.train_steps
                         else None,
                         "peak_rss_ratio": round(o["peak_rss_mb"] / p["peak_rss_mb"], 2),
                         "render_peak_rss_ratio": round(o["render_peak_rss_mb"] / p["render_peak_rss_mb"], 2)}
                  for name, o in best.items() if name != "peer"}
    import shutil

    shutil.rmtree(renders, ignore_errors=True)
    result = {"provenance": provenance(seed=0, threads=1),
              "config": {k: getattr(args, k) for k in ("views", "width", "height", "near", "far", "chunk",
                                                       "train_rays", "train_steps", "renders", "rounds", "crop")}
              | {"samples": "64 + 64", "inverse_depth": True, "weights": "random (seed 0)",
                 "peer_config": "configs/eval_llff.txt through its own config.py"},
              "peer_root": str(root) if root else None,
              "peer_note": None if root else "no IBRNet checkout was given (--ibrnet-root)",
              "best": best, "ratios": ratios, "runs": runs,
              "loadavg_start": load_start,
              "loadavg_end": [round(x, 2) for x in os.getloadavg()]}
    write_json(args.out, result)
    print(json.dumps({"best": best, "ratios": ratios}, indent=1))
    return result
