"""DynPT training losses (CoTracker3 recipe plus the paper's mobility term).

With M refinement iterations i = 0..M-1 and per-iteration predictions:
- track: Huber(delta) on GT-visible positions and L1 on GT-occluded ones, each a masked mean,
  weighted gamma^(M-1-i) (the last iteration gets 1) and divided by M;
- visibility, mobility: binary cross-entropy of the logits, plain mean over iterations;
- confidence: BCE against "this iteration's (detached) prediction is within `conf_radius_px` of
  the truth", on GT-visible points only.
Every weight is a config value (`loss:` section). Coordinates are pixels of the training crop.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from c4d_core.config import defaults_from


@dataclass(frozen=True)
@defaults_from("dynpt", "loss")
class LossWeights:
    """The `loss:` keys of configs/dynpt, where each is explained; defaults from the schema's root
    preset (tiny-cpu)."""

    track_visible: float
    track_occluded: float
    huber_delta_px: float
    gamma: float
    visibility: float
    confidence: float
    conf_radius_px: float
    mobility: float
    mobility_pos_weight: float

    @classmethod
    def from_config(cls, cfg) -> "LossWeights":
        """From the `loss:` config section (a mapping with these field names)."""
        return cls(**{k: float(cfg[k]) for k in cls.__dataclass_fields__})


def _masked_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of `values` where `mask` is True; 0 (with a graph) when nothing is masked in."""
    mask = mask.to(values.dtype)
    return (values * mask).sum() / mask.sum().clamp(min=1.0)


def track_loss(coords: list[torch.Tensor], gt: torch.Tensor, visible: torch.Tensor,
               valid: torch.Tensor, w: LossWeights) -> tuple[torch.Tensor, torch.Tensor]:
    """(visible term, occluded term), each gamma-weighted over iterations.

    coords: M tensors (B,T,N,2); gt (B,T,N,2); visible, valid (B,T,N) bool.
    """
    num_iters = len(coords)
    vis_total = occ_total = gt.new_zeros(())
    for i, pred in enumerate(coords):
        weight = w.gamma ** (num_iters - 1 - i)
        huber = F.huber_loss(pred, gt, reduction="none", delta=w.huber_delta_px).mean(-1)  # (B,T,N)
        l1 = (pred - gt).abs().mean(-1)  # (B,T,N)
        vis_total = vis_total + weight * _masked_mean(huber, visible & valid)
        occ_total = occ_total + weight * _masked_mean(l1, ~visible & valid)
    return vis_total / num_iters, occ_total / num_iters


def bce_over_iterations(logits: list[torch.Tensor], target: torch.Tensor, mask: torch.Tensor,
                        pos_weight: float = 1.0) -> torch.Tensor:
    """Masked BCE-with-logits averaged uniformly over the M iterations; logits (B,T,N)."""
    target = target.to(logits[0].dtype)
    weight = 1.0 + (pos_weight - 1.0) * target  # (B,T,N)
    losses = [
        _masked_mean(weight * F.binary_cross_entropy_with_logits(lg, target, reduction="none"), mask)
        for lg in logits
    ]
    return torch.stack(losses).mean()


def dynpt_loss(output, batch: dict, w: LossWeights) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Total loss and its weighted terms.

    output: a `DynPTOutput` (per-iteration lists `coords` (B,T,N,2), `vis_logits`,
    `conf_logits`, `moving_logits` (B,T,N), and `valid` (B,T,N) bool).
    batch: `tracks` (B,T,N,2) pixels, `visible` (B,T,N) bool, `moving` (B,T,N) bool.
    """
    gt, visible, moving = batch["tracks"], batch["visible"], batch["moving"]
    valid = output.valid
    coords = [c.float() for c in output.coords]
    track_vis, track_occ = track_loss(coords, gt, visible, valid, w)
    with torch.no_grad():
        close = [((c - gt).norm(dim=-1) < w.conf_radius_px) for c in coords]  # M x (B,T,N)
    conf = torch.stack([
        bce_over_iterations([lg.float()], target, visible & valid)
        for lg, target in zip(output.conf_logits, close)
    ]).mean()
    terms = {
        "track_visible": w.track_visible * track_vis,
        "track_occluded": w.track_occluded * track_occ,
        "visibility": w.visibility * bce_over_iterations(
            [lg.float() for lg in output.vis_logits], visible, valid),
        "confidence": w.confidence * conf,
        "mobility": w.mobility * bce_over_iterations(
            [lg.float() for lg in output.moving_logits], moving, valid, w.mobility_pos_weight),
    }
    return torch.stack(list(terms.values())).sum(), terms
