"""Pairwise pointmaps from a DUSt3R-family network (DUSt3R, MASt3R, MonST3R checkpoints).

Implements `c4d_pipeline.pointmaps.PointmapSource`: frames uint8 (T,H,W,3), already at the network
resolution (`c4d_pipeline.video_input.dust3r_resize`: H, W multiples of 16), and directed edges
(E,2) go in; `PairwisePointmaps` come out, pts_i / pts_j both in view i's camera frame, conf >= 1.

Pairs run in batches, in float32 by default as the official inference does (`precision='fp32'`,
config key `pointmaps.precision`). `precision='bf16'` runs the encoder and decoders under bfloat16
autocast on a GPU (the heads stay in float32): faster and smaller, but pointmaps move by about
1 % per pixel (median; up to 5 % at the 99th percentile) from the float32 result (measured with
the same autocast on the CPU, docs/RESULTS.md section 5), so it is an explicit choice; on a CPU
it is ignored. On a GPU the batch size is
estimated from free memory and halved on out-of-memory; on a CPU it is fixed.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from c4d_core.errors import UserError
from c4d_pipeline.pointmaps import PairwisePointmaps, sanitize
from dynpt.device import (autocast, bf16_supported, device_for, free_memory, pair_batch_size,
                          pin_memory, pointmap_autocast_dtype)
from dynpt.dust3r.net import Dust3rNet, load_dust3r

log = logging.getLogger(__name__)


def to_network_input(frames: np.ndarray) -> torch.Tensor:
    """uint8 (T,H,W,3) RGB -> float32 (T,3,H,W) in [-1, 1] (DUSt3R's Normalize(0.5, 0.5))."""
    return torch.from_numpy(np.ascontiguousarray(frames)).permute(0, 3, 1, 2).float() / 127.5 - 1.0


def pair_memory_bytes(net: Dust3rNet, height: int, width: int) -> int:
    """Rough peak activation bytes of one pair at inference: the two heads' full-resolution feature
    maps in float32 dominate (DPT: feature_dim at half and last_dim at full resolution), plus
    the encoder/decoder tokens. A deliberate overestimate used only to pick a batch size."""
    cfg = net.cfg
    pixels = height * width
    head_channels = cfg.dpt_feature_dim + cfg.dpt_last_dim + 4 if cfg.head_type == "dpt" else 8
    tokens = pixels // cfg.patch_size ** 2 * (cfg.enc_embed_dim * 6 + cfg.dec_embed_dim * (cfg.dec_depth + 6))
    return 2 * 4 * (3 * pixels * head_channels + tokens)


class Dust3rPointmaps:
    """Pointmap source running a `Dust3rNet` on image pairs.

    net: the network (eval mode); device: torch device (default cuda if available, else cpu);
    batch_size: pairs per forward pass, or 0 for automatic (GPU: from free memory; CPU: 2);
    progress: show a progress bar over the pairs; precision: 'fp32' (default, the official
    inference) or 'bf16' (bfloat16 autocast on a GPU, float32 heads; ignored on a CPU).
    """

    def __init__(self, net: Dust3rNet, device: str | torch.device | None = None, batch_size: int = 0,
                 progress: bool = False, precision: str = "fp32"):
        self.device = device_for(device)
        self.net = net.to(self.device).eval()
        self.amp_dtype = pointmap_autocast_dtype(self.device.type, precision, bf16_supported(self.device))
        if batch_size < 0:
            raise UserError(f"pointmap batch size must be >= 0 (0 = automatic), got {batch_size}")
        self.batch_size = batch_size
        self.progress = progress

    @classmethod
    def from_checkpoint(cls, path: str | Path, device=None, batch_size: int = 0,
                        progress: bool = False, precision: str = "fp32") -> "Dust3rPointmaps":
        """Load an official DUSt3R/MASt3R/MonST3R checkpoint file (see `load_dust3r`)."""
        net, report = load_dust3r(path)
        if report.ignored_keys:
            log.info("pointmap checkpoint %s: ignored %d tensors not used for pointmaps",
                     path, len(report.ignored_keys))
        return cls(net, device, batch_size, progress, precision)

    @property
    def image_size(self) -> int:
        """Long side (512) or square side (224) the network was trained at."""
        return self.net.cfg.img_size

    def _auto_batch(self, height: int, width: int) -> int:
        weights = sum(p.numel() * p.element_size() for p in self.net.parameters())
        return pair_batch_size(free_memory(self.device), weights,
                               pair_memory_bytes(self.net, height, width))

    @torch.no_grad()
    def _run(self, images: torch.Tensor, idx_i: np.ndarray, idx_j: np.ndarray):
        """Network outputs for one batch of pairs, moved to the CPU as float32 numpy arrays."""
        img1 = images[idx_i].to(self.device, non_blocking=True)  # (b,3,H,W)
        img2 = images[idx_j].to(self.device, non_blocking=True)
        with autocast(self.device.type, self.amp_dtype):
            outputs = self.net(img1, img2)
        return [o.float().cpu().numpy() for o in outputs]

    def pointmaps(self, frames: np.ndarray, edges: np.ndarray) -> PairwisePointmaps:
        """frames uint8 (T,H,W,3) at network resolution; edges int (E,2) -> PairwisePointmaps."""
        if frames.dtype != np.uint8 or frames.ndim != 4 or frames.shape[-1] != 3:
            raise UserError(f"the pointmap network needs uint8 RGB frames (T,H,W,3), got "
                            f"{frames.dtype} {frames.shape}")
        T, H, W = frames.shape[:3]
        p = self.net.cfg.patch_size
        if H % p or W % p:
            raise UserError(f"frames of {W}x{H} are not multiples of {p} pixels; resize them with "
                            "c4d_pipeline.video_input (DUSt3R preprocessing) first")
        edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
        if len(edges) and (edges.min() < 0 or edges.max() >= T):
            raise UserError(f"pointmap pairs refer to frames outside 0..{T - 1}")
        images = to_network_input(frames)  # (T,3,H,W)
        if pin_memory(self.device.type):
            images = images.pin_memory()
        E = len(edges)
        out = {k: np.empty((E, H, W, 3), np.float32) for k in ("pts_i", "pts_j")}
        out |= {k: np.empty((E, H, W), np.float32) for k in ("conf_i", "conf_j")}
        batch = self.batch_size or self._auto_batch(H, W)
        start = 0
        bar = tqdm(total=E, desc="pointmaps", unit="pair", disable=not self.progress, leave=False)
        while start < E:
            stop = min(start + batch, E)
            try:
                pts_i, conf_i, pts_j, conf_j = self._run(images, edges[start:stop, 0], edges[start:stop, 1])
            except torch.cuda.OutOfMemoryError:
                if batch == 1:
                    raise UserError(f"one {W}x{H} image pair does not fit in GPU memory; use a smaller "
                                    "network size (--size 224) or run on the CPU (device=cpu)") from None
                batch = max(1, batch // 2)
                torch.cuda.empty_cache()
                log.info("pointmaps: out of GPU memory, batch size lowered to %d pairs", batch)
                continue
            sl = slice(start, stop)
            out["pts_i"][sl], out["conf_i"][sl] = sanitize(pts_i, conf_i)
            out["pts_j"][sl], out["conf_j"][sl] = sanitize(pts_j, conf_j)
            bar.update(stop - start)
            start = stop
        bar.close()
        result = PairwisePointmaps(edges=edges, **out)
        result.validate(T, (H, W))
        return result
