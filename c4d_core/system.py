"""Checks of the system libraries the project needs, with messages that say how to fix them."""

from __future__ import annotations

import ctypes.util
import os

from c4d_core.errors import UserError

EGL_HELP = (
    "install Mesa's EGL and GL drivers, e.g. on Debian/Ubuntu: "
    "`sudo apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri libgles2`"
)


def require_egl() -> None:
    """Select PyOpenGL's EGL platform and check that libEGL can be loaded.

    Must run before `pyrender` or `OpenGL` is imported. Raises `UserError` naming the fix.
    """
    platform = os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    if platform != "egl":
        raise UserError(
            f"PYOPENGL_PLATFORM is {platform!r}, but offscreen rendering needs 'egl': "
            "unset it or set PYOPENGL_PLATFORM=egl"
        )
    if ctypes.util.find_library("EGL") is None:
        raise UserError(f"libEGL was not found, so nothing can be rendered: {EGL_HELP}")
