"""Multi-scale 4-D correlation between query-point neighbourhoods and current track neighbourhoods.

Coordinates are input pixels with pixel centres at integers. A feature map of stride s covers
s x s input pixels per cell, so input pixel x sits at feature coordinate (x + 0.5) / s - 0.5
(`align_corners=False`, the default). With `align_corners=True` (CoTracker3's convention, for
its weights) pixel x sits at x / s and the first and last cells' centres span the map.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


def feature_pyramid(fmaps: torch.Tensor, levels: int) -> list[torch.Tensor]:
    """(B,T,C,H,W) -> `levels` maps, each a 2x2 average pool of the previous one (not re-normalised)."""
    B, T = fmaps.shape[:2]
    pyramid = [fmaps]
    for _ in range(levels - 1):
        prev = pyramid[-1].flatten(0, 1)  # (B*T,C,h,w)
        pyramid.append(F.avg_pool2d(prev, 2, stride=2).unflatten(0, (B, T)))
    return pyramid


def _offsets(radius: int, device) -> torch.Tensor:
    """(P,2) integer (dx, dy) offsets of the (2r+1)^2 neighbourhood, row-major in (dy, dx)."""
    r = torch.arange(-radius, radius + 1, device=device, dtype=torch.float32)
    dy, dx = torch.meshgrid(r, r, indexing="ij")
    return torch.stack([dx, dy], dim=-1).reshape(-1, 2)


def _to_grid(xy: torch.Tensor, cell: float, h: int, w: int, align_corners: bool) -> torch.Tensor:
    """Input-pixel xy (...,2) -> grid_sample coordinates on an h x w map (see the module doc)."""
    if align_corners:
        u = xy / cell  # feature-map coordinates in cell centres from the first centre
        return torch.stack([2 * u[..., 0] / max(w - 1, 1) - 1, 2 * u[..., 1] / max(h - 1, 1) - 1], dim=-1)
    u = (xy + 0.5) / cell  # feature-map coordinates in "cells from the left edge"
    return torch.stack([2 * u[..., 0] / w - 1, 2 * u[..., 1] / h - 1], dim=-1)


def sample_neighbourhoods(
    fmap: torch.Tensor, xy: torch.Tensor, cell: float, radius: int, align_corners: bool = False
) -> torch.Tensor:
    """Bilinear samples of fmap (B,T,C,h,w) around xy (B,T,N,2) -> (B,T,C,N,P), P=(2r+1)^2.

    `cell` is the map's stride in input pixels; the offsets are whole cells of this level.
    """
    B, T, C, h, w = fmap.shape
    points = xy[:, :, :, None, :] + cell * _offsets(radius, xy.device)  # (B,T,N,P,2)
    grid = _to_grid(points, cell, h, w, align_corners).flatten(0, 1).to(fmap.dtype)  # (B*T,N,P,2)
    out = F.grid_sample(
        fmap.flatten(0, 1), grid, mode="bilinear", padding_mode="border", align_corners=align_corners
    )  # (B*T,C,N,P)
    return out.unflatten(0, (B, T))  # (B,T,C,N,P), channels first: no copy before the einsum


def sample_query_neighbourhoods(
    fmap: torch.Tensor, t: torch.Tensor, xy: torch.Tensor, cell: float, radius: int,
    align_corners: bool = False,
) -> torch.Tensor:
    """Neighbourhoods of each query in its own frame: fmap (B,T,C,h,w), t (B,N) long frame index
    into fmap, xy (B,N,2) -> (B,N,P,C). Frames are indexed exactly (no blending across time)."""
    B, T, C, h, w = fmap.shape
    N = t.shape[1]
    points = xy[:, :, None, :] + cell * _offsets(radius, xy.device)  # (B,N,P,2)
    grid = _to_grid(points, cell, h, w, align_corners).to(fmap.dtype)  # (B,N,P,2)
    out = fmap.new_zeros(B, N, grid.shape[2], C)
    for b in range(B):
        for frame in t[b].unique().tolist():
            sel = (t[b] == frame).nonzero(as_tuple=True)[0]  # tracks queried at this frame
            s = F.grid_sample(
                fmap[b, frame][None], grid[b, sel][None], mode="bilinear",
                padding_mode="border", align_corners=align_corners,
            )  # (1,C,n,P)
            out[b, sel] = s[0].permute(1, 2, 0).to(out.dtype)  # autocast runs grid_sample in fp32
    return out


class CorrelationEncoder(nn.Module):
    """4-D correlation per pyramid level, embedded by one MLP shared across levels.

    For each track, frame and level, all (2r+1)^2 x (2r+1)^2 dot products between the features
    around the current estimate and those around the query point, then MLP -> `out_dim`.
    Output (B,T,N,levels*out_dim). `align_corners` picks the sampling convention (module doc).
    """

    def __init__(self, levels: int, radius: int, hidden_dim: int, out_dim: int, align_corners: bool = False):
        super().__init__()
        self.levels, self.radius, self.align_corners = levels, radius, align_corners
        p = (2 * radius + 1) ** 2
        self.mlp = nn.Sequential(nn.Linear(p * p, hidden_dim), nn.GELU(), nn.Linear(hidden_dim, out_dim))
        self.out_dim = levels * out_dim

    def query_features(
        self, pyramid: list[torch.Tensor], t: torch.Tensor, xy: torch.Tensor, stride: int
    ) -> list[torch.Tensor]:
        """Per level (B,N,P,C): neighbourhoods of the queries (t (B,N) local frame, xy (B,N,2))."""
        return [
            sample_query_neighbourhoods(f, t, xy, stride * 2**i, self.radius, self.align_corners)
            for i, f in enumerate(pyramid)
        ]

    def forward(
        self, pyramid: list[torch.Tensor], query_feats: list[torch.Tensor], xy: torch.Tensor, stride: int
    ) -> torch.Tensor:
        """pyramid: per level (B,T,C,h,w); query_feats: per level (B,N,P,C); xy (B,T,N,2) pixels."""
        embs = []
        for i, (fmap, q) in enumerate(zip(pyramid, query_feats)):
            target = sample_neighbourhoods(fmap, xy, stride * 2**i, self.radius, self.align_corners)  # (B,T,C,N,P)
            corr = torch.einsum("btcnp,bnqc->btnpq", target, q)  # (B,T,N,P,P)
            embs.append(self.mlp(corr.flatten(-2)))  # (B,T,N,out)
        return torch.cat(embs, dim=-1)  # (B,T,N,levels*out)
