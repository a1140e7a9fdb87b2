"""A reconstruction on disk: every file of the contract's output table, written atomically, and read back.

OUT/
  frames/%06d.png            the frames used (uint8 RGB)
  depth/%06d.npy (+ .png)    float32 z-depth (+ colourised inverse depth, for looking at)
  masks/%06d.png             motion mask, 255 = dynamic
  poses_tum.txt              `timestamp tx ty tz qx qy qz qw`, camera-to-world, timestamp = frame index
  intrinsics.npy             float32 (T,3,3)
  pointmaps.npz              points (T,H,W,3) world, confidence (T,H,W)
  tracks_2d.npz              tracks (T,N,2), visible (T,N), moving (T,N), queries (N,3)
  tracks_3d.npz              tracks_world (T,N,3), valid (T,N)
  scene.ply                  coloured points: static background once, dynamic points per frame
  report.json                inputs, config, per-stage seconds, loss curves, versions
  config.yaml                the resolved config (`c4d run` writes it before the reconstruction starts)
Every file is first written under a temporary name and then renamed, so an interrupted run never
leaves a half-written file under a final name.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from c4d_core import geometry
from c4d_core.draw import colorize_depth
from c4d_core.errors import UserError
from c4d_core.files import atomic_path, write_bytes, write_json, write_text


@dataclass
class Reconstruction:
    """A 4D reconstruction of T frames of H x W pixels (N tracks)."""

    frames: np.ndarray  # uint8 (T,H,W,3)
    depth: np.ndarray  # float32 (T,H,W) z-depth
    masks: np.ndarray  # bool (T,H,W) True = dynamic
    cam_to_world: np.ndarray  # float32 (T,4,4)
    intrinsics: np.ndarray  # float32 (T,3,3)
    points: np.ndarray  # float32 (T,H,W,3) world pointmaps
    confidence: np.ndarray  # float32 (T,H,W)
    tracks_2d: dict[str, np.ndarray] | None = None  # tracks (T,N,2), visible, moving (T,N), queries (N,3)
    tracks_world: np.ndarray | None = None  # float32 (T,N,3)
    tracks_valid: np.ndarray | None = None  # bool (T,N)
    report: dict[str, Any] = field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        return int(self.depth.shape[0])


def _save_png(path: Path, image: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        Image.fromarray(image).save(tmp, format="PNG")


def _save_npy(path: Path, array: np.ndarray) -> None:
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.save(fh, array)


def _save_npz(path: Path, **arrays: np.ndarray) -> None:
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **arrays)



def tum_lines(cam_to_world: np.ndarray) -> str:
    """TUM trajectory text for (T,4,4) camera-to-world poses: `t tx ty tz qx qy qz qw` per line."""
    quat = geometry.matrix_to_quat(cam_to_world[:, :3, :3])  # (T,4) w,x,y,z
    lines = []
    for t, (pose, q) in enumerate(zip(cam_to_world, quat)):
        tx, ty, tz = pose[:3, 3]
        lines.append(f"{t:.1f} {tx:.9g} {ty:.9g} {tz:.9g} {q[1]:.9g} {q[2]:.9g} {q[3]:.9g} {q[0]:.9g}")
    return "\n".join(lines) + "\n"


def read_tum(path: Path) -> np.ndarray:
    """(T,4,4) float64 camera-to-world poses from a TUM trajectory file."""
    rows = np.loadtxt(path, ndmin=2)
    if rows.shape[1] != 8:
        raise UserError(f"{path}: expected 8 numbers per line (t tx ty tz qx qy qz qw)")
    quat = rows[:, [7, 4, 5, 6]]  # (T,4) w,x,y,z
    return geometry.make_pose(geometry.quat_to_matrix(quat), rows[:, 1:4])


def ply_points(rec: Reconstruction, pixel_stride: int = 2, static_frame_stride: int = 5,
               min_confidence: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Points (M,3) float32 and colours (M,3) uint8 for scene.ply: static pixels of every
    `static_frame_stride`-th frame (the background, once) and the dynamic pixels of every frame,
    both on a grid of every `pixel_stride`-th pixel, above `min_confidence`."""
    sub = (slice(None), slice(None, None, pixel_stride), slice(None, None, pixel_stride))
    keep = rec.confidence[sub] >= min_confidence  # (T,h,w)
    dynamic = rec.masks[sub]
    static_frames = np.zeros(rec.num_frames, bool)
    static_frames[::static_frame_stride] = True
    sel = keep & (dynamic | (~dynamic & static_frames[:, None, None]))
    return rec.points[sub][sel].astype(np.float32), rec.frames[sub][sel]


def _ply_bytes(points: np.ndarray, colours: np.ndarray) -> bytes:
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(points)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )
    rows = np.empty(len(points), dtype=[("xyz", "<f4", 3), ("rgb", "u1", 3)])
    rows["xyz"], rows["rgb"] = points, colours
    return header.encode() + rows.tobytes()


def read_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Points (M,3) and colours (M,3) of a scene.ply written by `write_reconstruction`."""
    data = Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    count = int(next(l for l in data[:end].decode().splitlines() if l.startswith("element vertex")).split()[-1])
    rows = np.frombuffer(data[end:], dtype=[("xyz", "<f4", 3), ("rgb", "u1", 3)], count=count)
    return rows["xyz"].copy(), rows["rgb"].copy()



def write_reconstruction(rec: Reconstruction, out_dir: str | Path, ply_pixel_stride: int = 2,
                         ply_static_frame_stride: int = 5, ply_min_confidence: float = 1.0) -> Path:
    """Write every file of the output table into `out_dir` (created); returns its path."""
    out = Path(out_dir)
    for t in range(rec.num_frames):
        _save_png(out / "frames" / f"{t:06d}.png", rec.frames[t])
        _save_npy(out / "depth" / f"{t:06d}.npy", rec.depth[t].astype(np.float32))
        _save_png(out / "depth" / f"{t:06d}.png", colorize_depth(rec.depth[t]))
        _save_png(out / "masks" / f"{t:06d}.png", (rec.masks[t] * 255).astype(np.uint8))
    write_text(out / "poses_tum.txt", tum_lines(rec.cam_to_world.astype(np.float64)))
    _save_npy(out / "intrinsics.npy", rec.intrinsics.astype(np.float32))
    _save_npz(out / "pointmaps.npz", points=rec.points.astype(np.float32),
              confidence=rec.confidence.astype(np.float32))
    if rec.tracks_2d is not None:
        _save_npz(out / "tracks_2d.npz", **{k: np.asarray(v) for k, v in rec.tracks_2d.items()})
    if rec.tracks_world is not None:
        _save_npz(out / "tracks_3d.npz", tracks_world=rec.tracks_world.astype(np.float32),
                  valid=np.asarray(rec.tracks_valid, bool))
    pts, rgb = ply_points(rec, ply_pixel_stride, ply_static_frame_stride, ply_min_confidence)
    write_bytes(out / "scene.ply", _ply_bytes(pts, rgb))
    write_json(out / "report.json", rec.report, indent=1)
    return out


def read_reconstruction(out_dir: str | Path) -> Reconstruction:
    """Read a reconstruction written by `write_reconstruction` (or `c4d run`)."""
    out = Path(out_dir)
    if not (out / "poses_tum.txt").is_file():
        raise UserError(f"{out} is not a reconstruction (no poses_tum.txt); give the OUT folder "
                        "of `c4d run`")
    names = sorted(p.stem for p in (out / "depth").glob("*.npy"))
    frames = np.stack([np.asarray(Image.open(out / "frames" / f"{n}.png").convert("RGB")) for n in names])
    depth = np.stack([np.load(out / "depth" / f"{n}.npy") for n in names])
    masks = np.stack([np.asarray(Image.open(out / "masks" / f"{n}.png")) > 127 for n in names])
    with np.load(out / "pointmaps.npz") as pm:
        points, confidence = pm["points"], pm["confidence"]
    tracks_2d = tracks_world = tracks_valid = None
    if (out / "tracks_2d.npz").is_file():
        with np.load(out / "tracks_2d.npz") as tz:
            tracks_2d = {k: tz[k] for k in tz.files}
    if (out / "tracks_3d.npz").is_file():
        with np.load(out / "tracks_3d.npz") as tz:
            tracks_world, tracks_valid = tz["tracks_world"], tz["valid"]
    report = json.loads((out / "report.json").read_text()) if (out / "report.json").is_file() else {}
    return Reconstruction(
        frames=frames, depth=depth, masks=masks,
        cam_to_world=read_tum(out / "poses_tum.txt").astype(np.float32),
        intrinsics=np.load(out / "intrinsics.npy"), points=points, confidence=confidence,
        tracks_2d=tracks_2d, tracks_world=tracks_world, tracks_valid=tracks_valid, report=report,
    )
