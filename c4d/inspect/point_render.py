"""A z-buffered point splatter in numpy, and camera paths for fly-throughs of a 4D point cloud.

Points are projected with the project's camera geometry (OpenCV axes, camera-to-world poses,
pixel centres at integer coordinates) and drawn as squares of (2r+1)^2 pixels; where several
land on a pixel, the nearest wins. No OpenGL, so it runs anywhere and is deterministic.
"""

from __future__ import annotations

import numpy as np

from c4d_core import geometry

NEAR = 1e-3  # points closer to the camera than this (scene units) are not drawn


def render_points(
    points: np.ndarray,
    colors: np.ndarray,
    intrinsics: np.ndarray,
    cam_to_world: np.ndarray,
    size: tuple[int, int],
    radius: int = 1,
    background: tuple[int, int, int] = (255, 255, 255),
) -> np.ndarray:
    """Splat world points (M,3) with RGB uint8 colours (M,3) into an (H,W,3) uint8 image.

    `intrinsics` (3,3) and `cam_to_world` (4,4) describe the virtual camera, `size` is (H, W),
    `radius` the half-size of each square splat in pixels. Non-finite points are skipped.
    """
    height, width = size
    image = np.empty((height * width, 3), np.uint8)
    image[:] = background
    points = np.asarray(points, np.float64).reshape(-1, 3)
    colors = np.asarray(colors, np.uint8).reshape(-1, 3)
    keep = np.isfinite(points).all(axis=1)
    uv, z = geometry.project(points[keep], intrinsics, cam_to_world)  # (M,2), (M,)
    colors = colors[keep]
    front = z > NEAR
    uv, z, colors = uv[front], z[front], colors[front]
    pixel = np.round(uv).astype(np.int64)  # (M,2) nearest pixel centre
    inside = (pixel[:, 0] >= 0) & (pixel[:, 0] < width) & (pixel[:, 1] >= 0) & (pixel[:, 1] < height)
    flat = pixel[inside, 1] * width + pixel[inside, 0]  # (M',)
    z, colors = z[inside], colors[inside]

    # z-buffer of the centre pixels: the nearest point of every pixel
    zbuf = np.full(height * width, np.inf)
    np.minimum.at(zbuf, flat, z)
    nearest = z <= zbuf[flat]  # (M',) the winners (equal depths: any of them)
    cbuf = image.copy()
    cbuf[flat[nearest]] = colors[nearest]

    # square splats: every pixel takes the nearest centre within `radius` pixels (a min filter)
    pad = ((radius, radius), (radius, radius))
    zpad = np.pad(zbuf.reshape(height, width), pad, constant_values=np.inf)
    cpad = np.pad(cbuf.reshape(height, width, 3), pad + ((0, 0),))
    best_z = np.full((height, width), np.inf)
    out = image.reshape(height, width, 3)
    for dy in range(2 * radius + 1):
        for dx in range(2 * radius + 1):
            z_shift = zpad[dy : dy + height, dx : dx + width]
            closer = z_shift < best_z
            best_z[closer] = z_shift[closer]
            out[closer] = cpad[dy : dy + height, dx : dx + width][closer]
    return out


def orbit_path(
    center: np.ndarray,
    start_eye: np.ndarray,
    up: np.ndarray,
    num_views: int,
    sweep_deg: float,
) -> np.ndarray:
    """Camera-to-world poses (V,4,4) swinging from `start_eye` around `center` about the `up` axis.

    The azimuth goes from 0 to +sweep/2, back through 0 to -sweep/2 and back to 0 (a smooth
    cosine sweep), always looking at `center`, without roll with respect to `up`.
    """
    center, start_eye = np.asarray(center, np.float64), np.asarray(start_eye, np.float64)
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    angles = np.deg2rad(sweep_deg / 2) * np.sin(np.linspace(0, 2 * np.pi, num_views, endpoint=False))
    offset = start_eye - center
    poses = []
    for angle in angles:  # Rodrigues rotation of the offset about `up`
        cos, sin = np.cos(angle), np.sin(angle)
        rotated = offset * cos + np.cross(up, offset) * sin + up * np.dot(up, offset) * (1 - cos)
        poses.append(geometry.look_at(center + rotated, center, up))
    return np.stack(poses)
