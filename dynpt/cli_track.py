"""`c4d track VIDEO --ckpt PATH --out DIR`: tracks (npz) and an overlay video coloured by mobility."""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import numpy as np

from c4d_core.errors import UserError

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
    parser.add_argument("--max-points", type=int, help="track at most this many points jointly "
                        "(bounds memory; default all together)")
    parser.add_argument("--support-grid", type=int, default=0, help="also track an NxN grid of "
                        "frame-0 points with the queries, then drop them (CoTracker3's predictor: 6) [0]")
    parser.add_argument("--no-backward", action="store_true",
                        help="track only forward from each query frame")
    parser.add_argument("--device", help="torch device (default: cuda if available, else cpu)")
    parser.add_argument("--fps", type=float, default=12.0, help="frame rate of the overlay video [12]")


def _read_queries(path: str) -> np.ndarray:
    p = Path(path)
    if not p.is_file():
        raise UserError(f"queries file {path!r} does not exist")
    try:
        return np.load(p) if p.suffix == ".npy" else np.loadtxt(p, ndmin=2)
    except ValueError as exc:
        raise UserError(f"cannot read queries from {path!r} ({exc}); write an (N,3) array of (t, x, y)") from exc


def run(args: argparse.Namespace) -> int:
    from c4d_core.draw import draw_tracks_enlarged
    from dynpt.inference import load_tracker
    from dynpt.video_io import read_video, write_video

    if args.grid_size < 1 or (args.max_points is not None and args.max_points < 1):
        raise UserError("--grid-size and --max-points must be at least 1")
    if args.support_grid < 0 or args.support_grid == 1:
        raise UserError("--support-grid must be 0 (none) or at least 2")
    video = read_video(args.video, stride=args.stride, max_frames=args.max_frames)
    queries = _read_queries(args.queries) if args.queries else None
    tracker = load_tracker(args.ckpt, args.device)
    out = Path(args.out)
    T, H, W = video.shape[:3]
    log.info("tracking %s points through %d frames of %dx%d on %s",
             "grid-sampled" if queries is None else len(queries), T, W, H, tracker.device)
    start = time.perf_counter()
    result = tracker.track(video, queries, grid_size=args.grid_size, seed=args.seed,
                           backward=not args.no_backward, max_points=args.max_points,
                           support_grid=args.support_grid)
    seconds = time.perf_counter() - start
    log.info("tracked %d points in %.1f s (%.2f s per frame)", result.tracks.shape[1], seconds,
             seconds / T)
    result.save(out / "tracks.npz")
    overlay = draw_tracks_enlarged(video, result.tracks, result.visible, result.moving,
                                   show_occluded=False, legend=True)
    write_video(out / "overlay.mp4", overlay, args.fps)
    moving = np.nanmean(result.moving[result.visible] > 0.5) if result.visible.any() else float("nan")
    log.info("wrote %s and %s (%.0f%% of visible points predicted moving)", out / "tracks.npz",
             out / "overlay.mp4", 100 * moving)
    return 0
