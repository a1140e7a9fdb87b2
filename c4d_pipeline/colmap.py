"""A `c4d run` reconstruction as COLMAP's text model: `c4d export colmap RECON OUT`
(docs/FORMAT.md, "Exports", `colmap`).

OUT holds cameras.txt, images.txt and points3D.txt, which COLMAP (`colmap model_converter`,
`--input_path OUT`, images from `RECON/frames`) and pycolmap read:
- one PINHOLE camera per distinct intrinsics (fx fy cx cy), the principal point shifted by half a
  pixel: COLMAP puts the centre of the top-left pixel at (0.5, 0.5), we put it at (0, 0);
- one image per frame, named as in RECON/frames (`000000.png`), with the world-to-camera
  rotation as a quaternion (qw qx qy qz) and translation;
- the static points (motion mask 0, finite pointmap), every `stride`-th in (frame, row, column)
  order, coloured by their frame; each is seen by the frame it comes from, at its pixel, so each
  image's POINTS2D lists the points taken from it and each track is that one observation
  (reprojection error 0: not measured).
Ids are 1-based (COLMAP's), in frame order; POINT2D_IDX is 0-based.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from c4d_core import geometry
from c4d_core.errors import UserError
from c4d_core.files import write_text
from c4d_core.ownership import output_folder
from c4d_pipeline.outputs import read_reconstruction, read_tum

KIND = "export-colmap"
MAX_POINTS = 100_000  # the default stride keeps at most this many static points


def static_pixels(masks: np.ndarray, points: np.ndarray, stride: int | None = None) -> np.ndarray:
    """Flat indices into (T,H,W) of every `stride`-th static pixel (mask False, finite point) in
    (frame, row, column) order; `stride` None: the smallest stride keeping at most `MAX_POINTS`.
    masks: bool (T,H,W), True = dynamic; points: (T,H,W,3) world pointmaps."""
    static = np.flatnonzero(~masks & np.isfinite(points).all(-1))
    if stride is None:
        stride = max(1, math.ceil(len(static) / MAX_POINTS))
    return static[::stride]


def pinhole_cameras(intrinsics: np.ndarray) -> tuple[dict[tuple[float, ...], int], np.ndarray]:
    """COLMAP's PINHOLE cameras of (T,3,3) intrinsics in our pixels: {(fx, fy, cx, cy) in COLMAP's
    pixels (principal point + 0.5): 1-based camera id}, one per distinct value, and the (T,)
    camera id of each frame."""
    params = np.asarray(intrinsics, np.float64)[:, [0, 1, 0, 1], [0, 1, 2, 2]]  # (T,4) fx fy cx cy
    params[:, 2:] += 0.5  # our top-left pixel centre (0, 0) is COLMAP's (0.5, 0.5)
    ids: dict[tuple[float, ...], int] = {}
    camera_of_frame = np.array([ids.setdefault(tuple(row), len(ids) + 1) for row in params.tolist()])
    return ids, camera_of_frame


def colmap_model(path: str | Path, stride: int | None = None) -> tuple[dict[str, str], int]:
    """{file name: text} of cameras.txt, images.txt and points3D.txt for the reconstruction at
    `path`, and the number of points; `stride` as in `static_pixels`. A reconstruction without
    static points is a UserError."""
    rec = read_reconstruction(path)
    cam_to_world = read_tum(Path(path) / "poses_tum.txt")  # (T,4,4) float64, as written
    num_frames, height, width = rec.masks.shape
    chosen = static_pixels(rec.masks, rec.points, stride)
    if not len(chosen):
        raise UserError(f"{path} has no static points to export: every pixel of every frame is "
                        "dynamic (masks/) or has no finite point (pointmaps.npz)")
    frame, row, col = np.unravel_index(chosen, (num_frames, height, width))
    xyz = rec.points[frame, row, col].astype(np.float64)  # (P,3) world
    rgb = rec.frames[frame, row, col]  # (P,3) uint8
    point_ids = np.arange(1, len(chosen) + 1)
    first = np.searchsorted(frame, np.arange(num_frames + 1))  # frame t's points: first[t]:first[t+1]
    point2d_idx = np.arange(len(chosen)) - first[frame]

    ids, camera_of_frame = pinhole_cameras(rec.intrinsics)
    cameras = [f"# Camera list with one line of data per camera: CAMERA_ID, MODEL, WIDTH, HEIGHT, "
               f"PARAMS[] (fx fy cx cy; pixel centres at +0.5)\n# Number of cameras: {len(ids)}"]
    cameras += [f"{cid} PINHOLE {width} {height} " + " ".join(map(repr, key)) for key, cid in ids.items()]

    images = ["# Image list with two lines of data per image:\n"
              "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
              "#   POINTS2D[] as (X, Y, POINT3D_ID)\n"
              f"# Number of images: {num_frames}, mean observations per image: "
              f"{len(chosen) / num_frames:g}"]
    for t in range(num_frames):
        world_to_cam = geometry.invert_pose(cam_to_world[t])
        quat = geometry.matrix_to_quat(world_to_cam[:3, :3])
        quat = quat if quat[0] >= 0 else -quat
        pose = " ".join(map(repr, [*quat.tolist(), *world_to_cam[:3, 3].tolist()]))
        images.append(f"{t + 1} {pose} {camera_of_frame[t]} {t:06d}.png")
        own = slice(first[t], first[t + 1])
        images.append(" ".join(f"{x + 0.5!r} {y + 0.5!r} {pid}" for x, y, pid
                               in zip(col[own].tolist(), row[own].tolist(), point_ids[own].tolist())))

    points = ["# 3D point list with one line of data per point:\n"
              "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
              f"# Number of points: {len(chosen)}, mean track length: 1"]
    points += [f"{pid} {x!r} {y!r} {z!r} {r} {g} {b} 0 {t + 1} {idx}" for pid, (x, y, z), (r, g, b), t, idx
               in zip(point_ids, xyz.tolist(), rgb.tolist(), frame, point2d_idx)]
    files = {name: "\n".join(lines) + "\n" for name, lines in
             (("cameras.txt", cameras), ("images.txt", images), ("points3D.txt", points))}
    return files, len(chosen)


def export_colmap(recon: str | Path, out: str | Path, stride: int | None = None,
                  overwrite: bool = False) -> int:
    """Write the COLMAP text model of the reconstruction `recon` into the folder `out` (claimed as
    an `export-colmap` output, c4d_core.ownership); returns the number of points written."""
    if stride is not None and stride < 1:
        raise UserError(f"--stride must be at least 1, not {stride}")
    files, num_points = colmap_model(recon, stride)
    with output_folder(out, KIND, overwrite) as folder:
        for name, text in files.items():
            write_text(folder / name, text)
    return num_points
