"""The official IBRNet code against our ``ibrnet-paper`` at the same configuration, in one run.

    python bench/peer_ibrnet.py --ibrnet-root ~/src/IBRNet      # a checkout of googleinterns/IBRNet
    python bench/peer_ibrnet.py                                 # no checkout: our side only, the JSON says so

The project never contains IBRNet's code: the user provides a checkout (``git clone
https://github.com/googleinterns/IBRNet``; the code layout of commit 41807b2 and its ancestors:
``ibrnet/mlp_network.py`` ``IBRNet``, ``ibrnet/feature_network.py`` ``ResUNet``,
``ibrnet/projection.py`` ``Projector``, ``ibrnet/render_ray.py`` ``render_rays``,
``ibrnet/render_image.py`` ``render_single_image``, ``ibrnet/sample_ray.py``
``RaySamplerSingleImage``). Its hard-wired CUDA calls (``.cuda()``, ``.to("cuda:0")``) are mapped to
the CPU by a shim active only while its code runs; both sides get random weights (speed does not
depend on them) and the same parameter count (8,957,392).

Configuration (``configs/eval_llff.txt`` and the training defaults): ``--views`` source views of
``--width x --height``, 64 coarse + 64 importance samples, inverse-depth sampling, chunk 4096 rays
(theirs and ours: our ``render_view`` also sub-batches per its fast paths), anti-alias pooling; a
training step is one target view, ``--train-rays`` random rays, encode + coarse + fine + masked MSE
on both passes + backward + Adam(W) step. Each side runs in its own fresh child process (so that
peak RSS is its own), alternately ``--rounds`` times; the table keeps each side's best time and its
largest peak RSS. Writes ``bench/results/peer_ibrnet.json`` with a provenance header.
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


@contextlib.contextmanager
def cuda_to_cpu():
    """While active: ``Tensor.cuda``/``Module.cuda`` return the CPU object, ``.to("cuda...")`` goes to the CPU."""
    import torch

    saved = (torch.Tensor.cuda, torch.nn.Module.cuda, torch.Tensor.to)
    real_to = torch.Tensor.to

    def to(self, *args, **kwargs):
        args = tuple("cpu" if isinstance(a, (str, torch.device)) and str(a).startswith("cuda") else a for a in args)
        if "device" in kwargs and str(kwargs["device"]).startswith("cuda"):
            kwargs["device"] = "cpu"
        return real_to(self, *args, **kwargs)

    torch.Tensor.cuda = lambda self, *a, **k: self
    torch.nn.Module.cuda = lambda self, *a, **k: self
    torch.Tensor.to = to
    try:
        yield
    finally:
        torch.Tensor.cuda, torch.nn.Module.cuda, torch.Tensor.to = saved


def _camera_vector(cams, i: int):
    """IBRNet's 34-number camera: ``H, W``, the 4x4 intrinsics and the 4x4 camera-to-world, flattened."""
    import torch

    K = torch.eye(4)
    K[0, 0], K[1, 1], K[0, 2], K[1, 2] = cams.fx[i], cams.fy[i], cams.cx[i], cams.cy[i]
    head = torch.tensor([float(cams.height), float(cams.width)])
    return torch.cat([head, K.flatten(), cams.c2w[i].float().flatten()])


def run_peer(root: Path, args) -> dict:
    """Time the official code (in this process)."""
    import argparse as ap

    import numpy as np
    import torch

    sys.path.insert(0, str(root))
    views, w, h = args.views, args.width, args.height
    cams, images = scene(views, w, h)
    base = peak_rss_mb()
    with cuda_to_cpu():
        from ibrnet.feature_network import ResUNet
        from ibrnet.mlp_network import IBRNet
        from ibrnet.projection import Projector
        from ibrnet.render_image import render_single_image
        from ibrnet.render_ray import render_rays
        from ibrnet.sample_ray import RaySamplerSingleImage

        opts = ap.Namespace(anti_alias_pooling=1, local_rank=0, coarse_feat_dim=32, fine_feat_dim=32,
                            N_samples=64, N_importance=64, inv_uniform=True, chunk_size=args.chunk)
        torch.manual_seed(0)
        model = ap.Namespace(net_coarse=IBRNet(opts, in_feat_ch=32, n_samples=64),
                             net_fine=IBRNet(opts, in_feat_ch=32, n_samples=128),
                             feature_net=ResUNet(coarse_out_ch=32, fine_out_ch=32, coarse_only=False))
        nets = (model.net_coarse, model.net_fine, model.feature_net)
        params = sum(p.numel() for n in nets for p in n.parameters())
        projector = Projector(device="cpu")
        data = {"rgb": images[views:].float(), "camera": _camera_vector(cams, views)[None],
                "rgb_path": ["target"], "depth_range": torch.tensor([[args.near, args.far]]),
                "src_rgbs": images[None, :views].float(),
                "src_cameras": torch.stack([_camera_vector(cams, i) for i in range(views)])[None]}

        def render():
            for n in nets:
                n.eval()
            with torch.no_grad():
                sampler = RaySamplerSingleImage(data, "cpu")
                batch = sampler.get_all()
                featmaps = model.feature_net(batch["src_rgbs"].squeeze(0).permute(0, 3, 1, 2))
                render_single_image(sampler, batch, model, projector, args.chunk, 64, inv_uniform=True,
                                    N_importance=64, det=True, featmaps=featmaps)

        opt = torch.optim.Adam([{"params": model.net_coarse.parameters()}, {"params": model.net_fine.parameters()},
                                {"params": model.feature_net.parameters(), "lr": 1e-3}], lr=5e-4)
        np.random.seed(0)

        def mse(out, rgb):  # their criterion (utils.img2mse with the ray mask), without importing utils
            m = out["mask"].float()[..., None]
            return ((out["rgb"] - rgb) ** 2 * m).sum() / (m.sum() * 3 + 1e-8)

        def train_step():
            for n in nets:
                n.train()
            sampler = RaySamplerSingleImage(data, "cpu")
            batch = sampler.random_sample(args.train_rays, sample_mode="uniform")
            featmaps = model.feature_net(batch["src_rgbs"].squeeze(0).permute(0, 3, 1, 2))
            ret = render_rays(batch, model, featmaps, projector=projector, N_samples=64, inv_uniform=True,
                              N_importance=64, det=False)
            opt.zero_grad()
            loss = mse(ret["outputs_coarse"], batch["rgb"]) + mse(ret["outputs_fine"], batch["rgb"])
            loss.backward()
            opt.step()

        return _time_both(render, train_step, params, base, args)


def run_ours(args) -> dict:
    """Time ``ibrnet-paper`` (in this process) at the same configuration."""
    import torch

    from omnirecon.engine.losses import LossModule
    from omnirecon.models.fast import FAST, reference
    from omnirecon.models.registry import build_model
    from omnirecon.rays import Rays, Sources

    views = args.views
    cams, images = scene(views, args.width, args.height)
    base = peak_rss_mb()
    ctx = reference() if args.reference else contextlib.nullcontext()
    with ctx:
        torch.manual_seed(0)
        model = build_model("ibrnet-paper", {"num_views": views, "coarse_samples": 64, "fine_samples": 64})
        params = sum(p.numel() for p in model.parameters())
        src = Sources(images[:views], cams[list(range(views))], args.near, args.far, "forward")
        target = cams[[views]]
        rays = Rays.from_image(target)
        g = torch.Generator().manual_seed(0)
        rgb = images[views].reshape(-1, 3)

        def render():
            model.eval()
            with torch.no_grad():
                feats = model.encode(src)
            model.render_view(feats, target, chunk=args.chunk)

        loss_mod = LossModule(model, aux_weight=1.0)
        opt = torch.optim.AdamW(model.parameters(), lr=5e-4)

        def train_step():
            model.train()
            idx = torch.randperm(len(rays), generator=g)[:args.train_rays]
            loss, _, _ = loss_mod(src, rays[idx], rgb[idx])
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()

        out = _time_both(render, train_step, params, base, args)
    out["fast_paths"] = "reference twins" if args.reference else repr(FAST)
    return out


def _time_both(render, train_step, params: int, base_rss: float, args) -> dict:
    t0 = time.perf_counter()
    render()
    render_s = time.perf_counter() - t0
    render_rss = peak_rss_mb()
    train_step()  # warm-up
    times = []
    for _ in range(args.train_steps):
        t0 = time.perf_counter()
        train_step()
        times.append(time.perf_counter() - t0)
    return {"params": params, "render_s": round(render_s, 3), "train_step_s": round(min(times), 3),
            "train_step_s_all": [round(t, 3) for t in times], "render_peak_rss_mb": round(render_rss, 1),
            "peak_rss_mb": round(peak_rss_mb(), 1), "baseline_rss_mb": round(base_rss, 1)}


def check_root(root: Path) -> list[str]:
    """The files of the checkout we run; missing ones listed."""
    return [f for f in PEER_FILES if not (root / f).is_file()]


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ibrnet-root", type=Path, default=None, help="a checkout of googleinterns/IBRNet")
    parser.add_argument("--views", type=int, default=3, help="source views (eval_llff: 3 in the issue's runs)")
    parser.add_argument("--width", type=int, default=200)
    parser.add_argument("--height", type=int, default=150)
    parser.add_argument("--near", type=float, default=1.5)
    parser.add_argument("--far", type=float, default=4.5)
    parser.add_argument("--chunk", type=int, default=4096)
    parser.add_argument("--train-rays", type=int, default=500)
    parser.add_argument("--train-steps", type=int, default=2, help="timed steps after a warm-up (best kept)")
    parser.add_argument("--rounds", type=int, default=1, help="alternating rounds of child processes")
    parser.add_argument("--reference-too", action="store_true",
                        help="also time our reference twins (fast paths off) in the same run")
    parser.add_argument("--out", type=Path, default=HERE / "results" / "peer_ibrnet.json")
    parser.add_argument("--child", choices=["peer", "ours"], help=argparse.SUPPRESS)
    parser.add_argument("--reference", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        import torch

        torch.set_num_threads(1)
        res = run_peer(args.ibrnet_root, args) if args.child == "peer" else run_ours(args)
        print(json.dumps(res))
        return res

    from omnirecon.data.io import write_json
    from omnirecon.errors import InputError
    from omnirecon.provenance import provenance

    root = args.ibrnet_root.expanduser().resolve() if args.ibrnet_root else None
    if root is not None:
        missing = check_root(root)
        if missing:
            raise InputError(f"{root} is not an IBRNet checkout (missing {', '.join(missing)})", None,
                             "pass the folder of `git clone https://github.com/googleinterns/IBRNet`")
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1",
               PYTHONPATH=os.pathsep.join([str(HERE.parent), os.environ.get("PYTHONPATH", "")]))
    common = ["--views", str(args.views), "--width", str(args.width), "--height", str(args.height),
              "--near", str(args.near), "--far", str(args.far), "--chunk", str(args.chunk),
              "--train-rays", str(args.train_rays), "--train-steps", str(args.train_steps)]
    sides = ([("peer", ["--ibrnet-root", str(root)])] if root else []) + [("ours", [])]
    if args.reference_too:
        sides.append(("ours_reference", ["--reference"]))
    runs: dict[str, list[dict]] = {name: [] for name, _ in sides}
    for _ in range(args.rounds):
        for name, extra in sides:
            child = "peer" if name == "peer" else "ours"
            res = subprocess.run([sys.executable, __file__, "--child", child, *common, *extra], env=env,
                                 capture_output=True, text=True)
            if res.returncode:
                raise SystemExit(f"{name} failed:\n{res.stderr[-3000:]}")
            runs[name].append(json.loads(res.stdout.strip().splitlines()[-1]))
            print(name, runs[name][-1], flush=True)
    best = {name: {"params": rs[0]["params"], "render_s": min(r["render_s"] for r in rs),
                   "train_step_s": min(r["train_step_s"] for r in rs),
                   "peak_rss_mb": max(r["peak_rss_mb"] for r in rs),
                   "render_peak_rss_mb": max(r["render_peak_rss_mb"] for r in rs)} for name, rs in runs.items()}
    n_render = args.width * args.height
    for b in best.values():
        b["render_rays_per_s"] = round(n_render / b["render_s"], 1)
        b["train_rays_per_s"] = round(args.train_rays / b["train_step_s"], 1)
    ratios = None
    if "peer" in best:
        p, o = best["peer"], best["ours"]
        ratios = {"render_speedup": round(p["render_s"] / o["render_s"], 2),
                  "train_speedup": round(p["train_step_s"] / o["train_step_s"], 2),
                  "peak_rss_ratio": round(o["peak_rss_mb"] / p["peak_rss_mb"], 2)}
    result = {"provenance": provenance(seed=0, threads=1),
              "config": {k: getattr(args, k) for k in ("views", "width", "height", "near", "far", "chunk",
                                                       "train_rays", "train_steps", "rounds")}
              | {"samples": "64 + 64", "inverse_depth": True, "weights": "random"},
              "peer_root": str(root) if root else None,
              "peer_note": None if root else "no IBRNet checkout was given (--ibrnet-root)",
              "best": best, "ratios": ratios, "runs": runs,
              "loadavg_end": [round(x, 2) for x in os.getloadavg()]}
    write_json(args.out, result)
    print(json.dumps({"best": best, "ratios": ratios}, indent=1))
    return result


if __name__ == "__main__":
    main()
