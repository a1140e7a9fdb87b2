"""Reports on a shard set: statistics, distributions, pictures and videos of scenes.

Two jobs, each streaming scene by scene through `dataset_check.iter_dataset` (memory stays at one
scene):
- `build_dataset_report`: counts and distributions (objects per scene, visible and moving
  fractions, camera speed, blur, track lengths) as plots, plus a contact sheet and a video of the
  first `samples` scenes (config key) showing RGB with tracks (and the objects' 2-D boxes) |
  depth | segmentation | flow | normals | object coordinates (the layers a scene has), tied
  together by `index.html`.
- `build_scene_report`: one scene in detail (every frame, object table, per-track curves) and its
  validation (`dataset_check.validate_scene`).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from c4d.inspect import html, plots
from c4d.inspect.dataset_check import iter_dataset, validate_scene
from c4d_core import draw, geometry
from c4d_core.errors import UserError
from c4d_core.files import make_folder, write_json
from c4d_core.video import write_image, write_video
from datagen.scene import Scene

# --------------------------------------------------------------------------------------------
# Statistics
# --------------------------------------------------------------------------------------------

# Statistic names -> (what one value is, unit) for plots and the summary.
STATISTICS_FIELDS = ("objects", "tracks", "occluded", "moving", "cam_to_world", "intrinsics", "meta")
STATISTICS = {
    "objects_per_scene": ("objects per scene", "count"),
    "tracks_per_scene": ("tracks per scene", "count"),
    "visible_fraction_per_track": ("visible fraction per track", "fraction of frames"),
    "moving_fraction_per_track": ("moving fraction per track", "fraction of frames"),
    "moving_fraction_per_frame": ("moving fraction of tracks per frame", "fraction of tracks"),
    "camera_speed": ("mean camera speed per scene", "units / frame"),
    "blur_shutter": ("motion blur: shutter open per scene", "frames"),
    "track_length": ("track length (visible frames)", "frames"),
}


def blur_strength(meta: dict) -> float | None:
    """Shutter time in frames recorded by datagen (`meta['motion_blur']`, 0 = sharp), or None."""
    value = meta.get("motion_blur")
    return float(value) if isinstance(value, (int, float)) else None


def scene_statistics(scene: Scene) -> dict[str, np.ndarray]:
    """The values one scene contributes to each distribution of `STATISTICS` (1-D arrays)."""
    visible = ~scene.occluded  # (N,T)
    positions = scene.cam_to_world[:, :3, 3].astype(np.float64)  # (T,3)
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=-1)  # (T-1,)
    blur = blur_strength(scene.meta)
    stats = {
        "objects_per_scene": np.array([len(scene.objects)]),
        "tracks_per_scene": np.array([scene.num_tracks]),
        "visible_fraction_per_track": visible.mean(axis=1),
        "track_length": visible.sum(axis=1),
        "camera_speed": np.array([steps.mean() if steps.size else 0.0]),
        "blur_shutter": np.array([] if blur is None else [blur]),
    }
    if scene.moving is not None:
        stats["moving_fraction_per_track"] = scene.moving.mean(axis=1)
        stats["moving_fraction_per_frame"] = scene.moving.mean(axis=0) if scene.num_tracks else np.zeros(0)
    return stats


def summarise(values: np.ndarray) -> dict[str, float]:
    """count, mean, min, median, max of a 1-D array (empty: count only)."""
    if values.size == 0:
        return {"count": 0}
    return {"count": int(values.size), "mean": float(values.mean()), "min": float(values.min()),
            "median": float(np.median(values)), "max": float(values.max())}


# --------------------------------------------------------------------------------------------
# Pictures of a scene
# --------------------------------------------------------------------------------------------


def colorize_normal(normal: np.ndarray) -> np.ndarray:
    """Unit normals (...,3) -> RGB uint8 (...,3): (n + 1) / 2 * 255 per axis (x red, y green,
    z blue; Kubric's normal PNG mapping at 8 bits), so the floor (+z) is light blue."""
    return np.round((np.clip(normal, -1.0, 1.0) + 1.0) * 127.5).astype(np.uint8)


def colorize_coordinates(coordinates: np.ndarray) -> np.ndarray:
    """Object coordinates (...,3) in [0,1] -> RGB uint8 (...,3): c * 255 (x red, y green, z
    blue; the background's 0 is black)."""
    return np.round(np.clip(coordinates, 0.0, 1.0) * 255.0).astype(np.uint8)


def draw_boxes(video: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """`video` uint8 (T,H,W,3) with the objects' 2-D boxes (K,T,4) [ymin, xmin, ymax, xmax]
    (fractions of H and W, NaN where hidden) drawn as one-pixel outlines in each object's
    segmentation colour (object k has segment k + 1)."""
    video = np.ascontiguousarray(video).copy()
    height, width = video.shape[1:3]
    palette = draw.segment_palette(len(boxes) + 1)
    scale = np.array([height, width, height, width], np.float64)
    for k, object_boxes in enumerate(boxes):
        color = tuple(int(c) for c in palette[k + 1])
        for t, box in enumerate(object_boxes):
            if np.isfinite(box).all():  # pixel edges -> the outermost pixels' indices
                y0, x0, y1, x1 = np.round(box * scale).astype(int) - [0, 0, 1, 1]
                cv2.rectangle(video[t], (int(x0), int(y0)), (int(x1), int(y1)), color, 1)
    return video


def scene_panels(scene: Scene, cfg) -> tuple[list[np.ndarray], list[str]]:
    """RGB with tracks (and 2-D boxes), depth, segmentation, forward flow, normals and object
    coordinates (those the scene has) as RGB uint8 videos (T,H',W',3).

    Small scenes are scaled up by an integer factor so the pictures stay legible; tracks are
    moved to the scaled pixel grid (centres at integers: x' = (x + 0.5) f - 0.5).
    """
    factor = draw.display_scale(scene.rgb.shape[1], cfg.min_panel_height)
    clip = scene.tracks_time_major()  # tracks (T,N,2), occluded and moving (T,N)
    tracks = geometry.rescale_pixels(clip["tracks"], factor)
    radius = max(1.5, cfg.track_radius * factor * max(scene.image_size))
    rgb = draw.upscale(scene.rgb, factor)
    labels = ["rgb + tracks"]
    if scene.instances is not None:
        rgb = draw_boxes(rgb, scene.instances["bbox_2d"])
        labels = ["rgb + tracks + boxes"]
    panels = [draw.draw_tracks(rgb, tracks, ~clip["occluded"], clip["moving"], radius=radius)]
    for name, colorize in (("depth", draw.colorize_depth),
                           ("segmentation", draw.colorize_segmentation),
                           ("flow_fwd", draw.colorize_flow), ("normal", colorize_normal),
                           ("object_coordinates", colorize_coordinates)):
        value = getattr(scene, name)
        if value is not None:
            panels.append(draw.upscale(colorize(value), factor))
            labels.append(name)
    if "flow_fwd" in labels:  # frame T-1 has no next frame: grey, and said so on the frame
        flow = labels.index("flow_fwd")
        panels[flow] = panels[flow].copy()
        last = np.full_like(panels[flow][-1], 128)
        middle = last.shape[0] // 2 - 12  # below the panel's own label
        last[middle:] = draw.label_image(last[middle:], "no flow: last frame")
        panels[flow][-1] = last
    return panels, labels


def _keys(scene: Scene, width: int) -> np.ndarray:
    """The colour keys under a scene's panels: track colours, depth bar, flow wheel."""
    entries = {**draw.TRACK_LEGEND, "ring: occluded": (200, 200, 200)} if scene.moving is not None else {}
    return draw.key_strip(width, entries, depth=scene.depth is not None,
                          flow=scene.flow_fwd is not None)


def scene_video(scene: Scene, cfg) -> np.ndarray:
    """All panels side by side over the colour keys: RGB uint8 (T,H',W',3)."""
    panels, labels = scene_panels(scene, cfg)
    video = draw.side_by_side(panels, labels)
    keys = _keys(scene, video.shape[2])
    return np.concatenate([video, np.broadcast_to(keys, (len(video), *keys.shape))], axis=1)


def scene_contact_sheet(scene: Scene, cfg, num_frames: int) -> np.ndarray:
    """`num_frames` evenly spaced frames (rows) of all panels (columns): one RGB uint8 image."""
    panels, labels = scene_panels(scene, cfg)
    times = np.unique(np.linspace(0, scene.num_frames - 1, num_frames).round().astype(int))
    rows = [draw.side_by_side([p[t] for p in panels], [f"{labels[0]} t={t}"] + labels[1:])
            for t in times]
    sheet = draw.contact_sheet(rows, columns=1)
    return np.concatenate([sheet, _keys(scene, sheet.shape[1])], axis=0)


# --------------------------------------------------------------------------------------------
# Reports
# --------------------------------------------------------------------------------------------


def _write_scene_pictures(scene: Scene, folder: Path, cfg, video_ext: str) -> tuple[Path, Path]:
    fps = float(scene.meta.get("fps", cfg.fps))
    sheet = write_image(folder / "sheet.png", scene_contact_sheet(scene, cfg, cfg.sheet_frames))
    video = write_video(folder / f"video{video_ext}", scene_video(scene, cfg), fps)
    return sheet, video


def build_dataset_report(source, out: str | Path, cfg, split: str | None = None,
                         video_ext: str = ".webm", progress: bool = True) -> dict:
    """Write statistics, plots, pictures of the first `cfg.samples` scenes and `index.html` of a
    shard set into `out`.

    Returns the summary (also written to `out/summary.json`). Unreadable samples are skipped,
    counted and listed; `dataset_check.check_dataset` explains them in full.
    """
    out = make_folder(out)
    values: dict[str, list[np.ndarray]] = {name: [] for name in STATISTICS}
    counts = {"scenes": 0, "frames": 0, "objects": 0, "tracks": 0, "unreadable": 0}
    presets: dict[str, int] = {}
    samples, unreadable = [], []
    num_samples = cfg.samples
    scenes = iter_dataset(source, split, fields=STATISTICS_FIELDS, full_first=num_samples)
    for sample in tqdm(scenes, desc="inspect", unit="scene", disable=not progress):
        if sample.scene is None:
            counts["unreadable"] += 1
            unreadable.append((sample.shard, sample.key, sample.error))
            continue
        scene = sample.scene
        counts["scenes"] += 1
        counts["frames"] += len(scene.cam_to_world)  # rgb is only decoded for the samples
        counts["objects"] += len(scene.objects)
        counts["tracks"] += scene.num_tracks
        preset = str(scene.meta.get("preset", "?"))
        presets[preset] = presets.get(preset, 0) + 1
        for name, value in scene_statistics(scene).items():
            values[name].append(np.asarray(value, np.float64))
        if len(samples) < num_samples and scene.rgb is not None:  # decoded in full
            folder = out / "scenes" / sample.key
            sheet, video = _write_scene_pictures(scene, folder, cfg, video_ext)
            samples.append({"key": sample.key, "shard": sample.shard, "sheet": sheet, "video": video,
                            "frames": scene.num_frames, "size": scene.image_size,
                            "objects": len(scene.objects), "tracks": scene.num_tracks})
    if counts["scenes"] == 0:
        raise UserError(f"no readable scene in {source}; run `c4d inspect {source} --check --out DIR` "
                        "to see why, and regenerate the shards")

    merged = {name: np.concatenate(v) if v else np.zeros(0) for name, v in values.items()}
    plot_path = plots.histogram_grid(
        out / "distributions.png",
        {STATISTICS[name][0]: (merged[name], STATISTICS[name][1]) for name in STATISTICS},
    )
    summary = {
        "source": str(source),
        "counts": counts,
        "presets": presets,
        "statistics": {name: summarise(v) for name, v in merged.items()},
        "samples": [{k: str(v) if isinstance(v, Path) else v for k, v in s.items()} for s in samples],
        "unreadable": [list(u) for u in unreadable],
    }
    write_json(out / "summary.json", summary)
    _write_dataset_page(out, summary, plot_path, samples, unreadable)
    return summary


def _write_dataset_page(out: Path, summary: dict, plot_path: Path, samples: list[dict],
                        unreadable: list) -> Path:
    counts = summary["counts"]
    fragments = [
        html.text(f"Source: {summary['source']}"),
        html.table([[k, v] for k, v in counts.items()] + [["presets", summary["presets"]]],
                   header=["count", "value"]),
    ]
    if unreadable:
        fragments.append(html.text(f"{len(unreadable)} samples could not be read and are left out; "
                                   "run `c4d inspect SOURCE --check` for details.", "bad"))
    fragments += [
        html.heading("Distributions"),
        html.image(plot_path, out),
        html.table([[STATISTICS[name][0], STATISTICS[name][1], *(s.get(k, "") for k in
                     ("count", "mean", "min", "median", "max"))]
                    for name, s in summary["statistics"].items()],
                   header=["statistic", "unit", "count", "mean", "min", "median", "max"]),
        html.heading("Sample scenes"),
        html.text("Tracks on RGB: blue = static, red = moving in the world (a probability blends "
                  "the two); filled = visible, hollow ring = occluded.", "note"),
    ]
    for s in samples:
        fragments += [
            html.heading(s["key"], level=3),
            html.text(f"{s['shard']}: {s['frames']} frames of {s['size'][0]}x{s['size'][1]}, "
                      f"{s['objects']} objects, {s['tracks']} tracks", "note"),
            html.video(s["video"], out),
            html.image(s["sheet"], out),
        ]
    return html.write_page(out / "index.html", "Dataset report", fragments)


def build_scene_report(source, out: str | Path, index: int, cfg, split: str | None = None,
                       video_ext: str = ".webm") -> Path:
    """Detail page of the `index`-th scene of `source` (reading order): every frame, objects,
    per-track curves and its validation. Returns the path of the page."""
    if index < 0:
        raise UserError(f"--scene must be >= 0, got {index}")
    sample = None
    for i, candidate in enumerate(iter_dataset(source, split)):
        if i == index:
            sample = candidate
            break
    if sample is None:
        raise UserError(f"{source} has fewer than {index + 1} scenes; choose --scene below that")
    if sample.scene is None:
        raise UserError(f"scene {index} ({sample.key} in {sample.shard}) cannot be read: {sample.error}")
    scene = sample.scene
    out = Path(out)
    sheet, video = _write_scene_pictures(scene, out, cfg, video_ext)
    all_frames = write_image(out / "all_frames.png",
                                       scene_contact_sheet(scene, cfg, scene.num_frames))
    curves = plots.track_curves(out / "tracks.png", scene, cfg.track_curves)
    problems = validate_scene(scene, cfg)
    stats = {name: summarise(np.asarray(v, np.float64)) for name, v in scene_statistics(scene).items()}

    fragments = [
        html.text(f"Scene {index}: key {sample.key} in {sample.shard}"),
        html.text("valid: no problem found" if not problems else "problems: " + "; ".join(problems),
                  "good" if not problems else "bad"),
        html.heading("Video"), html.video(video, out), html.image(sheet, out),
        html.heading("Per-track curves"), html.image(curves, out),
        html.heading("Statistics"),
        html.table([[STATISTICS[n][0], *(s.get(k, "") for k in ("count", "mean", "min", "max"))]
                    for n, s in stats.items()], header=["statistic", "count", "mean", "min", "max"]),
        html.heading("Objects"),
        html.table([[k + 1, o] for k, o in enumerate(scene.objects)],
                   header=["segment id", "object"]),
        html.heading("Meta"),
        html.table([[k, v] for k, v in scene.meta.items()], header=["key", "value"]),
        html.heading("Every frame"), html.image(all_frames, out),
    ]
    return html.write_page(out / "index.html", f"Scene {sample.key}", fragments)
