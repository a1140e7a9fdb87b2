"""`c4d view`: a reconstruction or a generated scene as an interactive 4D view in the browser.

`scene_data` builds what is shown and encodes it compactly, `page` writes the self-contained page
(three.js vendored under `assets/three/`), `browser` drives headless Chromium (screenshots, the
browser tests), `cli` is the command.
"""
