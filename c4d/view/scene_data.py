"""What the viewer shows, and its compact encoding for the page.

`ViewScene` is one moving point cloud with cameras and tracks in world coordinates (OpenCV camera
axes): built from a reconstruction (`from_reconstruction`: its pointmaps, confidences, motion
masks, poses and 3D tracks, optionally Sim(3)-aligned onto a generated scene's ground truth,
its cameras turned onto the true ones: `align_onto_truth`) or from a generated scene's own ground
truth (`from_scene`: depth unprojected with the true poses, the true motion masks and world
tracks).

`encode` reduces it to what the page draws, by the documented rule (`frame_selection`):
every `stride`-th pixel of every `stride`-th row of each frame, those the builder keeps (confidence
at least `--min-confidence`, finite), and of those at most `max_points` per frame, evenly spread
over the frame's kept pixels in row order. The defaults (stride 2, 20,000 points per frame) keep
90 frames of 512x384 at 1.8 M points, about 16 MB of data (docs/ARCHITECTURE.md, "c4d view").
Within a frame the static points come first, then the dynamic ones.

Long videos: `max_total` caps the points of all frames together (c4d.view.cli turns the page
size `--max-page-mb` into it with `page_other_bytes`) by lowering the per-frame cap to the
largest that fits (`frame_selections`), so every frame is thinned alike and short videos not at
all; the header's `thinned` says by how much. Unthinned, 1,000 frames of 256x192 make a 149 MB
page that headless Chromium needs 5-6 s to show, 64 MB ~3 s (docs/PERFORMANCE.md, "c4d view of
long reconstructions").

The page receives a small JSON header (counts, cameras, view settings) and one binary payload
(base64 in the page) of typed arrays: point positions as float16 relative to the scene's centre
(the median of the drawn points; relative precision 2^-11 of the distance to it), point colours
as uint8 RGB, the tracks' positions in every frame as float16 with uint8 validity and moving flags.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from c4d_core.errors import UserError

log = logging.getLogger(__name__)

DEFAULT_STRIDE = 2  # every 2nd pixel of every 2nd row
DEFAULT_MAX_POINTS = 20_000  # per frame: 90 frames stay at 1.8 M points
DEFAULT_MIN_CONFIDENCE = 1.0  # DUSt3R-family confidences are >= 1, so the default keeps them all
DEFAULT_MAX_TRACKS = 400  # tracks drawn, evenly chosen among those with a valid position
DEFAULT_MAX_PAGE_MB = 64.0  # page size (1e6 bytes) the points are thinned to stay under; 0: no limit
BYTES_PER_POINT = 12  # in the page: 3 float16 + 3 uint8 = 9 bytes, base64 (4/3)
FLOAT16_RANGE = 60_000.0  # points farther from the centre than this are dropped (float16 max 65504)


@dataclass
class ViewScene:
    """T frames of H x W pixels and N tracks, world coordinates; `keep` marks the pixels that may
    be drawn (confident and finite), `dynamic` those that move (None: unknown)."""

    title: str
    colors: np.ndarray  # uint8 (T,H,W,3) the frames
    points: np.ndarray  # float32 or float64 (T,H,W,3) world point of every pixel
    keep: np.ndarray  # bool (T,H,W)
    dynamic: np.ndarray | None  # bool (T,H,W) True = moving
    cam_to_world: np.ndarray  # float (T,4,4)
    intrinsics: np.ndarray  # float (T,3,3) K in pixels
    tracks: np.ndarray | None = None  # float (T,N,3) world position of each track
    tracks_valid: np.ndarray | None = None  # bool (T,N)
    tracks_moving: np.ndarray | None = None  # bool (T,N) True = moving (None: unknown)
    gt_cam_to_world: np.ndarray | None = None  # float (T,4,4) ground truth, in the same frame
    gt_intrinsics: np.ndarray | None = None  # float (T,3,3) ground truth, for these H x W pixels
    timestamps: np.ndarray | None = None  # float (T,) seconds (None: unknown)
    notes: list[str] = field(default_factory=list)  # lines shown under the title

    @property
    def num_frames(self) -> int:
        return len(self.points)


# --------------------------------------------------------------------------------------------
# Builders
# --------------------------------------------------------------------------------------------


def _check_frame_files(recon, folder: Path) -> None:
    """One `UserError` naming the first numbered file of frames/ or masks/ missing for a frame of
    pointmaps.npz (the strict reader reads what is there, without counting)."""
    count = len(recon.points)
    for name, value in (("frames", recon.frames), ("masks", recon.masks), ("depth", recon.depth)):
        if len(value) == count:
            continue
        suffix = ".npy" if name == "depth" else ".png"
        missing = next((f"{t:06d}{suffix}" for t in range(count)
                        if not (folder / name / f"{t:06d}{suffix}").is_file()), None)
        what = f"{name}/{missing} is missing" if missing else f"{name}/ holds {len(value)} files"
        raise UserError(f"{folder}: {what}, but pointmaps.npz has {count} frames; give a complete "
                        "OUT folder of `c4d run` (or run it again)")
    sizes = {name: value.shape[1:3] for name, value in (
        ("frames/", recon.frames), ("masks/", recon.masks), ("pointmaps.npz", recon.points),
        ("pointmaps.npz's confidence", recon.confidence))}
    if len(set(sizes.values())) > 1:
        raise UserError(f"{folder}: the image sizes disagree ("
                        + ", ".join(f"{n} {w}x{h}" for n, (h, w) in sizes.items())
                        + "); give a complete OUT folder of `c4d run`")
    if len(recon.cam_to_world) != count or len(recon.intrinsics) != count:
        raise UserError(f"{folder}: poses_tum.txt has {len(recon.cam_to_world)} poses and "
                        f"intrinsics.npy {len(recon.intrinsics)}, but pointmaps.npz {count} frames")


def from_reconstruction(folder: str | Path, min_confidence: float = DEFAULT_MIN_CONFIDENCE,
                        gt=None, gt_index: int = 0) -> ViewScene:
    """The reconstruction in `folder` (the OUT of `c4d run` / `c4d demo`); with `gt` (a generated
    `Scene`, the `gt_index`-th of its shard set) everything is Sim(3)-aligned onto its ground
    truth (`align_onto_truth`), drawn beside it."""
    from c4d_pipeline.outputs import read_reconstruction

    folder = Path(folder)
    recon = read_reconstruction(folder)
    _check_frame_files(recon, folder)
    points = recon.points  # float32 (T,H,W,3): a float64 copy would double view's memory
    cam_to_world = recon.cam_to_world.astype(np.float64)
    tracks, valid, moving = recon.tracks_world, recon.tracks_valid, None
    if tracks is not None and (valid is None or tracks.shape[:2] != valid.shape
                               or len(tracks) != len(points)):
        tracks = valid = None  # not this reconstruction's tracks: drawn without them
    if tracks is not None and recon.tracks_2d is not None:
        probability = recon.tracks_2d.get("moving")
        if probability is not None and probability.shape == valid.shape:
            moving = probability > 0.5
    notes = [f"{len(points)} frames of {points.shape[2]}x{points.shape[1]}; points with "
             f"confidence >= {min_confidence:g}; red: the motion masks' dynamic pixels"]
    title = f"c4d view: reconstruction {folder.resolve().name}"  # a name, not a machine's path
    gt_poses = gt_intrinsics = None
    if gt is not None:
        from c4d_pipeline.eval_metrics import orthonormalise, pose_metrics
        from c4d_pipeline.eval_recon import check_ground_truth, scene_frame_indices
        from c4d_pipeline.ground_truth import resize_intrinsics

        check_ground_truth(recon, gt)
        indices = scene_frame_indices(recon, gt.num_frames)[0]
        gt_poses = gt.cam_to_world[indices].astype(np.float64)
        gt_intrinsics = resize_intrinsics(gt.intrinsics[indices], gt.image_size, points.shape[1:3])
        scale, rotation, translation = align_onto_truth(cam_to_world, gt_poses)
        points = points @ (scale * rotation.T).astype(np.float32) + translation.astype(np.float32)
        if tracks is not None:
            tracks = scale * tracks.astype(np.float64) @ rotation.T + translation
        cam_to_world = orthonormalise(cam_to_world)
        cam_to_world[:, :3, :3] = rotation @ cam_to_world[:, :3, :3]
        cam_to_world[:, :3, 3] = scale * cam_to_world[:, :3, 3] @ rotation.T + translation
        truth, ate = gt.name(gt_index), pose_metrics(recon.cam_to_world, gt_poses)["ate"]
        title = f"c4d view: reconstruction of {truth} ({folder.resolve().name})"
        notes.append(f"green: ground truth of {truth}, the reconstruction Sim(3)-aligned onto its "
                     f"cameras (scale {scale:.3g}; ATE {ate:.4f}, as c4d eval-recon scores it)")
    confident = recon.confidence >= min_confidence
    if not confident.any():
        raise UserError(f"no point of {folder} has confidence >= {min_confidence:g} (the highest "
                        f"is {np.nanmax(recon.confidence):.3g}); give a lower --min-confidence")
    keep = finite_points(confident, points, str(folder), "rerun `c4d run`")
    return ViewScene(
        title=title, colors=recon.frames, points=points, keep=keep,
        dynamic=recon.masks, cam_to_world=cam_to_world, intrinsics=recon.intrinsics,
        tracks=tracks, tracks_valid=valid, tracks_moving=moving, gt_cam_to_world=gt_poses,
        gt_intrinsics=gt_intrinsics, timestamps=recon.timestamps, notes=notes)


def align_onto_truth(pred: np.ndarray, truth: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(s, R (3,3), t (3,)) of the Sim(3) x -> s R x + t that puts the estimated camera-to-world
    poses `pred` (T,4,4) onto the true ones `truth` (T,4,4) to draw them together: R turns the
    estimated cameras onto the true ones (the rotation nearest to the sum over frames of
    R_truth R_pred^T), then s and t fit the camera centres given R (least squares).

    Not the Umeyama fit of the centres alone that ATE is scored after (`align_trajectory`): that
    fixes R only as far as the centres span space, and a generated scene's camera moves on a
    straight line (datagen.sampling.CameraSpec), about which the estimated centres' scatter off
    the line turns R by any angle (a movi-e scene's true cameras were drawn 171 degrees away).
    A `UserError` where the estimated centres do not move along the true ones (s <= 0)."""
    from c4d_pipeline.eval_metrics import orthonormalise

    pred, truth = orthonormalise(pred), orthonormalise(truth)
    u, _, vt = np.linalg.svd(np.einsum("tij,tkj->ik", truth[:, :3, :3], pred[:, :3, :3]))
    rotation = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    p_mean, g_mean = pred[:, :3, 3].mean(axis=0), truth[:, :3, 3].mean(axis=0)
    p, g = pred[:, :3, 3] - p_mean, truth[:, :3, 3] - g_mean  # (T,3) centres about their mean
    spread = np.sum(p * p)
    scale = float(np.sum(g * (p @ rotation.T)) / spread) if spread > 0 else 0.0
    if not scale > 0:
        raise UserError("the reconstruction's camera centres do not move along the ground truth's "
                        f"(fitted scale {scale:.3g}), so no Sim(3) puts them onto it; leave out --gt")
    return scale, rotation, g_mean - scale * rotation @ p_mean


def finite_points(keep: np.ndarray, points: np.ndarray, name: str, fix: str) -> np.ndarray:
    """`keep` (T,H,W) less the pixels whose world point (T,H,W,3) is not finite (infinite or NaN
    depth), with a warning counting those; a `UserError` (ending in `fix`) where none is left."""
    finite = np.isfinite(points).all(-1)
    dropped, candidates = int((keep & ~finite).sum()), int(keep.sum())
    keep = keep & finite
    if not keep.any():
        raise UserError(f"{name}: none of its {candidates} points has a finite position (infinite "
                        f"or NaN depth), so there is nothing to draw; {fix}")
    if dropped:
        log.warning("%s: %d of %d points have an infinite or NaN position and are not drawn",
                    name, dropped, candidates)
    return keep


def from_scene(scene, source: str, index: int) -> ViewScene:
    """The `index`-th generated `Scene` of the shard set `source` from its ground truth: depth
    unprojected with the true intrinsics and poses, the true motion masks (red), the world tracks
    with their mobility labels."""
    name = f"{source} scene {index}"  # in messages: where it was read
    from c4d_core.geometry import unproject_depth_map
    from c4d_pipeline.ground_truth import ground_truth_motion_masks

    if scene.depth is None:
        raise UserError(f"{name} has no depth maps, so there is no point cloud to show")
    points = np.stack([unproject_depth_map(d, k, p) for d, k, p in
                       zip(scene.depth, scene.intrinsics, scene.cam_to_world)])  # (T,H,W,3)
    keep = finite_points(scene.depth > 0, points, name, "regenerate it with `c4d datagen`")
    dynamic = None
    if scene.segmentation is not None and scene.object_to_world is not None:
        with np.errstate(invalid="ignore"):  # non-finite points (not drawn) compare as False
            dynamic = ground_truth_motion_masks(scene)
    tracks = valid = moving = None
    if scene.tracks_world is not None:
        tracks = scene.tracks_world.swapaxes(0, 1)  # (T,N,3)
        valid = np.isfinite(tracks).all(-1)
        moving = None if scene.moving is None else scene.moving.swapaxes(0, 1)
    fps = scene.meta.get("fps")
    h, w = scene.image_size
    return ViewScene(
        title=f"c4d view: {scene.name(index)}", colors=scene.rgb, points=points,
        keep=keep, dynamic=dynamic,
        cam_to_world=scene.cam_to_world.astype(np.float64), intrinsics=scene.intrinsics,
        tracks=tracks, tracks_valid=valid, tracks_moving=moving,
        timestamps=None if not fps else np.arange(scene.num_frames) / float(fps),
        notes=[f"ground truth: {scene.num_frames} frames of {w}x{h}; red: points that move "
               "in the world"])


# --------------------------------------------------------------------------------------------
# Encoding
# --------------------------------------------------------------------------------------------


def frame_selection(keep: np.ndarray, stride: int, max_points: int) -> np.ndarray:
    """The flat indices into the stride grid (h,w) of one frame's `keep` (H,W) that are drawn:
    the kept pixels of the grid, thinned to at most `max_points` evenly in row order."""
    kept = np.flatnonzero(keep[::stride, ::stride])
    if len(kept) > max_points:
        kept = kept[np.arange(max_points) * len(kept) // max_points]
    return kept


def frame_selections(keep: np.ndarray, stride: int, max_points: int,
                     max_total: int | None = None) -> tuple[list[np.ndarray], dict | None]:
    """Every frame's `frame_selection` of `keep` (T,H,W), at most `max_points` each and, where
    `max_total` is given, at most that many in all: the per-frame cap is then lowered to the
    largest c with sum_t min(kept_t, c) <= max_total, so the frames are thinned alike. Returns
    the selections and, when thinned, {"cap", "points" drawn, "of" points before thinning}."""
    counts = np.array([np.count_nonzero(k[::stride, ::stride]) for k in keep])  # (T,)
    wanted = int(np.minimum(counts, max_points).sum())
    cap, thinned = max_points, None
    if max_total is not None and wanted > max_total:
        low, high = 0, max_points  # sum(min(counts, low)) <= max_total < sum(min(counts, high))
        while high - low > 1:
            middle = (low + high) // 2
            low, high = (middle, high) if np.minimum(counts, middle).sum() <= max_total else (low, middle)
        cap = low
        thinned = {"cap": cap, "points": int(np.minimum(counts, cap).sum()), "of": wanted}
    return [frame_selection(k, stride, cap) for k in keep], thinned


def page_other_bytes(view: ViewScene, max_tracks: int) -> int:
    """About how many bytes of the page `encode`'s header and payload take besides the points
    (at most, give or take): the cameras (their JSON with the cameras' mean as the centre, plus
    10 %), the per-frame counts and times, the tracks (base64), and 4 KB for the rest."""
    frames = view.num_frames
    centre = view.cam_to_world[:, :3, 3].mean(axis=0)
    cameras = len(json.dumps(_cameras(view.cam_to_world, view.intrinsics, centre), separators=(",", ":")))
    if view.gt_cam_to_world is not None:
        cameras *= 2
    counts = frames * 3 * (len(str(frames * view.points.shape[1] * view.points.shape[2])) + 1)
    tracks = 0
    if view.tracks is not None and max_tracks > 0:
        tracks = frames * len(_track_choice(view.tracks_valid, max_tracks)) * 8 * 4 // 3 + 64
    return int(1.1 * cameras) + counts + frames * 12 + tracks + 4096


def _track_choice(valid: np.ndarray, max_tracks: int) -> np.ndarray:
    """Indices of at most `max_tracks` tracks with a valid position, evenly among them."""
    usable = np.flatnonzero(valid.any(axis=0))
    if len(usable) > max_tracks:
        usable = usable[np.arange(max_tracks) * len(usable) // max_tracks]
    return usable


@dataclass
class Payload:
    """The page's data: `header` (JSON-ready) and `data`, the typed arrays one after another,
    each at a multiple of 4 bytes (`header['arrays']`: name -> offset, length, type)."""

    header: dict
    data: bytes


def encode(view: ViewScene, stride: int = DEFAULT_STRIDE, max_points: int = DEFAULT_MAX_POINTS,
           max_tracks: int = DEFAULT_MAX_TRACKS, max_total: int | None = None) -> Payload:
    """The page's data of `view`, at most `max_total` points in all (None: no limit; the module
    docstring says what is kept and how it is stored)."""
    grid_points = view.points[:, ::stride, ::stride]  # (T,h,w,3)
    grid_colors = view.colors[:, ::stride, ::stride]
    grid_dynamic = None if view.dynamic is None else view.dynamic[:, ::stride, ::stride]
    chosen, thinned = frame_selections(view.keep, stride, max_points, max_total)
    drawn = [grid_points[t].reshape(-1, 3)[c] for t, c in enumerate(chosen) if len(c)]
    centre = (np.median(np.concatenate(drawn), axis=0) if drawn
              else view.cam_to_world[:, :3, 3].mean(axis=0))  # no point drawn: the cameras'
    positions, colors, counts = [], [], {"start": [], "static": [], "dynamic": []}
    for t, selected in enumerate(chosen):
        xyz = grid_points[t].reshape(-1, 3)[selected] - centre
        near = (np.abs(xyz) < FLOAT16_RANGE).all(-1)
        selected, xyz = selected[near], xyz[near]
        moving = (np.zeros(len(selected), bool) if grid_dynamic is None
                  else grid_dynamic[t].reshape(-1)[selected])
        order = np.argsort(moving, kind="stable")  # static first, then dynamic
        counts["start"].append(sum(len(p) for p in positions))
        counts["static"].append(int((~moving).sum()))
        counts["dynamic"].append(int(moving.sum()))
        positions.append(xyz[order].astype(np.float16))
        colors.append(grid_colors[t].reshape(-1, 3)[selected][order])
    arrays = {"positions": np.concatenate(positions).reshape(-1),
              "colors": np.concatenate(colors).reshape(-1).astype(np.uint8)}
    tracks_header = None
    if view.tracks is not None:
        track_arrays, tracks_header = _track_arrays(view, centre, max_tracks)
        arrays.update(track_arrays)
    header = {
        "title": view.title, "notes": view.notes, "frames": view.num_frames,
        "image_size": list(view.points.shape[1:3]), "stride": stride, "max_points": max_points,
        "thinned": thinned,
        "centre": centre.tolist(), "points": counts, "has_dynamic": view.dynamic is not None,
        "point_size": _point_size(view, chosen, stride), "fps": _fps(view.timestamps) or 10.0,
        "timestamps": None if _fps(view.timestamps) is None else np.round(view.timestamps, 4).tolist(),
        "cameras": _cameras(view.cam_to_world, view.intrinsics, centre),
        "gt_cameras": None if view.gt_cam_to_world is None
        else _cameras(view.gt_cam_to_world, view.gt_intrinsics, centre),
        "frustum_depth": _frustum_depth(view, centre),
        "tracks": tracks_header,
    }
    data, header["arrays"] = bytearray(), {}
    for name, array in arrays.items():
        header["arrays"][name] = {"offset": len(data), "length": int(array.size), "type": str(array.dtype)}
        data += array.tobytes() + bytes(-array.nbytes % 4)
    return Payload(header, bytes(data))


def _track_arrays(view: ViewScene, centre: np.ndarray, max_tracks: int) -> tuple[dict, dict]:
    """The chosen tracks' positions (T*n*3,) float16 relative to the centre, their validity and
    moving flags (T*n,) uint8, time-major; and the header entry (n, whether moving is known).
    The page draws a track's segment from frame t-1 to t where both are valid, and its head."""
    chosen = _track_choice(view.tracks_valid, max_tracks)
    tracks = view.tracks[:, chosen] - centre  # (T,n,3)
    valid = view.tracks_valid[:, chosen] & (np.abs(tracks) < FLOAT16_RANGE).all(-1)
    moving = (np.zeros_like(valid) if view.tracks_moving is None
              else view.tracks_moving[:, chosen] & valid)
    arrays = {"track_points": np.where(valid[..., None], tracks, 0).astype(np.float16).reshape(-1),
              "track_valid": valid.astype(np.uint8).reshape(-1),
              "track_moving": moving.astype(np.uint8).reshape(-1)}
    return arrays, {"count": len(chosen), "has_moving": view.tracks_moving is not None}


def _cameras(cam_to_world: np.ndarray, intrinsics: np.ndarray, centre: np.ndarray) -> dict:
    """Rows of camera-to-world (T,16) relative to the centre and (fx, fy, cx, cy) (T,4)."""
    poses = np.array(cam_to_world, np.float64)
    poses[:, :3, 3] -= centre
    k = np.asarray(intrinsics, np.float64)
    return {"cam_to_world": np.round(poses.reshape(len(poses), 16), 6).tolist(),
            "intrinsics": np.round(np.stack([k[:, 0, 0], k[:, 1, 1], k[:, 0, 2], k[:, 1, 2]], -1), 4).tolist()}


def _point_size(view: ViewScene, chosen: list[np.ndarray], stride: int) -> float:
    """A point's width in world units: the median distance from camera to point times the
    pixel pitch of the drawn points (`stride`, widened where the cap thinned them) over focal."""
    widths = []
    for t, selected in enumerate(chosen):
        kept = int(view.keep[t, ::stride, ::stride].sum())
        if not len(selected):
            continue
        xyz = view.points[t, ::stride, ::stride].reshape(-1, 3)[selected]
        distance = np.median(np.linalg.norm(xyz - view.cam_to_world[t, :3, 3], axis=-1))
        widths.append(distance * stride * np.sqrt(kept / len(selected)) / view.intrinsics[t][0, 0])
    return float(np.median(widths)) if widths else 0.01


def _frustum_depth(view: ViewScene, centre: np.ndarray) -> float:
    """How deep a camera frustum is drawn: a tenth of the cameras' median distance to the
    centre (at least a hundredth of the path length)."""
    centres = view.cam_to_world[:, :3, 3]
    distance = float(np.median(np.linalg.norm(centres - centre, axis=-1)))
    path = float(np.linalg.norm(np.diff(centres, axis=0), axis=-1).sum())
    return max(0.1 * distance, 0.01 * path, 1e-3)


def _fps(timestamps: np.ndarray | None) -> float | None:
    """The source video's frames per second, from frame times that step by less than a second
    (`c4d run` writes frame indices when it knows no times); None when unknown (playback: 10)."""
    step = float(np.median(np.diff(timestamps))) if timestamps is not None and len(timestamps) > 1 else 0.0
    return float(min(1.0 / step, 60.0)) if 0 < step < 1 else None
