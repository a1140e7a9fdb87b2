"""`c4d run VIDEO [key=value ...] --out DIR --pointmaps CKPT [--tracker CKPT] [--flow dis|raft:PATH]`.

Reconstructs a monocular video with C4D: DUSt3R preprocessing of the frames, pairwise pointmaps
from a DUSt3R/MASt3R/MonST3R checkpoint, optical flow, DynPT tracks (or, without a tracker, the
flow-only motion mask and no trajectory smoothing), the two-stage optimisation, and the output
files of the contract (docs/FORMAT.md). Every checkpoint is read and checked before the video is
touched, so a wrong path fails in seconds, not after the network has run.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from c4d_core.config import load_config
from c4d_core.errors import UserError

log = logging.getLogger("c4d.run")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("video", help="video file (mp4, avi, ...) or folder of frames (sorted by name)")
    parser.add_argument("--out", required=True, help="output folder (created; files of the C4D output table)")
    parser.add_argument("--pointmaps", required=True, metavar="CKPT",
                        help="DUSt3R / MASt3R / MonST3R checkpoint (.pth) for the pairwise pointmaps")
    parser.add_argument("--tracker", metavar="CKPT", help="DynPT checkpoint from `c4d train`; without it "
                        "the motion masks come from optical flow alone and stage 2 (PTS) is skipped")
    parser.add_argument("--flow", default="dis", help="optical flow: 'dis', 'dis:fast' or 'raft:PATH' [dis]")
    parser.add_argument("--preset", default="default", help="c4d config preset or YAML file [default]")
    parser.add_argument("--config", action="append", default=[], metavar="YAML",
                        help="extra config file merged over the preset (repeatable)")
    parser.add_argument("--size", type=int, help="network image size: long side (512) or 224 "
                        "(default: the checkpoint's training size)")
    parser.add_argument("--stride", type=int, default=1, help="use every STRIDE-th frame [1]")
    parser.add_argument("--max-frames", type=int, help="use at most this many frames")
    parser.add_argument("--grid-size", type=int, default=20,
                        help="tracker query grid cell in pixels (a max-gradient + a random point per cell) [20]")
    parser.add_argument("--pointmap-batch", type=int, default=0,
                        help="image pairs per network pass (0 = from free GPU memory, 2 on CPU) [0]")
    parser.add_argument("overrides", nargs="*", metavar="key=value",
                        help="config overrides right after VIDEO, e.g. optim.stage1_iters=100 device=cuda")


def _check_file(path: str | None, what: str, flag: str) -> None:
    if path is not None and not Path(path).is_file():
        raise UserError(f"{what} {path!r} does not exist; give the path of a local file with {flag}")


class _FlowWithProgress:
    """Runs a flow estimator over the pairs in chunks, with a progress bar."""

    def __init__(self, estimator, chunk: int = 8):
        self.estimator, self.chunk = estimator, chunk

    def flow(self, frames: np.ndarray, pairs) -> np.ndarray:
        pairs = list(pairs)
        parts = []
        for start in tqdm(range(0, len(pairs), self.chunk), desc="optical flow", unit="chunk", leave=False):
            parts.append(self.estimator.flow(frames, pairs[start:start + self.chunk]))
        return np.concatenate(parts) if parts else np.zeros((0, *frames.shape[1:3], 2), np.float32)


def run(args: argparse.Namespace) -> int:
    from c4d_pipeline.dust3r_pointmaps import Dust3rPointmaps
    from c4d_pipeline.flow import build_flow
    from c4d_pipeline.pipeline import reconstruct
    from c4d_pipeline.video_input import load_video_input

    # 1. Everything the user named, checked before any heavy work.
    cfg = load_config("c4d", args.preset, config_files=args.config, overrides=args.overrides)
    if not Path(args.video).exists():
        raise UserError(f"video {args.video!r} does not exist; pass a video file or a folder of frames")
    _check_file(args.pointmaps, "pointmap checkpoint", "--pointmaps")
    _check_file(args.tracker, "tracker checkpoint", "--tracker")
    if args.grid_size < 1:
        raise UserError(f"--grid-size must be at least 1, got {args.grid_size}")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {str(out)!r} is a file; give a folder")
    seconds: dict[str, float] = {}

    start = time.perf_counter()
    log.info("loading the pointmap network from %s", args.pointmaps)
    source = Dust3rPointmaps.from_checkpoint(args.pointmaps, cfg.device, args.pointmap_batch, progress=True)
    tracker = None
    if args.tracker:
        from dynpt.inference import load_tracker

        log.info("loading the tracker from %s", args.tracker)
        tracker = load_tracker(args.tracker, cfg.device)
    else:
        log.warning("no --tracker given: motion masks from the flow-only baseline (MonST3R-style), "
                    "and no trajectory smoothing (stage 2)")
    flow = _FlowWithProgress(build_flow(args.flow, device=cfg.device))
    seconds["load_models"] = time.perf_counter() - start

    # 2. Frames at the network's resolution.
    start = time.perf_counter()
    size = args.size or source.image_size
    video = load_video_input(args.video, size=size, stride=args.stride, max_frames=args.max_frames)
    frames = video.frames
    T, H, W = frames.shape[:3]
    seconds["read_video"] = time.perf_counter() - start
    log.info("%d frames of %dx%d (source %dx%d)", T, W, H, video.preprocessing.source_hw[1],
             video.preprocessing.source_hw[0])

    # 3. Tracks on the same frames.
    tracks = None
    if tracker is not None:
        start = time.perf_counter()
        log.info("tracking points (grid %d px)", args.grid_size)
        tracks = tracker.track(frames, grid_size=args.grid_size, seed=int(cfg.seed))
        seconds["tracking"] = time.perf_counter() - start

    # 4. Pointmaps, flow, masks, optimisation, files.
    log.info("reconstructing: pointmaps, optical flow (%s), motion masks, optimisation", args.flow)
    inputs = {
        "video": str(Path(args.video).resolve()), "pointmaps_checkpoint": str(Path(args.pointmaps).resolve()),
        "tracker_checkpoint": str(Path(args.tracker).resolve()) if args.tracker else None,
        "flow": args.flow, "network_size": size, "stride": args.stride, "max_frames": args.max_frames,
        "frame_indices": video.source_indices.tolist(),
        "source_hw": list(video.preprocessing.source_hw), "resized_hw": list(video.preprocessing.resized_hw),
        "crop_xy": list(video.preprocessing.crop_xy), "grid_size": args.grid_size,
        "seconds_before_reconstruction": seconds,
    }
    rec = reconstruct(frames, source, flow, tracks, cfg, out, inputs=inputs)
    stage_seconds = rec.report["seconds"]
    log.info("wrote %s (%s)", out, ", ".join(f"{k} {v:.1f}s" for k, v in {**seconds, **stage_seconds}.items()))
    return 0
