"""Report on a reconstruction directory written by `c4d run` (layout: INTERFACES.md, docs/FORMAT.md).

Reads what is there with `c4d_pipeline.outputs.read_reconstruction(path, strict=False)`, which
lists what is missing or inconsistent, and writes into OUT:
`overview.webm` (frames with tracks | depth | motion mask), `depth.webm`, `masks.webm`,
`trajectory.png` (with the aligned ground truth when given), `mask_errors.png` (with the ground
truth: each frame's motion mask against the true dynamic pixels, true positives, false positives
and false negatives in the colours of `MASK_ERROR_COLORS`), `flythrough.webm` (the 4D point
cloud: static background once plus each frame's moving points, seen from an orbiting virtual
camera, rendered by `point_render`), `ply.png` (scene.ply read back with trimesh and rendered,
with a title and the world axes), `summary.json` and `index.html`.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from c4d.inspect import html, plots, point_render
from c4d_core import draw, geometry
from c4d_core.errors import UserError
from c4d_core.files import make_folder, write_json
from c4d_core.video import write_image, write_video
from c4d_pipeline.eval_metrics import align_trajectory, pose_metrics
from c4d_pipeline.eval_recon import scene_frame_indices
from c4d_pipeline.outputs import Reconstruction, read_reconstruction

AXIS_COLORS = ((230, 40, 40), (40, 170, 40), (40, 90, 235))  # RGB of the world x, y, z axes in ply.png
OBJECTIVES = ("ga", "cma", "cts", "pts")  # C4D's objectives, as report.json's loss curves name them
# RGB of mask_errors.png's classes (the rest of a tile is the frame in dimmed grey, r = g = b, so no
# pixel there can take one of these colours): found moving, wrongly marked, missed.
MASK_ERROR_COLORS = {"true positive": (40, 200, 40), "false positive": (255, 50, 40),
                     "false negative": (40, 120, 255)}
MASK_SHEET_COLUMNS = 6  # frames per row of mask_errors.png


# --------------------------------------------------------------------------------------------
# Pictures
# --------------------------------------------------------------------------------------------


def overview_video(recon: Reconstruction, cfg) -> np.ndarray | None:
    """Frames with tracks | depth | motion mask over the frames: RGB uint8 (T,H',W',3)."""
    if recon.frames is None:
        return None
    factor = draw.display_scale(recon.frames.shape[1], cfg.min_panel_height)
    frames = draw.upscale(recon.frames, factor)
    panels, labels = [frames], ["frames"]
    tracks = recon.tracks_2d
    if tracks is not None and {"tracks", "visible"} <= set(tracks) and len(tracks["tracks"]) == len(frames):
        scaled = geometry.rescale_pixels(tracks["tracks"], factor)  # (T,N,2) on the upscaled grid
        panels[0] = draw.draw_tracks(frames, scaled, tracks["visible"], tracks.get("moving"),
                                     radius=max(1.5, cfg.track_radius * max(frames.shape[1:3])))
        labels[0] = "frames + tracks"
    if recon.depth is not None and recon.depth.shape[:3] == recon.frames.shape[:3]:
        panels.append(draw.upscale(draw.colorize_depth(recon.depth), factor))
        labels.append("depth")
    if recon.masks is not None and recon.masks.shape[:3] == recon.frames.shape[:3]:
        mask_rgb = draw.colorize_mask(recon.masks)
        panels.append(draw.upscale(draw.blend(recon.frames, mask_rgb, 0.6), factor))
        labels.append("motion mask")
    video = draw.side_by_side(panels, labels)
    keys = draw.key_strip(video.shape[2], {**draw.TRACK_LEGEND, "red area: dynamic mask": draw.MOVING_COLOR}
                          if tracks is not None else {"red area: dynamic mask": draw.MOVING_COLOR},
                          depth="depth" in labels)
    return np.concatenate([video, np.broadcast_to(keys, (len(video), *keys.shape))], axis=1)


def _subsample(rng: np.random.Generator, count: int, limit: int) -> np.ndarray:
    return np.sort(rng.choice(count, limit, replace=False)) if count > limit else np.arange(count)


def _viewpoint(cam_to_world: np.ndarray, center: np.ndarray, cfg) -> tuple[np.ndarray, np.ndarray]:
    """A virtual camera (4,4) a little behind and above the first camera, looking at `center`,
    and the scene's up direction (3,): the mean of the cameras' up axes (OpenCV y is down)."""
    up = -cam_to_world[:, :3, 1].mean(axis=0)
    up /= np.linalg.norm(up)
    back = cam_to_world[0, :3, 3] - center
    eye = center + cfg.view_back * back + cfg.view_up * np.linalg.norm(back) * up
    return geometry.look_at(eye, center, up), up


def _virtual_intrinsics(height: int, width: int, cfg) -> np.ndarray:
    focal = cfg.focal * width
    return np.array([[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1]])


def flythrough_frames(recon: Reconstruction, cfg) -> np.ndarray | None:
    """The 4D point cloud from an orbiting virtual camera while time runs: uint8 (V,H,W,3).

    Static background (pixels outside the motion mask, all frames, subsampled once) plus the
    moving points of the current frame. The estimated cameras are not drawn: the virtual camera
    starts behind and above the first one, so they would lie below its view. `cfg`: the
    `flythrough` section of the inspect config.
    """
    if recon.points is None or recon.cam_to_world is None:
        return None
    num_frames, height, width = recon.points.shape[:3]
    colors = (recon.frames if recon.frames is not None and recon.frames.shape[:3] == recon.points.shape[:3]
              else np.full((num_frames, height, width, 3), 160, np.uint8))
    dynamic = (recon.masks if recon.masks is not None and recon.masks.shape == recon.points.shape[:3]
               else np.zeros(recon.points.shape[:3], bool))
    confidence = recon.confidence if recon.confidence is not None else np.ones(recon.points.shape[:3])
    finite = np.isfinite(recon.points).all(-1) & np.isfinite(confidence)
    threshold = np.quantile(confidence[finite], 1.0 - cfg.keep_confident) if finite.any() else 0.0
    good = finite & (confidence >= threshold)  # (T,H,W)

    rng = np.random.default_rng(cfg.seed)
    static = good & ~dynamic
    pick = _subsample(rng, int(static.sum()), cfg.static_points)
    static_points, static_colors = recon.points[static][pick], colors[static][pick]
    scene_points = static_points if len(static_points) else recon.points[good]
    if len(scene_points) == 0:
        return None
    center = np.median(scene_points, axis=0)
    start, up = _viewpoint(recon.cam_to_world, center, cfg)
    num_views = max(cfg.views_per_frame * num_frames, cfg.min_views)
    poses = point_render.orbit_path(center, start[:3, 3], up, num_views, cfg.sweep_deg)

    out_h = max(cfg.min_height, height)
    out_w = int(round(out_h * width / height))
    intrinsics = _virtual_intrinsics(out_h, out_w, cfg)
    views = []
    for v, pose in enumerate(poses):
        t = min(num_frames - 1, v * num_frames // num_views)
        moving = good[t] & dynamic[t]
        pick_t = _subsample(rng, int(moving.sum()), cfg.dynamic_points)
        points = np.concatenate([static_points, recon.points[t][moving][pick_t]])
        point_colors = np.concatenate([static_colors, colors[t][moving][pick_t]]).astype(np.uint8)
        image = point_render.render_points(points, point_colors, intrinsics, pose, (out_h, out_w),
                                           cfg.splat_radius)
        views.append(draw.label_image(image, f"frame {t}"))
    return np.stack(views)


def _round_length(value: float) -> float:
    """The largest of 1, 2, 5 times a power of ten that is at most `value` (> 0)."""
    power = 10.0 ** np.floor(np.log10(value))
    return max(step * power for step in (1, 2, 5) if step * power <= value)


def axes_length(points: np.ndarray, center: np.ndarray) -> float:
    """Length of the drawn world axes, in scene units: the round number (1, 2 or 5 times a power
    of ten) at most the median distance of the points (M,3) from `center` (3,)."""
    spread = float(np.median(np.linalg.norm(points - center, axis=1)))
    return _round_length(spread) if spread > 0 else 1.0


def ply_picture(recon: Reconstruction, cfg) -> np.ndarray | None:
    """scene.ply as read back by trimesh, from behind and above the first camera, under a title:
    (26 + H, W, 3) uint8. The world x, y, z axes (`AXIS_COLORS`, `axes_length` long) start at the
    points' median and are labelled at their tips."""
    if recon.ply_points is None or recon.cam_to_world is None:
        return None
    center = np.median(recon.ply_points, axis=0)
    pose, _ = _viewpoint(recon.cam_to_world, center, cfg)
    size = cfg.min_height * 3 // 2
    intrinsics = _virtual_intrinsics(size, size, cfg)
    image = point_render.render_points(recon.ply_points, recon.ply_colors, intrinsics, pose,
                                       (size, size), cfg.splat_radius)
    length = axes_length(recon.ply_points, center)
    ends = center + length * np.eye(3)  # (3,3): the tips of the x, y, z axes
    uv, depth = geometry.project(np.concatenate([center[None], ends]), intrinsics, pose)
    if (depth > point_render.NEAR).all():
        draw.draw_axes(image, uv[0], uv[1:], "xyz", AXIS_COLORS)
    title = f"scene.ply: {len(recon.ply_points)} points; world axes x, y, z {length:g} units long"
    return np.concatenate([draw.title_strip(size, title), image])


def mask_error_tile(frame: np.ndarray, predicted: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, dict]:
    """One frame's mask against the truth: the frame (H,W,3) in dimmed grey with the true
    positives, false positives and false negatives (bool (H,W) masks, True = dynamic) painted in
    `MASK_ERROR_COLORS`, and those three pixel counts."""
    grey = (0.3 * frame[..., 0] + 0.59 * frame[..., 1] + 0.11 * frame[..., 2]) * 0.6 + 40
    tile = np.repeat(grey.astype(np.uint8)[..., None], 3, axis=-1)
    classes = {"true positive": predicted & truth, "false positive": predicted & ~truth,
               "false negative": ~predicted & truth}
    for name, where in classes.items():
        tile[where] = MASK_ERROR_COLORS[name]
    return tile, {name: int(where.sum()) for name, where in classes.items()}


def mask_errors(recon: Reconstruction, scene, cfg) -> tuple[np.ndarray, dict] | None:
    """mask_errors.png: every reconstructed frame's motion mask against the true dynamic pixels
    of `scene` (`ground_truth_motion_masks`, the frames `c4d eval-recon` compares, the mask
    resized to the scene's size by nearest neighbour as there), one tile per frame under a strip
    naming the frame and its IoU, `MASK_SHEET_COLUMNS` to a row, a title with the IoU pooled over
    the frames and the share of dynamic pixels (what marking every pixel dynamic scores), and a
    colour key. Returns the picture uint8 and the counts {iou, true_positive, false_positive,
    false_negative, dynamic_fraction, per_frame: [...]}, or None without masks, frames or the
    scene's labels."""
    from c4d_pipeline.ground_truth import ground_truth_motion_masks

    if recon.masks is None or scene.depth is None or scene.segmentation is None or scene.object_to_world is None:
        return None
    indices, _ = scene_frame_indices(recon, scene.num_frames)
    truth = ground_truth_motion_masks(scene)[indices]  # (T,H,W) at the scene's size
    height, width = truth.shape[1:]
    predicted = np.stack([cv2.resize(m.astype(np.uint8), (width, height), interpolation=cv2.INTER_NEAREST)
                          for m in recon.masks]).astype(bool)
    frames = scene.rgb[indices]
    factor = draw.display_scale(height, cfg.min_panel_height // 2)
    tiles, per_frame = [], []
    for t, (frame, pred, true) in enumerate(zip(frames, predicted, truth)):
        tile, counts = mask_error_tile(frame, pred, true)
        union = sum(counts.values())
        iou = counts["true positive"] / union if union else 1.0
        per_frame.append({"frame": int(indices[t]), "iou": iou, **{k.replace(" ", "_"): v for k, v in counts.items()}})
        tile = draw.upscale(tile, factor)
        tiles.append(np.concatenate([draw.title_strip(tile.shape[1], f"frame {indices[t]}: IoU {iou:.2f}", 20), tile]))
    blank = np.full_like(tiles[0], 255)
    tiles += [blank] * (-len(tiles) % min(MASK_SHEET_COLUMNS, len(tiles)))
    sheet = draw.contact_sheet(tiles, columns=min(MASK_SHEET_COLUMNS, len(tiles)))
    totals = {key: sum(f[key] for f in per_frame) for key in ("true_positive", "false_positive", "false_negative")}
    union = sum(totals.values())
    result = {"iou": totals["true_positive"] / union if union else 1.0, **totals,
              "dynamic_fraction": float(truth.mean()), "per_frame": per_frame}
    title = (f"motion mask vs true dynamic pixels: IoU {result['iou']:.3f} over {len(per_frame)} frames; "
             f"every pixel dynamic would score {result['dynamic_fraction']:.3f}")
    keys = draw.key_strip(sheet.shape[1], {f"{name} ({totals[name.replace(' ', '_')]} px)": color
                                           for name, color in MASK_ERROR_COLORS.items()})
    return np.concatenate([draw.title_strip(sheet.shape[1], title), sheet, keys]), result


def method_name(report: dict) -> str:
    """The method a reconstruction ran, by the objectives whose losses report.json records:
    "C4D" (all of them, or when none is recorded: `c4d run` runs C4D), "GA only", or the
    objectives it used, e.g. "GA + CTS + PTS"."""
    losses = report.get("losses")
    used = {name for curves in (losses.values() if isinstance(losses, dict) else ())
            if isinstance(curves, dict) for name in curves if name in OBJECTIVES}
    if not used or used == set(OBJECTIVES):
        return "C4D"
    if used == {"ga"}:
        return "GA only"
    return " + ".join(name.upper() for name in OBJECTIVES if name in used)


def ground_truth_trajectory(recon: Reconstruction, scene) -> tuple[np.ndarray, np.ndarray, dict]:
    """The estimated poses Sim(3)-aligned onto the ground truth of the frames that were
    reconstructed (chosen as `c4d eval-recon` chooses them), the ground-truth poses, and the
    pose metrics: ((T,4,4), (T,4,4), {ate, rpe_trans, rpe_rot, sim3_scale})."""
    indices, _ = scene_frame_indices(recon, scene.num_frames)
    truth = scene.cam_to_world[indices].astype(np.float64)  # (T,4,4)
    aligned, _ = align_trajectory(recon.cam_to_world, truth)
    return aligned, truth, pose_metrics(recon.cam_to_world, truth)


# --------------------------------------------------------------------------------------------
# Report
# --------------------------------------------------------------------------------------------


def build_recon_report(path: str | Path, out: str | Path, cfg, gt_scene=None, gt_name: str = "",
                       video_ext: str = ".webm", compare: dict[str, Path] | None = None) -> dict:
    """Write the pictures, videos, `summary.json` and `index.html` of a reconstruction into `out`.

    `cfg`: the inspect config (`configs/inspect/default.yaml`).
    `gt_scene`: an optional `datagen.Scene` with the ground truth of the same video; its camera
    trajectory is drawn with the estimate aligned onto it. `compare`: other reconstructions of
    the same video by label (e.g. {"GA only": path}), drawn beside it in the trajectory plot and
    scored in the summary. Returns the summary.
    """
    out = make_folder(out)
    recon = read_reconstruction(path, strict=False)
    written: dict[str, Path] = {}
    fps = cfg.fps
    overview = overview_video(recon, cfg)
    if overview is not None:
        written["overview"] = write_video(out / f"overview{video_ext}", overview, fps)
    if recon.depth is not None:
        factor = draw.display_scale(recon.depth.shape[1], cfg.min_panel_height)  # as the overview,
        depth = draw.upscale(draw.colorize_depth(recon.depth), factor)  # so the key below fits
        keys = draw.key_strip(depth.shape[2], depth=True)
        written["depth"] = write_video(out / f"depth{video_ext}", np.concatenate(
            [depth, np.broadcast_to(keys, (len(depth), *keys.shape))], axis=1), fps)
    if recon.masks is not None:
        written["masks"] = write_video(out / f"masks{video_ext}",
                                                 draw.colorize_mask(recon.masks), fps)

    pose_errors, other_errors = None, {}
    if recon.cam_to_world is not None:
        method = method_name(recon.report)
        estimated, truth, title = recon.cam_to_world, None, "camera trajectory"
        unit = "reconstruction units"
        if gt_scene is not None:
            try:
                estimated, truth, pose_errors = ground_truth_trajectory(recon, gt_scene)
                title = (f"camera trajectory of {gt_name}, Sim(3)-aligned to the truth "
                         f"({method} ATE {pose_errors['ate']:.3g})")
                unit = "scene units"
            except UserError as exc:
                recon.problems.append(f"ground truth not drawn: {exc}")
        others, other_errors = {}, {}
        for label, other_path in (compare or {}).items():
            other = read_reconstruction(other_path, strict=False)
            if other.cam_to_world is None:
                continue
            if truth is not None:
                aligned, _, other_errors[label] = ground_truth_trajectory(other, gt_scene)
                others[label] = aligned[:, :3, 3]
            elif truth is None and gt_scene is None:
                others[label] = other.cam_to_world[:, :3, 3]
        if other_errors:
            title += "; " + ", ".join(f"{k} ATE {v['ate']:.3g}" for k, v in other_errors.items())
        written["trajectory"] = plots.trajectory_plot(
            out / "trajectory.png", estimated[:, :3, 3], method,
            None if truth is None else truth[:, :3, 3], title, unit, others)
    mask_check = None
    if gt_scene is not None:  # checked to be the reconstructed scene by the caller (`c4d inspect`)
        try:
            drawn = mask_errors(recon, gt_scene, cfg)
        except UserError as exc:
            drawn = None
            recon.problems.append(f"mask errors not drawn: {exc}")
        if drawn is not None:
            written["mask_errors"] = write_image(out / "mask_errors.png", drawn[0])
            mask_check = drawn[1]
    flythrough = flythrough_frames(recon, cfg.flythrough)
    if flythrough is not None:
        written["flythrough"] = write_video(out / f"flythrough{video_ext}", flythrough, fps)
        written["flythrough_still"] = write_image(out / "flythrough.png", flythrough[0])
    ply = ply_picture(recon, cfg.flythrough)
    if ply is not None:
        written["ply"] = write_image(out / "ply.png", ply)

    summary = {
        "reconstruction": str(recon.path),
        "frames": recon.num_frames,
        "image_size": None if recon.frames is None else list(recon.frames.shape[1:3]),
        "tracks": None if recon.tracks_2d is None else int(recon.tracks_2d["tracks"].shape[1]),
        "dynamic_pixel_fraction": None if recon.masks is None else float(recon.masks.mean()),
        "ply_points": None if recon.ply_points is None else int(len(recon.ply_points)),
        "pose_errors": pose_errors,
        **({"pose_errors_compared": other_errors} if other_errors else {}),
        **({"mask_vs_truth": {k: v for k, v in mask_check.items() if k != "per_frame"}}
           if mask_check is not None else {}),
        "problems": recon.problems,
        "files": {k: str(v) for k, v in written.items()},
    }
    write_json(out / "summary.json", summary)
    _write_page(out, recon, summary, written, gt_name)
    return summary


def _write_page(out: Path, recon: Reconstruction, summary: dict, written: dict[str, Path],
                scene_name: str = "") -> Path:
    fragments = [html.text(f"Reconstruction: {recon.path}")]
    fragments.append(html.text("consistent: no problem found" if not recon.problems
                               else "problems: " + "; ".join(recon.problems),
                               "good" if not recon.problems else "bad"))
    fragments.append(html.table([[k, v] for k, v in summary.items() if k not in ("problems", "files")],
                                header=["item", "value"]))
    captions = {
        "overview": "Frames with tracks (blue static, red moving; hollow = occluded), depth, motion mask.",
        "flythrough": "4D point cloud: static background plus the moving points of the current "
                      "frame, from an orbiting virtual camera that starts behind and above the "
                      "first camera (the camera path is in the trajectory plot).",
        "trajectory": f"Camera centres of this reconstruction ({method_name(recon.report)}, red), "
                      "other methods when compared, and ground truth (grey) when given, all "
                      "Sim(3)-aligned to the truth.",
        "ply": "scene.ply read back with trimesh, seen from behind and above the first camera, "
               "with the world axes.",
        "depth": "Depth (near red, far blue).",
        "masks": "Motion masks (red = dynamic).",
        "mask_errors": "Each frame's motion mask against the true dynamic pixels (surface points "
                       "that moved since the previous frame): green = found (true positive), red "
                       "= marked dynamic but static (false positive), blue = moving but missed "
                       "(false negative); the rest is the frame in grey.",
    }
    for name in ("overview", "mask_errors", "flythrough", "trajectory", "ply", "depth", "masks"):
        if name in written:
            fragments.append(html.heading(name))
            show = html.image if written[name].suffix == ".png" else html.video
            fragments.append(show(written[name], out, captions[name]))
    if recon.report:
        fragments.append(html.heading("report.json"))
        rows = []
        for key, value in recon.report.items():  # one row per entry of each section
            items = value.items() if isinstance(value, dict) else [("", value)]
            rows += [[key, name, v] for name, v in items]
        fragments.append(html.table(rows, header=["section", "key", "value"]))
    title = f"Reconstruction of {scene_name} ({recon.path.name})" if scene_name else f"Reconstruction {recon.path.name}"
    return html.write_page(out / "index.html", title, fragments)
