"""The viewer page: one self-contained HTML file, opened offline, from a file or a local server.

`build_page(payload)` fills `assets/view.html` with the payload of `scene_data.encode` (the JSON
header in a `<script type="application/json">`, the typed arrays base64-encoded in a second
script element) and the viewer `assets/view.js`, an ES module importing three.js. three.js
(`assets/three/`, vendored from the npm registry: VENDORED.md) reaches the module through the
page's import map as `data:` URLs, so the page loads nothing from anywhere.

When the scene is drawn, the page sets `data-c4d-state="ready"` on <html> (or "error", with the
message in the title) and exposes `window.c4dView`: `stats` (frame, points, dynamicPoints,
cameras, gtCameras, trackSegments drawn now), `setFrame(t)`, `play()`, `pause()`.
"""

from __future__ import annotations

import base64
import html
import json
from importlib import resources
from string import Template

from c4d.view.scene_data import Payload

MODULES = {  # import-map specifier -> vendored file under assets/three/
    "three": "three.module.min.js",
    "three/addons/controls/OrbitControls.js": "OrbitControls.js",
}


def _asset(name: str) -> str:
    return resources.files("c4d.view").joinpath("assets", name).read_text(encoding="utf-8")


def _script_text(text: str) -> str:
    """`text` safe inside a <script> element (no `</script` can end it early)."""
    return text.replace("</", "<\\/")


def page_overhead(title: str) -> int:
    """Bytes of the page (UTF-8) besides its header and payload: the HTML, three.js and the viewer."""
    return len(build_page(Payload({"title": title}, b"")).encode("utf-8"))


def build_page(payload: Payload) -> str:
    """The whole page (HTML text) showing `payload`."""
    imports = {name: "data:text/javascript;base64," + base64.b64encode(
        _asset(f"three/{file}").encode("utf-8")).decode("ascii") for name, file in MODULES.items()}
    return Template(_asset("view.html")).substitute(
        title=html.escape(payload.header["title"]),
        import_map=_script_text(json.dumps({"imports": imports})),
        header=_script_text(json.dumps(payload.header, separators=(",", ":"))),
        payload=base64.b64encode(payload.data).decode("ascii"),
        viewer=_script_text(_asset("view.js")),
    )
