"""`c4d run VIDEO [key=value ...] --out DIR --pointmaps CKPT [--tracker CKPT] [--flow dis|raft:PATH]`.

Every flag but `--out`, `--preset` and `--config` stands for a key of configs/c4d (`--pointmaps`
is `pointmaps.checkpoint`, `--tracker` is `tracker.checkpoint`, `--threads` is `threads`, ...;
see `RUN_FLAGS`), so a YAML file given with `--config` (or as `--preset`) can hold a whole run; a
key set both by its flag and by `key=value` is an error. The video's frame count is checked before
anything is written; OUT keeps the resolved config as `config.yaml`.

Reconstructs a monocular video with C4D: DUSt3R preprocessing of the frames, pairwise pointmaps
from a DUSt3R/MASt3R/MonST3R checkpoint, optical flow, DynPT tracks (or, without a tracker, the
flow-only motion mask and no trajectory smoothing), the two-stage optimisation, and the output
files of the contract (docs/FORMAT.md); with `--window FRAMES`, window by window in bounded memory
(`c4d_pipeline.windows`). Every checkpoint is read and checked before the video is
touched, so a wrong path fails in seconds, not after the network has run.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from c4d_core.config import flag_overrides, load_config, refuse_override_as_positional, to_yaml
from c4d_core.errors import UserError
from c4d_core.files import staged_folder, write_text
from c4d_core.ownership import check_folder, mark_folder
from c4d_core.system import configure_threads

log = logging.getLogger("c4d.run")


# flag (argparse dest) -> the config key it sets
RUN_FLAGS = {"pointmaps": "pointmaps.checkpoint", "tracker": "tracker.checkpoint", "flow": "flow",
             "size": "pointmaps.size", "stride": "video.stride", "max_frames": "video.max_frames",
             "grid_size": "tracker.grid_size", "pointmap_batch": "pointmaps.batch",
             "intrinsics": "intrinsics.known", "intrinsics_mode": "intrinsics.mode",
             "window": "window.frames", "window_overlap": "window.overlap",
             "threads": "threads"}  # --threads: c4d.cli's flag of every subcommand


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("video", help="video file (mp4, avi, ...) or folder of frames (sorted by name)")
    parser.add_argument("--out", required=True, help="output folder (created; files of the C4D output table)")
    parser.add_argument("--pointmaps", metavar="CKPT", help="DUSt3R / MASt3R / MonST3R checkpoint (.pth) "
                        "for the pairwise pointmaps (key pointmaps.checkpoint; required)")
    parser.add_argument("--tracker", metavar="CKPT", help="DynPT checkpoint from `c4d train`; without it "
                        "the motion masks come from optical flow alone and stage 2 (PTS) is skipped "
                        "(key tracker.checkpoint)")
    parser.add_argument("--flow", help="optical flow: 'dis', 'dis:fast', 'dis:medium@2x+chain' or "
                        "'raft:PATH' (key flow) [dis]")
    parser.add_argument("--preset", default="default", help="c4d config preset or YAML file [default]")
    parser.add_argument("--config", action="append", default=[], metavar="YAML",
                        help="extra config file merged over the preset (repeatable)")
    parser.add_argument("--size", type=int, help="network image size: long side (512) or 224 "
                        "(key pointmaps.size; default: the checkpoint's training size)")
    parser.add_argument("--stride", type=int, help="use every STRIDE-th frame (key video.stride) [1]")
    parser.add_argument("--max-frames", type=int,
                        help="use at most this many frames (key video.max_frames; default: all)")
    parser.add_argument("--intrinsics", metavar="FX,FY,CX,CY|FILE",
                        help="known camera intrinsics in the source video's pixels, or a .txt/.npy file "
                        "with one row fx fy cx cy per source frame (or one row); key intrinsics.known "
                        "(default: estimated)")
    parser.add_argument("--intrinsics-mode", choices=["fixed", "init"],
                        help="fixed: known intrinsics are not optimised; init: the focal starts there "
                        "and is optimised (key intrinsics.mode) [fixed]")
    parser.add_argument("--window", type=int, metavar="FRAMES",
                        help="reconstruct long videos in overlapping windows of FRAMES frames joined by "
                        "Sim(3), memory bounded by FRAMES, not by the video's length (key window.frames; "
                        "0: the whole video at once) [0]")
    parser.add_argument("--window-overlap", type=int, metavar="N",
                        help="frames shared by neighbouring windows, at least the scene graph's longest "
                        "pair (key window.overlap) [10]")
    parser.add_argument("--grid-size", type=int, help="tracker query grid cell in pixels (a max-gradient "
                        "+ a random point per cell; key tracker.grid_size) [20]")
    parser.add_argument("--pointmap-batch", type=int, help="image pairs per network pass (0 = from "
                        "free GPU memory, 2 on CPU; key pointmaps.batch) [0]")
    parser.add_argument("overrides", nargs="*", metavar="key=value",
                        help="config overrides right after VIDEO, e.g. optim.stage1_iters=100 device=cuda")


def load_run_config(args: argparse.Namespace):
    """The c4d config of a run: preset, --config files, then key=value overrides and the flags."""
    refuse_override_as_positional(args.video, "VIDEO", args.overrides,
                                  "`c4d run VIDEO --pointmaps CKPT --out DIR [key=value ...]`")
    flags = {key: getattr(args, dest, None) for dest, key in RUN_FLAGS.items()}
    overrides = [*args.overrides, *flag_overrides(flags, args.overrides)]
    return load_config("c4d", args.preset, config_files=args.config, overrides=overrides)


def _check_file(path: str, what: str, flag: str) -> None:
    if path:
        from dynpt.torch_files import require_file  # torch: only once a run starts

        require_file(Path(path), what, f"give the path of a local file with {flag}")


def _check_out(out: Path, overwrite: bool) -> None:
    """`UserError` unless `out` is new, an empty folder, or (with --overwrite) a reconstruction or
    another c4d command's output (`c4d_core.ownership`)."""
    if check_folder(out, "run", overwrite) == "run" and not overwrite:
        raise UserError(f"--out {str(out)!r} already holds a reconstruction; pass --overwrite to "
                        "replace it (it is kept until the new one is complete) or give another folder")


class _FlowWithProgress:
    """Runs a flow estimator over the pairs in chunks, with a progress bar: a chunk holds the pairs
    whose earlier frame lies in a block of `frames_per_chunk` frames, so an estimator that reuses
    work between pairs of nearby frames (`dis...+chain`: the consecutive steps) keeps most of it."""

    def __init__(self, estimator, frames_per_chunk: int = 16):
        self.estimator, self.frames_per_chunk = estimator, frames_per_chunk

    def flow(self, frames: np.ndarray, pairs) -> np.ndarray:
        pairs = [tuple(map(int, p)) for p in pairs]
        out = np.zeros((len(pairs), *frames.shape[1:3], 2), np.float32)  # (P,H,W,2)
        blocks: dict[int, list[int]] = {}  # block of the earlier frame -> indices of its pairs
        for p, pair in enumerate(pairs):
            blocks.setdefault(min(pair) // self.frames_per_chunk, []).append(p)
        for block in tqdm(sorted(blocks), desc="optical flow", unit="chunk", leave=False):
            index = blocks[block]
            out[index] = self.estimator.flow(frames, [pairs[p] for p in index])
        return out


def run(args: argparse.Namespace) -> int:
    from c4d_pipeline.flow import build_flow
    from c4d_pipeline.pointmap_sources import build_pointmaps
    from c4d_pipeline.pipeline import reconstruct
    from c4d_pipeline.scene_graph import graph_from_config
    from c4d_pipeline.video_input import load_video_input, network_intrinsics, read_intrinsics
    from c4d_pipeline.windows import plan_windows, reconstruct_windowed
    from dynpt.device import device_for

    # 1. Everything the user named, checked before any heavy work.
    cfg = load_run_config(args)
    configure_threads(threads=cfg.threads)  # for the networks, tracking and flow alike
    device_for(cfg.device)  # a GPU this machine lacks: one line here, not deep inside torch
    if not Path(args.video).exists():
        raise UserError(f"video {args.video!r} does not exist; pass a video file or a folder of frames")
    if not cfg.pointmaps.checkpoint:
        raise UserError("no pointmap checkpoint: give --pointmaps CKPT (or pointmaps.checkpoint=CKPT)")
    _check_file(cfg.pointmaps.checkpoint, "pointmap checkpoint", "--pointmaps")
    _check_file(cfg.tracker.checkpoint, "tracker checkpoint", "--tracker")
    known = read_intrinsics(cfg.intrinsics.known) if cfg.intrinsics.known else None  # (N,4) source px
    out = Path(args.out)
    _check_out(out, args.overwrite)
    seconds: dict[str, float] = {}

    start = time.perf_counter()
    log.info("loading the pointmap network from %s", cfg.pointmaps.checkpoint)
    source = build_pointmaps(f"dust3r:{cfg.pointmaps.checkpoint}", cfg, device=cfg.device, progress=True)
    tracker = None
    if cfg.tracker.checkpoint:
        from dynpt.inference import load_tracker

        log.info("loading the tracker from %s", cfg.tracker.checkpoint)
        tracker = load_tracker(cfg.tracker.checkpoint, cfg.device)
    else:
        log.warning("no --tracker given: motion masks from the flow-only baseline (MonST3R-style), "
                    "and no trajectory smoothing (stage 2)")
    flow = _FlowWithProgress(build_flow(cfg.flow, device=cfg.device))
    seconds["load_models"] = time.perf_counter() - start

    # 2. Frames at the network's resolution.
    start = time.perf_counter()
    size = cfg.pointmaps.size or source.image_size
    video = load_video_input(args.video, size=size, stride=cfg.video.stride,
                             max_frames=cfg.video.max_frames or None)
    frames = video.frames
    T, H, W = frames.shape[:3]
    seconds["read_video"] = time.perf_counter() - start
    log.info("%d frames of %dx%d (source %dx%d)", T, W, H, video.preprocessing.source_hw[1],
             video.preprocessing.source_hw[0])
    if T < 2:
        raise UserError(f"{args.video} gives {T} frame(s) at video.stride={cfg.video.stride} (--stride); "
                        "a reconstruction needs at least 2: lower the stride or use a longer video")
    graph_from_config(T, cfg.graph)  # a graph that does not connect the frames: refused here
    if cfg.window.frames:  # windows that cannot hold that graph: refused here too
        plan_windows(T, cfg.window.frames, cfg.window.overlap, cfg.graph)
    intrinsics = None if known is None else network_intrinsics(
        known, video, read_whole=not cfg.video.max_frames or T < cfg.video.max_frames)  # (T,4)

    # 3 and 4 write into OUT.partial, which becomes OUT when complete (an old OUT stays till then).
    with staged_folder(out) as stage:
        mark_folder(stage, "run")
        write_text(stage / "config.yaml", to_yaml(cfg))  # every input read: what runs now

        # 3. Tracks on the same frames.
        tracks = None
        if tracker is not None:
            start = time.perf_counter()
            log.info("tracking points (grid %d px)", cfg.tracker.grid_size)
            tracks = tracker.track(frames, grid_size=cfg.tracker.grid_size, seed=int(cfg.seed))
            seconds["tracking"] = time.perf_counter() - start

        # 4. Pointmaps, flow, masks, optimisation, files.
        log.info("reconstructing: pointmaps, optical flow (%s), motion masks, optimisation", cfg.flow)
        inputs = {
            "video": str(Path(args.video).resolve()),
            "pointmaps_checkpoint": str(Path(cfg.pointmaps.checkpoint).resolve()),
            "tracker_checkpoint": str(Path(cfg.tracker.checkpoint).resolve()) if cfg.tracker.checkpoint else None,
            "network_size": size, "frame_indices": video.source_indices.tolist(),
            "source_hw": list(video.preprocessing.source_hw), "resized_hw": list(video.preprocessing.resized_hw),
            "crop_xy": list(video.preprocessing.crop_xy),
            "seconds_before_reconstruction": seconds,
        }
        rec = (reconstruct_windowed if cfg.window.frames else reconstruct)(
            frames, source, flow, tracks, cfg, stage, inputs={**inputs, "fps": video.fps},
            timestamps=video.timestamps, intrinsics=intrinsics)
    stage_seconds = rec.report["seconds"]
    log.info("wrote %s (%s)", out, ", ".join(f"{k} {v:.1f}s" for k, v in {**seconds, **stage_seconds}.items()))
    return 0
