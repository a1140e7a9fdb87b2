"""Tracking videos with a trained DynPT: input checks, query sampling, resizing, both directions.

`Tracker.track` resizes the video to the model's `resolution` (if the config sets one), tracks
forward from every query frame with the model's sliding windows, and, for queries after the first
frame, backward by tracking the reversed video, so every frame gets a prediction.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from c4d_core.errors import UserError
from c4d_core.files import atomic_path
from c4d_core.geometry import rescale_pixels
from dynpt.checkpoint import load_checkpoint, model_from_checkpoint
from dynpt.device import autocast, bf16_supported, device_for, inference_autocast_dtype
from dynpt.model import DynPT
from dynpt.query_sampling import sample_queries


MIN_SIDE = 17  # px at the network's resolution: the CNN's 1/16 features need more than one cell


@dataclass
class TrackResult:
    """Tracker output (numpy, T frames, N tracks): tracks float32 (T,N,2) (x, y) input pixels;
    visible bool (T,N); confidence float32 (T,N) in [0,1]; moving float32 (T,N) probability that
    the point moves in the world; queries float32 (N,3) as (t, x, y)."""

    tracks: np.ndarray
    visible: np.ndarray
    confidence: np.ndarray
    moving: np.ndarray
    queries: np.ndarray

    def save(self, path: str | os.PathLike) -> Path:
        """Write all arrays to an .npz file atomically."""
        path = Path(path)
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez_compressed(fh, tracks=self.tracks, visible=self.visible,
                                confidence=self.confidence, moving=self.moving, queries=self.queries)
        return path

    def scaled(self, fx: float, fy: float) -> "TrackResult":
        """The same tracks in pixels of an image `fx` x `fy` times the size (pixel centres kept)."""
        if (fx, fy) == (1, 1):
            return self
        scale = np.array([fx, fy], np.float32)
        queries = self.queries.copy()
        queries[:, 1:] = rescale_pixels(queries[:, 1:], scale)
        return replace(self, tracks=rescale_pixels(self.tracks, scale), queries=queries)


def check_video(video) -> np.ndarray | torch.Tensor:
    """`video` as uint8 (T,H,W,3); a path (str or PathLike) is read with `dynpt.read_video`."""
    if isinstance(video, (str, os.PathLike)):
        from c4d_core.video import read_video

        video = read_video(video)
    if isinstance(video, torch.Tensor):
        shape, dtype_ok = tuple(video.shape), video.dtype == torch.uint8
    else:
        video = np.asarray(video)
        shape, dtype_ok = video.shape, video.dtype == np.uint8
    if len(shape) != 4 or shape[-1] != 3:
        raise UserError(f"video must be RGB frames of shape (T,H,W,3), got shape {shape}; "
                        "convert grey or RGBA frames to RGB first")
    if not dtype_ok:
        raise UserError(f"video must be uint8 (values 0..255), got {video.dtype}; convert it first")
    if shape[0] < 2:
        raise UserError(f"video has {shape[0]} frame(s); tracking needs at least 2")
    if shape[1] < 1 or shape[2] < 1:
        raise UserError(f"video frames are empty ({shape[1]}x{shape[2]} pixels)")
    return video


def _check_queries(queries, T: int, H: int, W: int) -> np.ndarray:
    q = np.asarray(queries.detach().cpu() if isinstance(queries, torch.Tensor) else queries, np.float32)
    if q.ndim != 2 or q.shape[1] != 3 or len(q) == 0:
        raise UserError(f"queries must be a non-empty (N,3) array of (t, x, y), got shape {q.shape}")
    if not np.isfinite(q).all():
        raise UserError("queries contain NaN or infinite values")
    t, x, y = q.T
    bad_t = (t < 0) | (t > T - 1) | (np.abs(t - np.round(t)) > 1e-3)
    if bad_t.any():
        raise UserError(f"query {int(np.argmax(bad_t))} has frame index {t[bad_t][0]:g}, but the video "
                        f"has frames 0..{T - 1}; give integer frame indices in that range")
    outside = (x < -0.5) | (x > W - 0.5) | (y < -0.5) | (y > H - 0.5)
    if outside.any():
        i = int(np.argmax(outside))
        raise UserError(f"query {i} at (x={x[i]:g}, y={y[i]:g}) lies outside the {W}x{H} frame; "
                        "give pixel coordinates with 0 <= x < W and 0 <= y < H")
    q[:, 0] = np.round(t)
    return q


def visibility(vis: torch.Tensor, conf: torch.Tensor, rule: str, threshold: float) -> torch.Tensor:
    """Visible flags (bool, same shape) from visibility and confidence probabilities (in [0, 1]):
    rule "vis_conf" is vis * conf > threshold (CoTracker3's online predictor, 0.6), "vis" is
    vis > threshold (its offline predictor, 0.9); the model config carries both."""
    if rule == "vis":
        return vis > threshold
    if rule == "vis_conf":
        return vis * conf > threshold
    raise UserError(f"model.visibility_rule={rule!r}: choose vis_conf or vis")


class Tracker:
    """A DynPT model in eval mode on a device, tracking whole videos."""

    def __init__(self, model: DynPT, device: str | torch.device | None = None):
        device = device_for(device)
        self.model = model.eval().to(device)
        self.device = device

    def _autocast(self):
        return autocast(self.device.type, inference_autocast_dtype(self.device.type,
                                                                   bf16_supported(self.device)))

    def _video_tensor(self, video, size: tuple[int, int]) -> torch.Tensor:
        """uint8 (T,H,W,3) -> uint8 (1,T,3,h,w) on the device, resized a few frames at a time."""
        video = torch.as_tensor(video)
        out = []
        for chunk in video.split(32):
            x = chunk.to(self.device).permute(0, 3, 1, 2)  # (t,3,H,W)
            if tuple(x.shape[-2:]) != size:
                x = F.interpolate(x.float(), size=size, mode="bilinear", align_corners=False,
                                  antialias=True).round().clamp(0, 255).to(torch.uint8)
            out.append(x)
        return torch.cat(out)[None]

    def _run(self, video: torch.Tensor, queries: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Final coords (T,N,2), logits (T,N,3) (vis, conf, moving) and valid (T,N) of one pass."""
        q = torch.from_numpy(queries).to(self.device)[None]  # (1,N,3)
        with self._autocast():
            out = self.model(video, q, iters=self.model.config["eval_iters"])
        logits = torch.stack([out.vis_logits[-1], out.conf_logits[-1], out.moving_logits[-1]], -1)
        return out.coords[-1][0].float(), logits[0].float(), out.valid[0]

    def _predict(self, video: torch.Tensor, queries: np.ndarray, backward: bool):
        """Forward pass, plus (as CoTracker3's predictor with backward tracking) a pass of every
        query over the reversed video whose results fill the frames before each query frame."""
        coords, logits, done = self._run(video, queries)  # (T,N,2), (T,N,3), (T,N)
        T = video.shape[1]
        tq = torch.from_numpy(queries[:, 0]).to(self.device)
        before = torch.arange(T, device=self.device)[:, None] < tq[None]  # (T,N)
        if backward and before.any():
            rev = queries.copy()
            rev[:, 0] = T - 1 - rev[:, 0]
            b_coords, b_logits, _ = self._run(video.flip(1), rev)
            fill = before[..., None]  # (T,N,1)
            coords = torch.where(fill, b_coords.flip(0), coords)  # back in forward time
            logits = torch.where(fill, b_logits.flip(0), logits)
            done = done | before
        return coords, logits, done

    @torch.inference_mode()
    def track(self, video, queries=None, grid_size: int = 20, seed: int = 0, backward: bool = True,
              max_points: int | None = None, support_grid: int = 0) -> TrackResult:
        """Track points through `video`: uint8 (T,H,W,3) numpy or torch, or the path of a video
        file or of a folder of frames (read at full size: `dynpt.read_video` reads a part).

        queries: float (N,3) as (t, x, y) in input pixels, or None for the paper's sampling on the
        first frame (per `grid_size` cell: max-gradient point + one random point, `seed`ed).
        backward: also track queries after frame 0 backward in time (else frames before a query
        frame keep the query position, visible False, confidence 0, moving NaN).
        max_points: track at most this many points jointly (memory grows linearly with it);
        None tracks all together (points inform each other through the transformer).
        support_grid: also track a support_grid x support_grid grid of points from frame 0 with
        every chunk of queries, then drop them (CoTracker3's predictor uses 6 with given queries).
        """
        video = check_video(video)
        if support_grid < 0 or support_grid == 1:
            raise UserError(f"support_grid={support_grid}: give 0 (none) or a grid size of at least 2")
        T, H, W = video.shape[:3]
        if queries is None:
            first = video[0].cpu().numpy() if isinstance(video, torch.Tensor) else video[0]
            queries = sample_queries(first, grid_size, seed)
        queries = _check_queries(queries, T, H, W)
        cfg = self.model.config
        h, w = cfg["resolution"] or (H, W)
        if min(h, w) < MIN_SIDE:
            origin = ("the checkpoint's model.resolution" if cfg["resolution"] else "the frames' own "
                      "size: --size/--max-size of c4d track, --size of c4d run, eval.resolution of "
                      "c4d eval")
            raise UserError(f"the tracker's network size {w}x{h} pixels ({origin}) is too small: it "
                            f"needs at least {MIN_SIDE}x{MIN_SIDE} (its coarsest features are 1/16 "
                            "of the frame)")
        sx, sy = w / W, h / H
        scaled = queries.copy()
        scaled[:, 1] = rescale_pixels(queries[:, 1], sx)
        scaled[:, 2] = rescale_pixels(queries[:, 2], sy)
        frames = self._video_tensor(video, (h, w))  # (1,T,3,h,w) uint8

        chunk = max_points or len(queries)
        support = support_queries(support_grid, h, w)  # (G,3)
        parts = [[x[:, :min(chunk, len(queries) - i)] for x in
                  self._predict(frames, np.concatenate([scaled[i:i + chunk], support]), backward)]
                 for i in range(0, len(queries), chunk)]
        coords, logits, done = (torch.cat(p, dim=1) for p in zip(*parts))  # (T,N,...)
        coords[..., 0] = rescale_pixels(coords[..., 0], sx, inverse=True)
        coords[..., 1] = rescale_pixels(coords[..., 1], sy, inverse=True)
        prob = torch.sigmoid(logits)  # (T,N,3)
        visible = visibility(prob[..., 0], prob[..., 1], cfg["visibility_rule"],
                             cfg["visibility_threshold"])
        confidence, moving = prob[..., 1], prob[..., 2]
        # the query frame is known exactly; frames not predicted get neutral values
        tq = torch.from_numpy(queries[:, 0]).long().to(self.device)
        n = torch.arange(len(queries), device=self.device)
        xy_q = torch.from_numpy(queries[:, 1:]).to(self.device)
        coords = torch.where(done[..., None], coords, xy_q[None])
        coords[tq, n] = xy_q
        visible = visible & done
        visible[tq, n] = True
        confidence = torch.where(done, confidence, torch.zeros_like(confidence))
        moving = torch.where(done, moving, torch.full_like(moving, float("nan")))
        np_ = lambda x: x.cpu().numpy()
        return TrackResult(tracks=np_(coords).astype(np.float32), visible=np_(visible),
                           confidence=np_(confidence).astype(np.float32),
                           moving=np_(moving).astype(np.float32), queries=queries)


def support_queries(size: int, h: int, w: int) -> np.ndarray:
    """(size^2, 3) queries at frame 0 on CoTracker3's support grid of an h x w frame: rows and
    columns evenly spaced between a margin of w/64 pixels from the edges, row-major."""
    if size == 0:
        return np.zeros((0, 3), np.float32)
    m = w / 64
    y, x = np.meshgrid(np.linspace(m, h - m, size), np.linspace(m, w - m, size), indexing="ij")
    return np.stack([np.zeros(size * size), x.ravel(), y.ravel()], -1).astype(np.float32)


def load_tracker(path: str | os.PathLike, device: str | torch.device | None = None) -> Tracker:
    """A `Tracker` (eval mode) from a DynPT checkpoint file (no config file needed), or from
    `cotracker3:PATH`, a CoTracker3 release file (its windowing guessed as in
    `dynpt.cotracker3_weights.config_from_state`; the mobility head untrained)."""
    if str(path).startswith("cotracker3:"):
        from dynpt.cotracker3_weights import build_from_file, parse_init

        return Tracker(build_from_file(parse_init(str(path))), device)
    ckpt = load_checkpoint(path)
    return Tracker(model_from_checkpoint(ckpt, path), device)
