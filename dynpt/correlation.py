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


def _to_cells(xy: torch.Tensor, cell: float, align_corners: bool) -> torch.Tensor:
    """Input-pixel xy (...,2) -> feature-map coordinates in cells (see the module doc): where
    `grid_sample` with `_to_grid`'s grid samples."""
    return xy / cell if align_corners else (xy + 0.5) / cell - 0.5


class _PatchCorrelation(torch.autograd.Function):
    """rows (R,C), index (B,N,K) into rows, query (B,N,Q,C) -> (B,N,K,Q): rows[index] @ query^T.

    Autograd would keep the gathered (B,N,K,C) rows for the backward pass; this keeps the index
    (and `rows`, which the window holds anyway) and gathers them again there (a copy, far cheaper
    than the products)."""

    @staticmethod
    @torch.amp.custom_fwd(device_type="cuda")
    def forward(ctx, rows, index, query):
        B, N, K = index.shape
        ctx.save_for_backward(rows, index, query)
        return rows.index_select(0, index.flatten()).view(B, N, K, -1) @ query.transpose(-1, -2)

    @staticmethod
    @torch.amp.custom_bwd(device_type="cuda")  # under bf16 autocast: the forward's dtypes
    def backward(ctx, grad):
        rows, index, query = ctx.saved_tensors
        grad_rows = grad_query = None
        if ctx.needs_input_grad[0]:
            flat = (grad @ query).flatten(0, 2).to(rows.dtype)  # (B*N*K,C)
            grad_rows = rows.new_zeros(rows.shape).index_add_(0, index.flatten(), flat)
        if ctx.needs_input_grad[2]:
            B, N, K = index.shape
            patches = rows.index_select(0, index.flatten()).view(B, N, K, -1)
            grad_query = (grad.transpose(-1, -2) @ patches).to(query.dtype)
        return grad_rows, None, grad_query


def neighbourhood_correlation(
    fmap: torch.Tensor, query: torch.Tensor, xy: torch.Tensor, cell: float, radius: int,
    align_corners: bool = False,
) -> torch.Tensor:
    """All dot products between the (2r+1)^2 bilinear samples of fmap around xy and the query
    neighbourhoods: fmap (B,T,h,w,C) channels-last, query (B,N,Q,C), xy (B,T,N,2) pixels ->
    (B,N,T,P*Q), P=(2r+1)^2 target offsets (row-major dy, dx) major, query offsets minor.

    The same numbers as `grid_sample` (bilinear, border padding) of the P offsets of whole cells
    followed by the products, to rounding: the offsets share one pair of bilinear weights, so
    the products are taken with the (2r+2)^2 whole cells under the neighbourhood (edge cells
    repeated past the border, which is what border padding samples) and blended after.
    """
    B, T, h, w, C = fmap.shape
    N, k = xy.shape[2], 2 * radius + 2
    u = _to_cells(xy, cell, align_corners).transpose(1, 2)  # (B,N,T,2) in cells
    u = torch.nan_to_num(u).clamp(-k, max(h, w) + k)  # far outside: the same edge cells
    corner = u.floor()
    frac = u - corner  # (B,N,T,2) bilinear weights of the next cell in x and y
    first = corner.long() - radius  # (B,N,T,2) the patch's top-left cell
    steps = torch.arange(k, device=xy.device)
    xs = (first[..., 0, None] + steps).clamp_(0, w - 1)  # (B,N,T,k)
    ys = (first[..., 1, None] + steps).clamp_(0, h - 1)
    frames = torch.arange(B, device=xy.device)[:, None] * T + torch.arange(T, device=xy.device)  # (B,T)
    rows = (frames[:, None, :, None] * h + ys)[..., :, None] * w + xs[..., None, :]  # (B,N,T,k,k)
    products = _PatchCorrelation.apply(fmap.reshape(B * T * h * w, C), rows.flatten(2), query)
    products = products.unflatten(2, (T, k, k))  # (B,N,T,k,k,Q)
    fx, fy = (frac[..., i, None, None, None].to(products.dtype) for i in (0, 1))  # (B,N,T,1,1,1)
    x_blend = torch.lerp(products[..., :-1, :], products[..., 1:, :], fx)  # (B,N,T,k,k-1,Q)
    corr = torch.lerp(x_blend[..., :-1, :, :], x_blend[..., 1:, :, :], fy)  # (B,N,T,k-1,k-1,Q)
    return corr.flatten(3)


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
    Output (B,N,T,levels*out_dim). `align_corners` picks the sampling convention (module doc).
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

    @staticmethod
    def target_maps(pyramid: list[torch.Tensor]) -> list[torch.Tensor]:
        """The pyramid (per level (B,T,C,h,w)) channels-last, (B,T,h,w,C), as `forward` reads it."""
        return [f.permute(0, 1, 3, 4, 2).contiguous() for f in pyramid]

    def forward(
        self, targets: list[torch.Tensor], query_feats: list[torch.Tensor], xy: torch.Tensor, stride: int
    ) -> torch.Tensor:
        """targets: `target_maps` of the pyramid; query_feats: per level (B,N,P,C); xy (B,T,N,2)
        pixels -> (B,N,T,levels*out)."""
        embs = [
            self.mlp(neighbourhood_correlation(fmap, q, xy, stride * 2**i, self.radius, self.align_corners))
            for i, (fmap, q) in enumerate(zip(targets, query_feats))
        ]  # per level (B,N,T,out)
        return torch.cat(embs, dim=-1)
