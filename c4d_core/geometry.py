"""Camera and rigid-body geometry in numpy, used project-wide.

Conventions (docs/FORMAT.md, the interface contract):
- World: right-handed, Z up.
- Camera: OpenCV axes (x right, y down, z forward); poses are camera-to-world 4x4 matrices.
- Intrinsics: 3x3 K in pixels; pixel (x, y) has x the column and the centre of the top-left pixel at
  (0, 0), so the principal point of a centred lens is ((W - 1) / 2, (H - 1) / 2).
- Depth: z-depth along the optical axis.
- Quaternions: (w, x, y, z), unit norm.
All functions broadcast over leading dimensions written `...`.
"""

from __future__ import annotations

import numpy as np

WORLD_UP = np.array([0.0, 0.0, 1.0])


# ----------------------------------------------------------------------------- rigid transforms


def make_pose(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """(...,3,3) rotation and (...,3) translation -> (...,4,4) rigid transform."""
    rotation = np.asarray(rotation, dtype=np.float64)
    translation = np.asarray(translation, dtype=np.float64)
    shape = np.broadcast_shapes(rotation.shape[:-2], translation.shape[:-1])
    pose = np.zeros(shape + (4, 4))
    pose[..., :3, :3] = rotation
    pose[..., :3, 3] = translation
    pose[..., 3, 3] = 1.0
    return pose


def invert_pose(pose: np.ndarray) -> np.ndarray:
    """Inverse of (...,4,4) rigid transforms (rotation transposed, translation negated)."""
    rot_t = np.swapaxes(pose[..., :3, :3], -1, -2)  # (...,3,3)
    return make_pose(rot_t, -np.einsum("...ij,...j->...i", rot_t, pose[..., :3, 3]))


def transform_points(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply (...,4,4) transforms to (...,3) points (leading dims broadcast)."""
    return np.einsum("...ij,...j->...i", pose[..., :3, :3], points) + pose[..., :3, 3]


def rotate_vectors(pose: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """Apply only the rotation of (...,4,4) transforms to (...,3) directions."""
    return np.einsum("...ij,...j->...i", pose[..., :3, :3], vectors)


# ------------------------------------------------------------------ quaternions (w,x,y,z)


def quat_normalize(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def quat_matrix_entries(w, x, y, z) -> list:
    """The 9 entries, row-major, of the rotation matrix of the unit quaternion (w,x,y,z).

    Elementwise arithmetic only, so the components may be numpy arrays or torch tensors of any one
    shape (...): `quat_to_matrix` stacks them with numpy, `c4d_pipeline.scene_params` with torch
    (differentiable). Each entry has the components' shape (...).
    """
    return [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(...,4) quaternions (w,x,y,z), normalised here -> (...,3,3) rotation matrices."""
    rot = np.stack(quat_matrix_entries(*np.moveaxis(quat_normalize(q), -1, 0)), axis=-1)  # (...,9)
    return rot.reshape(rot.shape[:-1] + (3, 3))


def matrix_to_quat(rot: np.ndarray) -> np.ndarray:
    """(...,3,3) rotation matrices -> (...,4) quaternions (w,x,y,z) with w >= 0."""
    rot = np.asarray(rot, dtype=np.float64)
    m = rot.reshape(-1, 3, 3)
    # Four candidate solutions; pick the numerically largest denominator per matrix.
    trace = np.einsum("nii->n", m)
    cands = np.stack(
        [
            [1 + trace, m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1]],
            [m[:, 2, 1] - m[:, 1, 2], 1 + 2 * m[:, 0, 0] - trace, m[:, 0, 1] + m[:, 1, 0],
             m[:, 0, 2] + m[:, 2, 0]],
            [m[:, 0, 2] - m[:, 2, 0], m[:, 0, 1] + m[:, 1, 0], 1 + 2 * m[:, 1, 1] - trace,
             m[:, 1, 2] + m[:, 2, 1]],
            [m[:, 1, 0] - m[:, 0, 1], m[:, 0, 2] + m[:, 2, 0], m[:, 1, 2] + m[:, 2, 1],
             1 + 2 * m[:, 2, 2] - trace],
        ]
    )  # (4 candidates, 4 components, n)
    diag = np.stack([1 + trace, 1 + 2 * m[:, 0, 0] - trace, 1 + 2 * m[:, 1, 1] - trace,
                     1 + 2 * m[:, 2, 2] - trace])  # (4, n)
    best = np.argmax(diag, axis=0)  # (n,)
    q = cands[best, :, np.arange(m.shape[0])]  # (n,4)
    q = quat_normalize(q)
    q = np.where(q[:, :1] < 0, -q, q)
    return q.reshape(rot.shape[:-2] + (4,))


def quat_from_xyzw(q_xyzw: np.ndarray) -> np.ndarray:
    """pybullet's (x,y,z,w) order -> (w,x,y,z)."""
    q = np.asarray(q_xyzw, dtype=np.float64)
    return np.concatenate([q[..., 3:], q[..., :3]], axis=-1)


def quat_to_xyzw(q: np.ndarray) -> np.ndarray:
    """(w,x,y,z) -> pybullet's (x,y,z,w) order."""
    q = np.asarray(q, dtype=np.float64)
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def quat_slerp(q0: np.ndarray, q1: np.ndarray, alpha: np.ndarray | float) -> np.ndarray:
    """Spherical interpolation between (...,4) quaternions at fraction `alpha` in [0, 1]."""
    q0, q1 = quat_normalize(q0), quat_normalize(q1)
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)  # shortest arc
    dot = np.clip(np.abs(dot), 0.0, 1.0)
    alpha = np.asarray(alpha, dtype=np.float64)[..., None]
    theta = np.arccos(dot)
    sin_theta = np.sin(theta)
    small = sin_theta < 1e-6
    safe = np.where(small, 1.0, sin_theta)
    w0 = np.where(small, 1.0 - alpha, np.sin((1.0 - alpha) * theta) / safe)
    w1 = np.where(small, alpha, np.sin(alpha * theta) / safe)
    return quat_normalize(w0 * q0 + w1 * q1)


# ----------------------------------------------------------------------------- cameras


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = WORLD_UP) -> np.ndarray:
    """OpenCV camera-to-world (...,4,4) at `eye` looking at `target`, without roll.

    Columns of the rotation are the camera axes in the world: x = image right (horizontal),
    y = image down, z = viewing direction.
    """
    eye = np.asarray(eye, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    forward = target - eye
    forward = forward / np.linalg.norm(forward, axis=-1, keepdims=True)
    right = np.cross(forward, up)
    right = right / np.linalg.norm(right, axis=-1, keepdims=True)
    down = np.cross(forward, right)
    return make_pose(np.stack([right, down, forward], axis=-1), eye)


def intrinsics_from_lens(focal_mm: float, sensor_mm: float, height: int, width: int) -> np.ndarray:
    """3x3 K for a lens of `focal_mm` on a sensor `sensor_mm` wide (horizontal fit), square pixels.

    The principal point is the image centre, ((W - 1) / 2, (H - 1) / 2) in our pixel convention.
    """
    f = focal_mm / sensor_mm * width
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


def intrinsics_problem(intrinsics: np.ndarray) -> str | None:
    """Why camera matrices K (T,3,3) in pixels are not all a pinhole camera's
    [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with finite entries and focal lengths fx, fy > 0 (the
    cameras `unproject` inverts: any other K is singular, mirrored or no camera), in words naming
    the first bad frame; None if every frame's K is one."""
    K = np.asarray(intrinsics, np.float64)
    if K.ndim != 3 or K.shape[1:] != (3, 3):
        return f"intrinsics have shape {K.shape}, not (T,3,3)"
    pinhole = (np.isfinite(K).all(axis=(1, 2)) & (K[:, 0, 0] > 0) & (K[:, 1, 1] > 0)
               & (K[:, 1, 0] == 0) & (K[:, 2] == [0.0, 0.0, 1.0]).all(axis=1))
    bad = np.flatnonzero(~pinhole)
    if not len(bad):
        return None
    return (f"the intrinsics of {len(bad)} of {len(K)} frames (first frame {bad[0]}: "
            f"{np.round(K[bad[0]], 3).tolist()}) are no camera matrix [[fx, s, cx], [0, fy, cy], "
            "[0, 0, 1]] with finite entries and focal lengths fx, fy > 0")


def project(points_world: np.ndarray, intrinsics: np.ndarray, cam_to_world: np.ndarray):
    """World points (...,3) -> pixels (...,2) as (x, y), and z-depth (...).

    intrinsics (...,3,3), cam_to_world (...,4,4).

    Points behind the camera (z <= 0) get meaningless pixels; check z.
    """
    p_cam = transform_points(invert_pose(cam_to_world), points_world)  # (...,3)
    z = p_cam[..., 2]
    safe_z = np.where(np.abs(z) < 1e-9, 1e-9, z)
    uv = np.einsum("...ij,...j->...i", intrinsics, p_cam / safe_z[..., None])  # (...,3)
    return uv[..., :2], z


def unproject(pixels: np.ndarray, depth: np.ndarray, intrinsics: np.ndarray,
              cam_to_world: np.ndarray) -> np.ndarray:
    """Pixels (...,2) with z-depth (...) -> world points (...,3)."""
    pixels = np.asarray(pixels, dtype=np.float64)
    ones = np.ones(pixels.shape[:-1] + (1,))
    homogeneous = np.concatenate([pixels, ones], -1)  # (...,3)
    rays = np.einsum("...ij,...j->...i", np.linalg.inv(intrinsics), homogeneous)  # z = 1
    return transform_points(cam_to_world, rays * np.asarray(depth, dtype=np.float64)[..., None])


def pixel_grid(height: int, width: int) -> np.ndarray:
    """(H,W,2) pixel-centre coordinates (x, y)."""
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)
    return np.stack([xs, ys], axis=-1)


def rescale_pixels(coords, scale, inverse: bool = False):
    """Pixel coordinates `coords` (any shape) in an image `scale` times the size, pixel centres
    kept: (coords + 0.5) * scale - 0.5, or with `inverse` back to the original image,
    (coords + 0.5) / scale - 0.5. Plain arithmetic, so numpy arrays, torch tensors and numbers alike;
    `scale` broadcasts against `coords` (a number, or (sx, sy) against (...,2))."""
    if inverse:
        return (coords + 0.5) / scale - 0.5
    return (coords + 0.5) * scale - 0.5


def swap_track_axes(array):
    """Point tracks between the two layouts, a view: point-major (N,T,...) as datagen stores them
    (tracks (N,T,2), flags (N,T)) <-> time-major (T,N,...) as the tracker works."""
    return array.swapaxes(0, 1)


def unproject_depth_map(depth: np.ndarray, intrinsics: np.ndarray,
                        cam_to_world: np.ndarray) -> np.ndarray:
    """z-depth map (H,W) -> world points (H,W,3) at every pixel centre."""
    return unproject(pixel_grid(*depth.shape), depth, intrinsics, cam_to_world)
