"""A minimal static HTML page: headings, tables, pictures and videos, with relative links.

The reports are a folder that opens in any browser without a server, so pages only reference
files next to them. Text is escaped; fragments are plain strings joined in order.
"""

from __future__ import annotations

import html
import os
from collections.abc import Iterable, Sequence
from pathlib import Path

from c4d_core.files import write_text

_STYLE = """
body { font-family: sans-serif; margin: 1.5em; max-width: 1400px; color: #222; }
h1 { font-size: 1.5em; } h2 { font-size: 1.2em; margin-top: 1.6em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: 0.5em 0; }
td, th { border: 1px solid #ccc; padding: 2px 8px; text-align: left; font-size: 0.9em; }
img, video { max-width: 100%; image-rendering: pixelated; margin: 4px 0; display: block; }
.controls { margin: 0 0 4px 0; } .controls button { font-size: 0.85em; }
.bad { color: #b00; } .good { color: #070; } .note { color: #555; font-size: 0.9em; }
"""


MIN_VIDEO_WIDTH = 512  # CSS pixels a small video is enlarged to (integer factor)


def cell_text(value: object) -> str:
    """A value as a short table cell: floats to 4 significant digits, dicts as `key: value`
    pairs, long lists of numbers as their count and ends, None as n/a (never a raw repr)."""
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, dict):
        return ", ".join(f"{k}: {cell_text(v)}" for k, v in value.items())
    if isinstance(value, (list, tuple)):
        if len(value) > 6 and all(isinstance(v, (int, float)) for v in value):
            return f"{len(value)} values: {cell_text(value[0])} ... {cell_text(value[-1])}"
        return "[" + ", ".join(cell_text(v) for v in value) + "]"
    return "n/a" if value is None else str(value)


def text(value: object, css_class: str | None = None) -> str:
    """An escaped paragraph."""
    attr = f' class="{css_class}"' if css_class else ""
    return f"<p{attr}>{html.escape(str(value))}</p>"


def heading(value: str, level: int = 2) -> str:
    return f"<h{level}>{html.escape(value)}</h{level}>"


def table(rows: Iterable[Sequence[object]], header: Sequence[str] | None = None) -> str:
    """Rows of cells (escaped, formatted by `cell_text`) as an HTML table."""

    def cell(value: object) -> str:
        return html.escape(cell_text(value))

    parts = ["<table>"]
    if header:
        parts.append("<tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in header) + "</tr>")
    parts += ["<tr>" + "".join(f"<td>{cell(v)}</td>" for v in row) + "</tr>" for row in rows]
    parts.append("</table>")
    return "\n".join(parts)


def _relative(path: str | os.PathLike, page_dir: Path) -> str:
    return html.escape(Path(os.path.relpath(path, page_dir)).as_posix())


def image(path: str | os.PathLike, page_dir: Path, caption: str | None = None) -> str:
    """An <img> of a file, linked relative to the page's folder, with an optional caption."""
    src = _relative(path, page_dir)
    tag = f'<a href="{src}"><img src="{src}" alt="{html.escape(caption or src)}"></a>'
    return tag + (text(caption, "note") if caption else "")


def video(path: str | os.PathLike, page_dir: Path, caption: str | None = None) -> str:
    """A looping, muted, autoplaying <video> of a file relative to the page's folder (a GIF is
    shown as an image, which browsers animate)."""
    if Path(path).suffix.lower() == ".gif":
        return image(path, page_dir, caption)
    src = _relative(path, page_dir)
    # Small videos are enlarged by an integer factor to at least MIN_VIDEO_WIDTH pixels; the
    # controls sit below the picture, so they never hide part of it.
    enlarge = (f"var f=Math.max(1,Math.ceil({MIN_VIDEO_WIDTH}/this.videoWidth));"
               "this.style.width=Math.min(this.videoWidth*f,window.innerWidth-40)+'px'")
    toggle = "var v=this.parentNode.previousElementSibling;if(v.paused){v.play()}else{v.pause()}"
    step = "var v=this.parentNode.previousElementSibling;v.pause();v.currentTime+=VALUE"
    tag = (f'<video src="{src}" loop muted autoplay playsinline onloadedmetadata="{enlarge}"></video>'
           f'<div class="controls"><button onclick="{toggle}">play / pause</button> '
           f'<button onclick="{step.replace("VALUE", "-0.1")}">&#9664; frame</button> '
           f'<button onclick="{step.replace("VALUE", "0.1")}">frame &#9654;</button></div>')
    return tag + (text(caption, "note") if caption else "")


def write_page(path: str | os.PathLike, title: str, fragments: Iterable[str]) -> Path:
    """Write a complete HTML page (through a temporary file) and return its path."""
    path = Path(path)
    body = "\n".join(fragments)
    page = (
        "<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\">"
        f"<title>{html.escape(title)}</title><style>{_STYLE}</style></head>\n"
        f"<body><h1>{html.escape(title)}</h1>\n{body}\n</body></html>\n"
    )
    return write_text(path, page)
