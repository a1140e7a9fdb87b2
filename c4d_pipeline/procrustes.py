"""The weighted similarity fit (Umeyama) of initialisation, ground-truth pointmaps and evaluation."""

from __future__ import annotations

import torch


def weighted_procrustes(
    src: torch.Tensor, dst: torch.Tensor, weights: torch.Tensor, with_scale: bool = True
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Batched weighted Umeyama: argmin over (s, R, t) of sum_n w_n ||dst_n - (s R src_n + t)||^2.

    src, dst (B,N,3), weights (B,N) >= 0. Returns scale (B,), rotation (B,3,3), translation (B,3),
    computed in float64 and returned in src's dtype. `with_scale=False` fixes s = 1 (rigid).
    """
    dtype = src.dtype
    src, dst, weights = src.double(), dst.double(), weights.double()
    w = weights / weights.sum(-1, keepdim=True).clamp_min(1e-12)  # (B,N)
    mu_s = torch.einsum("bn,bnc->bc", w, src)  # (B,3)
    mu_d = torch.einsum("bn,bnc->bc", w, dst)  # (B,3)
    cs, cd = src - mu_s[:, None], dst - mu_d[:, None]  # (B,N,3)
    cov = torch.einsum("bn,bni,bnj->bij", w, cd, cs)  # (B,3,3)
    u, sv, vt = torch.linalg.svd(cov)
    sign = torch.sign(torch.linalg.det(u @ vt))  # (B,)
    d = torch.ones_like(sv)
    d[:, 2] = torch.where(sign == 0, torch.ones_like(sign), sign)
    rot = u @ torch.diag_embed(d) @ vt  # (B,3,3)
    if with_scale:
        var_s = torch.einsum("bn,bnc->b", w, cs * cs).clamp_min(1e-12)  # (B,)
        scale = (sv * d).sum(-1) / var_s
    else:
        scale = torch.ones_like(sv[:, 0])
    trans = mu_d - scale[:, None] * torch.einsum("bij,bj->bi", rot, mu_s)
    return scale.to(dtype), rot.to(dtype), trans.to(dtype)
