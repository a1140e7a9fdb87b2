"""A reconstruction on disk: every file of the contract's output table, written atomically, and read back.

OUT/
  frames/%06d.png            the frames used (uint8 RGB)
  depth/%06d.npy (+ .png)    float32 z-depth (+ colourised inverse depth, for looking at)
  masks/%06d.png             motion mask, 255 = dynamic
  poses_tum.txt              `timestamp tx ty tz qx qy qz qw`, camera-to-world; timestamp = the frame's
                             time in the source video, seconds (its frame index when none is known)
  intrinsics.npy             float32 (T,3,3)
  pointmaps.npz              points (T,H,W,3) world, confidence (T,H,W)
  tracks_2d.npz              tracks (T,N,2), visible (T,N), moving (T,N), queries (N,3)
  tracks_3d.npz              tracks_world (T,N,3), valid (T,N)
  scene.ply                  coloured points: static background once, dynamic points per frame
  report.json                inputs, config, per-stage seconds, loss curves, versions
  config.yaml                the resolved config (`c4d run` writes it before the reconstruction starts)
Every file is first written under a temporary name and then renamed, so an interrupted run never
leaves a half-written file under a final name. `write_frame`, `write_npz_frames` and `PlyStream`
write the same files a frame at a time, for reconstructions that are never whole in memory
(`c4d_pipeline.windows`).

`read_reconstruction` reads it back: strictly for scoring, tolerantly (listing what is missing or
inconsistent) for `c4d inspect`. scene.ply is written here (`_ply_bytes`: x y z float32, red green
blue uchar, nothing else) and read with trimesh (`read_ply`). trimesh's own PLY export is not used
for writing because it adds a comment line and an alpha channel to every point, so the file
would no longer be the one docs/FORMAT.md describes.
"""

from __future__ import annotations

import io
import json
import shutil
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from PIL import Image

from c4d_core import geometry
from c4d_core.draw import colorize_depth
from c4d_core.errors import UserError
from c4d_core.files import atomic_path, write_bytes, write_json, write_text


@dataclass
class Reconstruction:
    """A 4D reconstruction of T frames of H x W pixels (N tracks): what `reconstruct` makes and
    `read_reconstruction` reads back.

    After a tolerant read (`read_reconstruction(path, strict=False)`) any array is None whose file
    is missing or unreadable, `problems` says why, and `ply_points`/`ply_colors` hold scene.ply.
    """

    frames: np.ndarray  # uint8 (T,H,W,3)
    depth: np.ndarray  # float32 (T,H,W) z-depth
    masks: np.ndarray  # bool (T,H,W) True = dynamic
    cam_to_world: np.ndarray  # (T,4,4) float32; float64 as in poses_tum.txt after a tolerant read
    intrinsics: np.ndarray  # float32 (T,3,3)
    points: np.ndarray  # float32 (T,H,W,3) world pointmaps
    confidence: np.ndarray  # float32 (T,H,W)
    tracks_2d: dict[str, np.ndarray] | None = None  # tracks (T,N,2), visible, moving (T,N), queries (N,3)
    tracks_world: np.ndarray | None = None  # float32 (T,N,3)
    tracks_valid: np.ndarray | None = None  # bool (T,N)
    report: dict[str, Any] = field(default_factory=dict)
    timestamps: np.ndarray | None = None  # float64 (T,) source time of each frame, s (None: 0,1,2..)
    path: Path | None = None  # the folder it was read from
    ply_points: np.ndarray | None = None  # float64 (P,3) of scene.ply (tolerant read only)
    ply_colors: np.ndarray | None = None  # uint8 (P,3)
    problems: list[str] = field(default_factory=list)  # what is missing or inconsistent (tolerant read)

    @property
    def num_frames(self) -> int | None:
        """T: the length of the first of frames, depth, poses, pointmaps that is there."""
        for value in (self.frames, self.depth, self.cam_to_world, self.points):
            if value is not None:
                return len(value)
        return None


def save_png(path: Path, image: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        Image.fromarray(image).save(tmp, format="PNG")


def save_npy(path: Path, array: np.ndarray) -> None:
    buffer = io.BytesIO()  # numpy's own writes to a file report a full disk without an errno
    np.save(buffer, array)
    write_bytes(path, buffer.getvalue())


def save_npz(path: Path, **arrays: np.ndarray) -> None:
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **arrays)



def tum_lines(cam_to_world: np.ndarray, timestamps: np.ndarray | None = None) -> str:
    """TUM trajectory text for (T,4,4) camera-to-world poses: `t tx ty tz qx qy qz qw` per line;
    t from `timestamps` (T,) seconds, or the frame index."""
    quat = geometry.matrix_to_quat(cam_to_world[:, :3, :3])  # (T,4) w,x,y,z
    times = np.arange(len(cam_to_world), dtype=np.float64) if timestamps is None else timestamps
    lines = []
    for t, pose, q in zip(times, cam_to_world, quat):
        tx, ty, tz = pose[:3, 3]
        lines.append(f"{t:.6f} {tx:.9g} {ty:.9g} {tz:.9g} {q[1]:.9g} {q[2]:.9g} {q[3]:.9g} {q[0]:.9g}")
    return "\n".join(lines) + "\n"


def read_tum(path: Path) -> np.ndarray:
    """(T,4,4) float64 camera-to-world poses from a TUM trajectory file."""
    rows = np.loadtxt(path, ndmin=2)
    if rows.shape[1] != 8:
        raise UserError(f"{path}: expected 8 numbers per line (t tx ty tz qx qy qz qw)")
    quat = rows[:, [7, 4, 5, 6]]  # (T,4) w,x,y,z
    return geometry.make_pose(geometry.quat_to_matrix(quat), rows[:, 1:4])


def frame_ply_points(points: np.ndarray, confidence: np.ndarray, dynamic: np.ndarray, colours: np.ndarray,
                     static_frame: bool, pixel_stride: int = 2,
                     min_confidence: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """One frame's points (M,3) float32 and colours (M,3) uint8 for scene.ply: on a grid of every
    `pixel_stride`-th pixel, above `min_confidence`, the dynamic pixels, and the static ones too
    where `static_frame`. points float (H,W,3) world, confidence (H,W), dynamic bool (H,W),
    colours uint8 (H,W,3)."""
    sub = (slice(None, None, pixel_stride), slice(None, None, pixel_stride))
    moving = dynamic[sub]
    sel = (confidence[sub] >= min_confidence) & (moving | (~moving & static_frame))
    return points[sub][sel].astype(np.float32), colours[sub][sel]


def ply_points(rec: Reconstruction, pixel_stride: int = 2, static_frame_stride: int = 5,
               min_confidence: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Points (M,3) float32 and colours (M,3) uint8 for scene.ply: static pixels of every
    `static_frame_stride`-th frame (the background, once) and the dynamic pixels of every frame,
    both on a grid of every `pixel_stride`-th pixel, above `min_confidence` (`frame_ply_points`
    of every frame, in order)."""
    parts = [frame_ply_points(rec.points[t], rec.confidence[t], rec.masks[t], rec.frames[t],
                              t % static_frame_stride == 0, pixel_stride, min_confidence)
             for t in range(rec.num_frames)]
    return np.concatenate([p for p, _ in parts]), np.concatenate([c for _, c in parts])


def _ply_header(count: int) -> bytes:
    return ("ply\nformat binary_little_endian 1.0\n"
            f"element vertex {count}\n"
            "property float x\nproperty float y\nproperty float z\n"
            "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n").encode()


def _ply_rows(points: np.ndarray, colours: np.ndarray) -> bytes:
    rows = np.empty(len(points), dtype=[("xyz", "<f4", 3), ("rgb", "u1", 3)])
    rows["xyz"], rows["rgb"] = points, colours
    return rows.tobytes()


def _ply_bytes(points: np.ndarray, colours: np.ndarray) -> bytes:
    return _ply_header(len(points)) + _ply_rows(points, colours)


class PlyStream:
    """scene.ply written a frame at a time: `add(points (M,3), colours (M,3))` appends rows to a
    scratch file `body`; leaving the `with` block writes header and rows to `path` atomically
    (the file `_ply_bytes` writes for the same points) and removes `body`."""

    def __init__(self, path: Path, body: Path):
        self.path, self.body, self.count = Path(path), Path(body), 0

    def __enter__(self) -> "PlyStream":
        self._file = open(self.body, "wb")
        return self

    def add(self, points: np.ndarray, colours: np.ndarray) -> None:
        self._file.write(_ply_rows(points, colours))
        self.count += len(points)

    def __exit__(self, kind, value, traceback) -> None:
        self._file.close()
        if kind is None:
            with atomic_path(self.path) as tmp, open(tmp, "wb") as fh, open(self.body, "rb") as body:
                fh.write(_ply_header(self.count))
                shutil.copyfileobj(body, fh)
        self.body.unlink()


def write_npz_frames(path: Path, num_frames: int, arrays: dict) -> None:
    """An .npz file (as `np.savez_compressed` writes: one deflated `NAME.npy` member per array)
    of float32 arrays (T,...) written a frame at a time, atomically. arrays: {name: (frame shape,
    a function returning an iterator of the T frames, each float (frame shape))}; the members are
    written in turn, so each iterator runs once, after the previous one is exhausted."""
    with atomic_path(path) as tmp, zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED, allowZip64=True) as zf:
        for name, (shape, frames) in arrays.items():
            header = {"descr": "<f4", "fortran_order": False, "shape": (num_frames, *shape)}
            with zf.open(f"{name}.npy", "w", force_zip64=True) as member:
                np.lib.format.write_array_header_2_0(member, header)
                count = 0
                for frame in frames():
                    member.write(np.ascontiguousarray(frame, "<f4").reshape(shape).tobytes())
                    count += 1
            if count != num_frames:
                raise ValueError(f"{name}: {count} frames written, {num_frames} declared")


def read_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Points (M,3) float64 (the file's float32 values, exactly) and colours (M,3) uint8 (grey
    where the file has none) of a PLY point cloud, read with trimesh: the independent reader
    that shows other tools can open what `write_reconstruction` wrote."""
    import trimesh  # here: a second to import, and only the tolerant read needs it

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(path)
    cloud = trimesh.load(path, process=False)
    vertices = np.asarray(cloud.vertices)
    if len(vertices) == 0:
        raise ValueError("it has no points")
    colors = getattr(cloud, "colors", None)
    if colors is None or len(colors) != len(vertices):
        colors = getattr(getattr(cloud, "visual", None), "vertex_colors", None)
    if colors is None or len(colors) != len(vertices):
        return vertices, np.full((len(vertices), 3), 128, np.uint8)
    return vertices, np.asarray(colors)[:, :3].astype(np.uint8)


MARKER_FILES = ("poses_tum.txt", "pointmaps.npz", "report.json")  # any one marks a reconstruction


def is_reconstruction(path: str | Path) -> bool:
    """True if `path` is a directory that looks like the output of `c4d run`."""
    path = Path(path)
    return path.is_dir() and any((path / name).is_file() for name in MARKER_FILES)


def write_frame(out: Path, t: int, frame: np.ndarray, depth: np.ndarray, mask: np.ndarray) -> None:
    """Frame t's files but the coloured depth: frames/, depth/*.npy, masks/. frame uint8
    (H,W,3), depth float (H,W), mask bool (H,W) True = dynamic."""
    save_png(out / "frames" / f"{t:06d}.png", frame)
    save_npy(out / "depth" / f"{t:06d}.npy", depth.astype(np.float32))
    save_png(out / "masks" / f"{t:06d}.png", (mask * 255).astype(np.uint8))


def read_mask(out: Path, t: int) -> np.ndarray:
    """bool (H,W) motion mask of frame t written by `write_frame` (True = dynamic)."""
    return _read_images([out / "masks" / f"{t:06d}.png"], cv2.IMREAD_GRAYSCALE)[0] > 127


def write_reconstruction(rec: Reconstruction, out_dir: str | Path, ply_pixel_stride: int = 2,
                         ply_static_frame_stride: int = 5, ply_min_confidence: float = 1.0) -> Path:
    """Write every file of the output table into `out_dir` (created); returns its path."""
    out = Path(out_dir)
    depth_rgb = colorize_depth(rec.depth)  # one colour range for the whole video, not per frame
    for t in range(rec.num_frames):
        write_frame(out, t, rec.frames[t], rec.depth[t], rec.masks[t])
        save_png(out / "depth" / f"{t:06d}.png", depth_rgb[t])
    write_text(out / "poses_tum.txt", tum_lines(rec.cam_to_world.astype(np.float64), rec.timestamps))
    save_npy(out / "intrinsics.npy", rec.intrinsics.astype(np.float32))
    save_npz(out / "pointmaps.npz", points=rec.points.astype(np.float32),
              confidence=rec.confidence.astype(np.float32))
    if rec.tracks_2d is not None:
        save_npz(out / "tracks_2d.npz", **{k: np.asarray(v) for k, v in rec.tracks_2d.items()})
    if rec.tracks_world is not None:
        save_npz(out / "tracks_3d.npz", tracks_world=rec.tracks_world.astype(np.float32),
                  valid=np.asarray(rec.tracks_valid, bool))
    pts, rgb = ply_points(rec, ply_pixel_stride, ply_static_frame_stride, ply_min_confidence)
    write_bytes(out / "scene.ply", _ply_bytes(pts, rgb))
    write_json(out / "report.json", rec.report, indent=1)
    return out


def _numbered(folder: Path, suffix: str) -> list[Path]:
    """The numbered files of `folder` in order; FileNotFoundError when there are none."""
    files = sorted(folder.glob(f"[0-9]*{suffix}")) if folder.is_dir() else []
    if not files:
        raise FileNotFoundError(folder)
    return files


def _read_images(paths: list[Path], flags: int) -> np.ndarray:
    """(T,H,W,3) RGB or (T,H,W) grey uint8 images."""
    images = []
    for path in paths:
        image = cv2.imread(str(path), flags)
        if image is None:
            raise ValueError(f"{path.name} is not a readable image")
        images.append(image[..., ::-1] if image.ndim == 3 else image)
    return np.ascontiguousarray(np.stack(images))


def read_reconstruction(out_dir: str | Path, strict: bool = True) -> Reconstruction:
    """Read a reconstruction written by `write_reconstruction` (or `c4d run`), part by part.

    strict (`c4d eval-recon`, the demo): frames, depth, masks, poses, intrinsics and pointmaps
    must be there and readable (else `UserError`); tracks and report.json may be missing (None,
    {}); cam_to_world is float32, as `reconstruct` makes it.
    strict=False (`c4d inspect`): whatever is present and readable, a missing or broken file
    becoming None and a line of `problems`, followed by what disagrees between the parts (frame
    counts, image sizes, non-finite values); scene.ply is read too (`read_ply`), and cam_to_world
    keeps the float64 of poses_tum.txt.
    """
    out = Path(out_dir)
    if strict and not (out / "poses_tum.txt").is_file():
        raise UserError(f"{out} is not a reconstruction (no poses_tum.txt); give the OUT folder "
                        "of `c4d run`")
    if not out.is_dir():
        raise UserError(f"reconstruction directory {out} does not exist; pass the --out of `c4d run`")
    parts: dict[str, Any] = dict.fromkeys(
        ("frames", "depth", "masks", "cam_to_world", "intrinsics", "points", "confidence"))
    problems: list[str] = []
    tracks_3d_keys: list[str] | None = None  # the arrays tracks_3d.npz holds, once read

    def frames():
        parts["frames"] = _read_images(_numbered(out / "frames", ".png"), cv2.IMREAD_COLOR)

    def depth():
        parts["depth"] = np.stack([np.load(f) for f in _numbered(out / "depth", ".npy")]).astype(np.float32)

    def masks():
        values = _read_images(_numbered(out / "masks", ".png"), cv2.IMREAD_GRAYSCALE)
        if not strict and not np.isin(values, (0, 255)).all():
            problems.append("masks/ holds values other than 0 and 255")
        parts["masks"] = values > 127

    def poses():
        cam_to_world = read_tum(out / "poses_tum.txt")
        parts["cam_to_world"] = cam_to_world.astype(np.float32) if strict else cam_to_world
        parts["timestamps"] = np.loadtxt(out / "poses_tum.txt", ndmin=2)[:, 0]

    def intrinsics():
        parts["intrinsics"] = np.load(out / "intrinsics.npy")

    def pointmaps():
        with np.load(out / "pointmaps.npz") as data:
            parts["points"], parts["confidence"] = data["points"], data["confidence"]

    def tracks_2d():
        with np.load(out / "tracks_2d.npz") as data:
            parts["tracks_2d"] = {k: data[k] for k in data.files}

    def tracks_3d():
        nonlocal tracks_3d_keys
        with np.load(out / "tracks_3d.npz") as data:
            tracks_3d_keys = list(data.files)
            parts["tracks_world"] = data["tracks_world"] if "tracks_world" in data.files else None
            parts["tracks_valid"] = data["valid"] if "valid" in data.files else None

    def ply():
        parts["ply_points"], parts["ply_colors"] = read_ply(out / "scene.ply")

    def report():
        parts["report"] = json.loads((out / "report.json").read_text())

    for name, reader, required in (
            ("frames/", frames, True), ("depth/", depth, True), ("masks/", masks, True),
            ("poses_tum.txt", poses, True), ("intrinsics.npy", intrinsics, True),
            ("pointmaps.npz", pointmaps, True), ("tracks_2d.npz", tracks_2d, False),
            ("tracks_3d.npz", tracks_3d, False), *(() if strict else (("scene.ply", ply, False),)),
            ("report.json", report, False)):
        try:
            reader()
        except FileNotFoundError:
            if strict and required:
                raise UserError(f"{out}: {name} is missing; give the OUT folder of `c4d run`") from None
            if not strict:
                problems.append(f"{name} is missing")
        except Exception as exc:  # noqa: BLE001 -- strict: one error line; tolerant: listed, reading goes on
            if strict:
                raise exc if isinstance(exc, UserError) else UserError(
                    f"{out}: {name} cannot be read: {type(exc).__name__}: {exc}") from exc
            problems.append(f"{name} cannot be read: {type(exc).__name__}: {exc}")
    rec = Reconstruction(**parts, path=out, problems=problems)
    if not strict:
        rec.problems += _consistency_problems(rec, tracks_3d_keys)
    return rec


def _consistency_problems(rec: Reconstruction, tracks_3d_keys: list[str] | None) -> list[str]:
    """Disagreements between the parts of a tolerantly read reconstruction (frame counts, sizes,
    values, arrays its npz files lack); `tracks_3d_keys`: the arrays tracks_3d.npz holds (None:
    not read)."""
    problems = []
    counts = {name: len(value) for name, value in (
        ("frames", rec.frames), ("depth", rec.depth), ("masks", rec.masks),
        ("poses", rec.cam_to_world), ("intrinsics", rec.intrinsics), ("pointmaps", rec.points),
        ("tracks_2d", None if rec.tracks_2d is None else rec.tracks_2d.get("tracks")),
        ("tracks_3d", rec.tracks_world),
    ) if value is not None}
    if len(set(counts.values())) > 1:
        problems.append(f"frame counts disagree: {counts}")
    sizes = {name: value.shape[1:3] for name, value in (
        ("frames", rec.frames), ("depth", rec.depth), ("masks", rec.masks),
        ("pointmaps", rec.points)) if value is not None}
    if len(set(sizes.values())) > 1:
        problems.append(f"image sizes disagree: {sizes}")
    for name, value in (("depth", rec.depth), ("poses", rec.cam_to_world),
                        ("intrinsics", rec.intrinsics), ("pointmaps", rec.points)):
        if value is not None and not np.isfinite(value).all():
            problems.append(f"{name} has {int((~np.isfinite(value)).sum())} NaN or infinite values")
    if rec.depth is not None and (rec.depth[np.isfinite(rec.depth)] <= 0).any():
        problems.append("depth has values <= 0")
    if rec.intrinsics is not None and rec.intrinsics.shape[1:] != (3, 3):
        problems.append(f"intrinsics.npy has shape {rec.intrinsics.shape}, expected (T,3,3)")
    if rec.tracks_2d is not None:
        missing = {"tracks", "visible", "moving", "queries"} - set(rec.tracks_2d)
        if missing:
            problems.append(f"tracks_2d.npz lacks {sorted(missing)}")
    if tracks_3d_keys is not None:
        missing = {"tracks_world", "valid"} - set(tracks_3d_keys)
        if missing:
            problems.append(f"tracks_3d.npz lacks {sorted(missing)}")
    return problems
