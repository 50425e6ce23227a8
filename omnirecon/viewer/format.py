"""The viewer bundle's name and version, and the check ``omnirecon view`` runs before serving one (no torch here:
the server starts fast).

Versions: 1, a fixed set of sources (3 by default), the far fill, no source masks; 2 (:mod:`.bundle`), every
training view a source (the network blend takes each frame's nearest, the angle blend each point's nearest), the
sources' object masks in the images' alpha channel, the nearest fill and the crack fill (``MeshRenderer``'s real-time
setting), the source cameras in ``cameras.bin``.
"""

from __future__ import annotations

import json
from pathlib import Path

from omnirecon.errors import InputError

FORMAT = "omnirecon-viewer"
VERSION = 2


def check_bundle(folder: Path) -> dict:
    """``folder/bundle.json`` parsed, or a one-line :class:`InputError` when it is not a bundle of this
    :data:`VERSION` (unreadable, another format, an older or newer version)."""
    path = Path(folder) / "bundle.json"
    fix = "re-export it with this omnirecon: omnirecon export --scene SCENE --ckpt CKPT --mesh MESH --out DIR"
    try:
        meta = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(f"cannot read the viewer bundle ({type(e).__name__})", path, fix) from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise InputError(f"not an {FORMAT} bundle", path, fix)
    if meta.get("version") != VERSION:
        raise InputError(f"viewer bundle version {meta.get('version')!r}; this omnirecon reads version {VERSION}", path,
                         fix)
    return meta
