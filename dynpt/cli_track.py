"""`c4d track VIDEO --ckpt PATH --out DIR`: tracks (npz) and an overlay video coloured by mobility.

The video is tracked at a working size (`--size`, `--max-size`; default its own) with at most
`--points` grid-sampled points; tracks.npz holds the tracks in the source video's pixels and the
overlay is drawn at the working size, at the source frame rate divided by `--stride`.
"""

from __future__ import annotations

import argparse
import logging
import math
import time
from pathlib import Path

import numpy as np

from c4d_core.errors import UserError
from c4d_core.schema import device as device_rule
from c4d_core.geometry import rescale_pixels
from c4d_core.ownership import check_folder, output_folder

log = logging.getLogger("c4d.track")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("video", help="video file or folder of frames (sorted by name)")
    parser.add_argument("--ckpt", required=True, help="DynPT checkpoint written by `c4d train`, or "
                        "cotracker3:PATH for a CoTracker3 release file (mobility untrained)")
    parser.add_argument("--out", required=True, help="output folder (tracks.npz, overlay.mp4)")
    parser.add_argument("--queries", help=".npy or text file of (N,3) queries (t, x, y) in pixels; "
                        "default: the paper's grid sampling on the first frame")
    parser.add_argument("--grid-size", type=int, default=20, help="cell size in pixels of the default "
                        "query sampling (max-gradient + random point per cell) [20]")
    parser.add_argument("--seed", type=int, default=0, help="seed of the random query points [0]")
    parser.add_argument("--stride", type=int, default=1, help="use every STRIDE-th frame [1]")
    parser.add_argument("--max-frames", type=int, help="use at most this many frames")
    parser.add_argument("--size", type=int, help="track at this long side in pixels (frames resized)")
    parser.add_argument("--max-size", type=int, help="shrink frames whose long side exceeds this "
                        "many pixels (e.g. 512 for a 720p video; never enlarges)")
    parser.add_argument("--points", type=int, help="point budget of the default query grid: the grid "
                        "cells widen until at most this many points are sampled")
    parser.add_argument("--max-points", type=int, help="track at most this many points jointly "
                        "(bounds memory; default all together)")
    parser.add_argument("--support-grid", type=int, default=0, help="also track an NxN grid of "
                        "frame-0 points with the queries, then drop them (CoTracker3's predictor: 6) [0]")
    parser.add_argument("--mobility", choices=("head", "epipolar"), default="head",
                        help="where the points' moving probability comes from: the network's head, "
                        "or the head fused with the tracks' epipolar geometry pooled over time "
                        "(dynpt/track_mobility.py; the settings of configs/dynpt eval.epipolar) [head]")
    parser.add_argument("--refine", choices=("none", "lk"), default="none",
                        help="the tracks as the network gives them, or refined to sub-pixel by "
                        "Lucas-Kanade frame to frame from each query point (dynpt/refine.py; the settings of "
                        "configs/dynpt eval.lk); with --mobility epipolar the geometry reads the "
                        "refined tracks [none]")
    parser.add_argument("--no-backward", action="store_true",
                        help="track only forward from each query frame")
    parser.add_argument("--device", help="torch device (default: cuda if available, else cpu)")
    parser.add_argument("--fps", type=float, help="frame rate of the overlay video (default: the "
                        "source's divided by --stride; 12 for a folder of frames)")


def _read_queries(path: str) -> np.ndarray:
    p = Path(path)
    if not p.is_file():
        raise UserError(f"queries file {path!r} does not exist")
    try:
        return np.load(p) if p.suffix == ".npy" else np.loadtxt(p, ndmin=2)
    except ValueError as exc:
        raise UserError(f"cannot read queries from {path!r} ({exc}); write an (N,3) array of (t, x, y)") from exc


def grid_for_budget(height: int, width: int, grid_size: int, points: int | None) -> int:
    """The query grid cell (pixels) for a frame of `height` x `width`: `grid_size`, widened so that
    the sampling's two points per cell stay within `points` (None: no budget)."""
    if points is None:
        return grid_size
    cell = grid_size
    while 2 * math.ceil(height / cell) * math.ceil(width / cell) > points and cell < max(height, width):
        cell += 1
    return cell


def run(args: argparse.Namespace) -> int:
    from c4d_core.draw import draw_tracks_enlarged
    from c4d_core.video import read_video, resize_long_side, video_fps, write_user_video
    from dynpt.inference import load_tracker
    from dynpt.postprocess import Postprocess, PostprocessedTracker
    from dynpt.refine import TrackRefinement
    from dynpt.track_mobility import EpipolarMobility

    for flag in ("grid_size", "max_points", "points", "size", "max_size"):
        value = getattr(args, flag)
        if value is not None and value < 1:
            raise UserError(f"--{flag.replace('_', '-')} must be at least 1, got {value}")
    if args.size is not None and args.max_size is not None and args.size > args.max_size:
        raise UserError(f"--size {args.size} is larger than --max-size {args.max_size}: --size sets "
                        "the long side exactly and --max-size only caps it, so give one of them")
    if args.support_grid < 0 or args.support_grid == 1:
        raise UserError("--support-grid must be 0 (none) or at least 2")
    if args.device is not None:
        device_rule().check("--device", args.device)
    if args.seed < 0:
        raise UserError(f"--seed must be 0 or more, got {args.seed}")
    if args.fps is not None and not (math.isfinite(args.fps) and args.fps > 0):
        raise UserError(f"--fps must be a positive number of frames per second, got {args.fps}")
    source = read_video(args.video, stride=args.stride, max_frames=args.max_frames)
    video = resize_long_side(source, args.size, args.max_size)
    (T, H0, W0), (H, W) = source.shape[:3], video.shape[1:3]
    sx, sy = W / W0, H / H0  # working pixels per source pixel
    queries = _read_queries(args.queries) if args.queries else None
    if queries is not None and (sx, sy) != (1, 1):
        queries = np.asarray(queries, np.float64).copy()
        queries[:, 1] = rescale_pixels(queries[:, 1], sx)
        queries[:, 2] = rescale_pixels(queries[:, 2], sy)
    grid = grid_for_budget(H, W, args.grid_size, args.points)
    tracker = load_tracker(args.ckpt, args.device)
    tracker = PostprocessedTracker(tracker, Postprocess(
        TrackRefinement() if args.refine == "lk" else None,
        EpipolarMobility() if args.mobility == "epipolar" else None))
    out = Path(args.out)
    check_folder(out, "track", args.overwrite)  # before the work
    log.info("tracking %s points through %d frames of %dx%d (source %dx%d) on %s",
             f"grid-sampled ({grid} px cells)" if queries is None else len(queries), T, W, H, W0, H0,
             tracker.device)
    start = time.perf_counter()
    result = tracker.track(video, queries, grid_size=grid, seed=args.seed,
                           backward=not args.no_backward, max_points=args.max_points,
                           support_grid=args.support_grid)
    seconds = time.perf_counter() - start
    log.info("tracked %d points in %.1f s (%.2f s per frame)", result.tracks.shape[1], seconds,
             seconds / T)
    overlay = draw_tracks_enlarged(video, result.tracks, result.visible, result.moving,
                                   show_occluded=False, legend=True)
    source_fps = video_fps(args.video)
    fps = args.fps or (source_fps / args.stride if source_fps else 12.0)
    with output_folder(out, "track", args.overwrite):
        result.scaled(1 / sx, 1 / sy).save(out / "tracks.npz")
        write_user_video(out / "overlay.mp4", overlay, fps)
    moving = np.nanmean(result.moving[result.visible] > 0.5) if result.visible.any() else float("nan")
    log.info("wrote %s and %s (%.0f%% of visible points predicted moving)", out / "tracks.npz",
             out / "overlay.mp4", 100 * moving)
    return 0
