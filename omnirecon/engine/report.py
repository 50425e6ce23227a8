"""Static HTML report pages: sections of text, tables and pictures, linked relatively.

A report is a folder with ``index.html`` and the files it shows; every path in it is relative to
that folder, so the folder can be moved, zipped or served as it is. Written atomically.
"""

from __future__ import annotations

import html
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from torch import Tensor

from omnirecon.data.io import atomic_path, write_image

STYLE = """
body { font-family: system-ui, sans-serif; max-width: 1100px; margin: 2em auto; padding: 0 1em; color: #222; }
h1 { margin-bottom: 0.2em; } h2 { border-bottom: 1px solid #ddd; padding-bottom: 0.2em; margin-top: 1.6em; }
table { border-collapse: collapse; margin: 0.6em 0; font-size: 0.92em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: right; } th { background: #f4f4f4; }
td:first-child, th:first-child { text-align: left; }
figure { display: inline-block; margin: 0.4em 0.8em 0.4em 0; vertical-align: top; }
figure img, figure video { max-width: 100%; image-rendering: pixelated; border: 1px solid #ddd; }
figcaption { font-size: 0.85em; color: #555; max-width: 420px; }
.note { color: #666; font-size: 0.9em; } code { background: #f4f4f4; padding: 0 0.2em; }
"""


@dataclass
class Section:
    """One ``<h2>`` section of a report."""

    title: str
    """Heading."""
    parts: list[str] = field(default_factory=list)
    """HTML fragments, in order (built with :meth:`text`, :meth:`table`, :meth:`figure`)."""

    def text(self, words: str, css: str = "") -> "Section":
        """A paragraph of plain text (escaped)."""
        self.parts.append(f"<p{f' class={css!r}' if css else ''}>{html.escape(words)}</p>")
        return self

    def table(self, header: list[str], rows: list[list]) -> "Section":
        """A table; cells are escaped; floats are shown with 4 significant digits."""
        def cell(v) -> str:
            return html.escape(f"{v:.4g}" if isinstance(v, float) else str(v))

        head = "".join(f"<th>{cell(h)}</th>" for h in header)
        body = "".join("<tr>" + "".join(f"<td>{cell(c)}</td>" for c in r) + "</tr>" for r in rows)
        self.parts.append(f"<table><tr>{head}</tr>{body}</table>")
        return self

    def figure(self, path: Path, root: Path, caption: str = "", width: int | None = None) -> "Section":
        """A picture, GIF or MP4 at ``path`` (inside ``root``), linked relatively, with a caption."""
        rel = Path(path).resolve().relative_to(Path(root).resolve()).as_posix()
        size = f' width="{width}"' if width else ""
        if rel.endswith(".mp4"):
            media = f'<video src="{html.escape(rel)}"{size} autoplay loop muted playsinline controls></video>'
        else:
            media = f'<a href="{html.escape(rel)}"><img src="{html.escape(rel)}"{size} alt="{html.escape(caption)}"></a>'
        self.parts.append(f"<figure>{media}<figcaption>{html.escape(caption)}</figcaption></figure>")
        return self

    def link(self, path: Path, root: Path, label: str) -> "Section":
        """A link to a file in the report folder."""
        rel = Path(path).resolve().relative_to(Path(root).resolve()).as_posix()
        self.parts.append(f'<p><a href="{html.escape(rel)}">{html.escape(label)}</a></p>')
        return self


def write_report(folder: Path, title: str, sections: list[Section], footer: str = "") -> Path:
    """Write ``folder/index.html`` with ``sections``; returns its path."""
    body = "".join(f"<h2>{html.escape(s.title)}</h2>{''.join(s.parts)}" for s in sections)
    page = (f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
            f"<style>{STYLE}</style></head><body><h1>{html.escape(title)}</h1>{body}"
            f"<p class='note'>{html.escape(footer)}</p></body></html>")
    path = Path(folder) / "index.html"
    with atomic_path(path) as tmp:
        tmp.write_text(page)
    return path


def save_val_picture(path: Path, rows: list[tuple[Tensor, Tensor]], max_err: float = 0.25) -> None:
    """One row per view: ground truth | render | absolute error (mean over RGB, inferno, 0..``max_err``)."""
    from matplotlib import colormaps

    cmap = colormaps["inferno"]
    lines = []
    for gt, pred in rows:
        err = (pred - gt).abs().mean(-1).numpy() / max_err  # [H, W]
        heat = cmap(np.clip(err, 0, 1))[..., :3].astype(np.float32)
        sep = np.ones((gt.shape[0], 2, 3), np.float32)
        lines.append(np.concatenate([gt.numpy(), sep, pred.numpy(), sep, heat], 1))
    width = max(line.shape[1] for line in lines)
    pic = np.concatenate([np.pad(line, ((0, 2), (0, width - line.shape[1]), (0, 0)), constant_values=1)
                          for line in lines], 0)
    write_image(path, pic)
