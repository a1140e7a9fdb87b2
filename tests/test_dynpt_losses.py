"""DynPT losses against hand-computed values."""

from types import SimpleNamespace

import pytest
import torch

from dynpt.losses import LossWeights, bce_over_iterations, dynpt_loss, track_loss


def _batch(B=1, T=3, N=2):
    gt = torch.zeros(B, T, N, 2)
    visible = torch.ones(B, T, N, dtype=torch.bool)
    visible[:, :, 1] = False  # track 1 occluded throughout
    return {"tracks": gt, "visible": visible, "moving": torch.zeros(B, T, N, dtype=torch.bool)}


def test_track_loss_huber_l1_and_gamma():
    batch = _batch()
    valid = torch.ones(1, 3, 2, dtype=torch.bool)
    w = LossWeights(gamma=0.5, huber_delta_px=6.0)
    far = torch.zeros(1, 3, 2, 2)
    far[..., 0] = 10.0  # x off by 10, y exact: huber 6*(10-3)=42, mean over xy 21; L1 mean 5
    near = torch.zeros(1, 3, 2, 2)
    near[..., 0] = 2.0  # huber 0.5*4=2 -> mean 1; L1 mean 1
    vis, occ = track_loss([far, near], batch["tracks"], batch["visible"], valid, w)
    assert vis.item() == pytest.approx((0.5 * 21 + 1 * 1) / 2)
    assert occ.item() == pytest.approx((0.5 * 5 + 1 * 1) / 2)


def test_bce_masked_and_averaged_over_iterations():
    target = torch.tensor([[[1.0, 0.0]]])
    mask = torch.tensor([[[True, False]]])
    logits = [torch.zeros(1, 1, 2), torch.full((1, 1, 2), 100.0)]
    # iteration 0: -log(0.5); iteration 1: ~0; the masked-out entry never counts.
    assert bce_over_iterations(logits, target, mask).item() == pytest.approx(0.5 * 0.6931, abs=1e-3)


def test_total_loss_terms_weights_and_confidence_target():
    batch = _batch()
    batch["moving"][:, :, 0] = True
    coords = torch.zeros(1, 3, 2, 2, requires_grad=True)
    big = 50.0
    out = SimpleNamespace(
        coords=[coords],
        vis_logits=[torch.tensor([[[big, -big]] * 3])],
        conf_logits=[torch.full((1, 3, 2), big)],  # perfect prediction is within 12 px
        moving_logits=[torch.tensor([[[big, -big]] * 3])],
        valid=torch.ones(1, 3, 2, dtype=torch.bool),
    )
    total, terms = dynpt_loss(out, batch, LossWeights())
    assert set(terms) == {"track_visible", "track_occluded", "visibility", "confidence", "mobility"}
    assert total.item() == pytest.approx(0.0, abs=1e-6)
    # Now 20 px off: confidence target flips to 0 for visible points, mobility weight scales.
    out.coords = [coords + torch.tensor([20.0, 0.0])]
    out.moving_logits = [torch.zeros(1, 3, 2)]
    total, terms = dynpt_loss(out, batch, LossWeights(mobility=2.0, mobility_pos_weight=1.0))
    assert terms["confidence"].item() == pytest.approx(big, rel=1e-3)
    assert terms["mobility"].item() == pytest.approx(2 * 0.6931, abs=1e-3)
    assert terms["track_occluded"].item() == pytest.approx(0.01 * 10.0)
    total.backward()
    assert coords.grad is not None and coords.grad.abs().sum() > 0
