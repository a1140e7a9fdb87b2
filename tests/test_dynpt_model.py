"""DynPT model: shapes for odd sizes, sliding windows, later queries, gradients, determinism,
and the DUSt3R encoder loaded from a file with the official key layout."""

import argparse

import pytest
import torch

from c4d_core.config import load_config
from c4d_core.errors import UserError
from dynpt.dust3r.vit_encoder import Dust3rEncoder
from dynpt.model import build_model



def tiny_cfg(*overrides):
    return load_config("dynpt/model", "tiny", overrides=overrides).model


def make_model(*overrides, seed=0):
    torch.manual_seed(seed)
    return build_model(tiny_cfg(*overrides))


def random_video(B, T, H, W, seed=0):
    g = torch.Generator().manual_seed(seed)
    # smooth random blobs, so features and correlations are not pure noise
    low = torch.rand(B * T, 3, H // 8 + 2, W // 8 + 2, generator=g)
    video = torch.nn.functional.interpolate(low, size=(H, W), mode="bilinear", align_corners=False)
    return (255 * video).reshape(B, T, 3, H, W)


def random_queries(B, N, T, H, W, seed=1, max_t=None):
    g = torch.Generator().manual_seed(seed)
    t = torch.randint(0, max_t or T, (B, N), generator=g).float()
    return torch.stack([t, torch.rand(B, N, generator=g) * (W - 1), torch.rand(B, N, generator=g) * (H - 1)], -1)


@pytest.mark.parametrize("encoder", [False, True])
def test_shapes_and_dtypes_for_odd_sizes(encoder):
    model = make_model(*(["model.encoder_3d.random_init=true"] if encoder else []))
    B, T, H, W, N = 2, 11, 37, 53, 6  # T > window (8): three windows
    queries = random_queries(B, N, T, H, W)
    model.train()
    out = model(random_video(B, T, H, W), queries)
    assert len(out.coords) == len(out.vis_logits) == len(out.moving_logits) == 2  # train_iters
    for xy, vis, conf, mov in zip(out.coords, out.vis_logits, out.conf_logits, out.moving_logits):
        assert xy.shape == (B, T, N, 2) and xy.dtype == torch.float32
        assert vis.shape == conf.shape == mov.shape == (B, T, N)
        assert torch.isfinite(xy).all() and torch.isfinite(mov).all()
    assert out.valid.dtype == torch.bool
    expected = torch.arange(T)[None, :, None] >= queries[..., 0].long()[:, None, :]
    assert torch.equal(out.valid, expected)
    model.eval()
    with torch.no_grad():
        assert len(model(random_video(B, 3, H, W), random_queries(B, N, 3, H, W)).coords) == 3  # eval_iters


def test_sliding_windows_leave_the_first_window_unchanged():
    """Frames only the first window covers come out as in a single-window run on those frames."""
    model = make_model().eval()
    video = random_video(1, 20, 40, 56)  # windows start at 0, 4, 8, 12 (window 8, stride 4)
    queries = random_queries(1, 7, 8, 40, 56, max_t=4)
    with torch.no_grad():
        long = model(video, queries)
        single = model(video[:, :8], queries)
    for a, b in zip(long.coords, single.coords):
        torch.testing.assert_close(a[:, :4], b[:, :4], rtol=0, atol=1e-5)
    torch.testing.assert_close(long.moving_logits[-1][:, :4], single.moving_logits[-1][:, :4], rtol=0, atol=1e-5)
    # the later windows did change the overlapping frames (they saw more of the video)
    assert not torch.allclose(long.coords[-1][:, 4:8], single.coords[-1][:, 4:8], atol=1e-5)


def test_query_in_a_later_window_matches_tracking_the_clipped_video():
    """A track queried at frame 13 first enters the window [8,16) and starts fresh there."""
    model = make_model().eval()
    video = random_video(1, 16, 40, 56, seed=3)
    query = torch.tensor([[[13.0, 30.2, 17.7]]])
    with torch.no_grad():
        full = model(video, query)
        clipped = model(video[:, 8:], query - torch.tensor([8.0, 0, 0]))
    assert not full.valid[0, :13].any() and full.valid[0, 13:].all()
    torch.testing.assert_close(full.coords[-1][:, 13:], clipped.coords[-1][:, 5:], rtol=0, atol=1e-5)
    torch.testing.assert_close(full.vis_logits[-1][:, 13:], clipped.vis_logits[-1][:, 5:], rtol=0, atol=1e-5)


def test_gradient_reaches_every_trainable_parameter_and_not_the_frozen_encoder():
    model = make_model("model.encoder_3d.random_init=true").train()
    assert not model.encoder_3d.training  # train() keeps the frozen encoder in eval mode
    out = model(random_video(1, 10, 32, 48), random_queries(1, 5, 10, 32, 48))
    loss = sum(x.square().mean() for x in out.coords) + sum(
        (v + c + m).mean() for v, c, m in zip(out.vis_logits, out.conf_logits, out.moving_logits))
    loss.backward()
    for name, p in model.named_parameters():
        if name.startswith("encoder_3d."):
            assert not p.requires_grad and p.grad is None, name
        else:
            assert p.grad is not None and p.grad.abs().sum() > 0, name


def test_eval_outputs_are_deterministic():
    video, queries = random_video(1, 9, 36, 44), random_queries(1, 4, 9, 36, 44)
    runs = []
    for _ in range(2):
        model = make_model("model.encoder_3d.random_init=true", seed=5).eval()
        with torch.no_grad():
            runs.append([model(video, queries) for _ in range(2)])
    (a, b), (c, _) = runs
    for x, y, z in zip(a.coords + a.moving_logits, b.coords + b.moving_logits, c.coords + c.moving_logits):
        assert torch.equal(x, y) and torch.equal(x, z)


def write_official_checkpoint(path, depth=2, dim=32, heads=2, seed=0):
    """A DUSt3R-layout file: {'model': encoder + decoder-like keys, 'args': Namespace(model=...)}."""
    torch.manual_seed(seed)
    encoder = Dust3rEncoder(patch_size=16, embed_dim=dim, depth=depth, num_heads=heads)
    state = dict(encoder.state_dict())
    state["dec_blocks.0.norm1.weight"] = torch.ones(8)  # non-encoder keys are ignored
    state["downstream_head1.proj.weight"] = torch.zeros(4, 8)
    args = argparse.Namespace(model=f"AsymmetricCroCo3DStereo(pos_embed='RoPE100', enc_embed_dim={dim}, "
                                    f"enc_depth={depth}, enc_num_heads={heads}, head_type='linear')")
    torch.save({"model": state, "args": args, "epoch": 3}, path)
    return encoder.state_dict()


def test_dust3r_checkpoint_loads_into_the_3d_branch(tmp_path):
    path = tmp_path / "dust3r_tiny.pth"
    expected = write_official_checkpoint(path, depth=3, dim=48, heads=3)
    model = build_model(tiny_cfg(f"model.encoder_3d.checkpoint={path}", "model.encoder_3d.layers=[0,1]"))
    loaded = model.encoder_3d.state_dict()
    assert loaded.keys() == expected.keys()
    for k in expected:
        assert torch.equal(loaded[k], expected[k]), k
    enc_cfg = model.config["encoder_3d"]
    assert (enc_cfg["embed_dim"], enc_cfg["depth"], enc_cfg["num_heads"]) == (48, 3, 3)  # from the file
    assert all(not p.requires_grad for p in model.encoder_3d.parameters())
    assert model.vit_proj.in_features == 48 * 3  # two blocks + the final output
    with torch.no_grad():
        out = model.eval()(random_video(1, 4, 33, 47), random_queries(1, 3, 4, 33, 47))
    assert out.coords[-1].shape == (1, 4, 3, 2)


def test_encoder_configuration_errors(tmp_path):
    with pytest.raises(UserError, match="encoder_3d.checkpoint"):
        build_model(load_config("dynpt/model", "full").model)
    bad = tmp_path / "not_dust3r.pth"
    torch.save({"model": {"head.weight": torch.zeros(2)}, "args": argparse.Namespace(model="X()")}, bad)
    with pytest.raises(UserError, match="encoder weights"):
        build_model(tiny_cfg(f"model.encoder_3d.checkpoint={bad}"))
    good = tmp_path / "dust3r.pth"
    write_official_checkpoint(good)
    with pytest.raises(UserError, match="outside the encoder"):
        build_model(tiny_cfg(f"model.encoder_3d.checkpoint={good}", "model.encoder_3d.layers=[5]"))
    with pytest.raises(UserError, match="not both"):
        build_model(tiny_cfg(f"model.encoder_3d.checkpoint={good}", "model.encoder_3d.random_init=true"))
    assert make_model().encoder_3d is None  # no checkpoint configured: CNN only, no random ViT


def _sampled_correlation(fmap, query, xy, cell, radius, align_corners):
    """The correlation as the code before issue 29 computed it: `grid_sample` (bilinear, border
    padding) of the (2r+1)^2 whole-cell offsets around xy, then all products with the query
    neighbourhoods. fmap (B,T,C,h,w), query (B,N,Q,C), xy (B,T,N,2) -> (B,N,T,P*Q)."""
    from dynpt.correlation import _offsets, _to_grid

    B, T, C, h, w = fmap.shape
    points = xy[:, :, :, None, :] + cell * _offsets(radius, xy.device)  # (B,T,N,P,2)
    grid = _to_grid(points, cell, h, w, align_corners).flatten(0, 1)
    target = torch.nn.functional.grid_sample(fmap.flatten(0, 1), grid, mode="bilinear",
                                             padding_mode="border", align_corners=align_corners)
    corr = torch.einsum("btcnp,bnqc->bntpq", target.unflatten(0, (B, T)), query)
    return corr.flatten(3)


@pytest.mark.parametrize("align_corners", [False, True])
def test_correlation_equals_sampling_then_products(align_corners):
    """The whole-cell patch form gives grid_sample's numbers and gradients, past the borders too."""
    from dynpt.correlation import neighbourhood_correlation

    g = torch.Generator().manual_seed(3)
    B, T, C, h, w, N, r, cell = 2, 3, 5, 6, 7, 9, 2, 4
    fmap = torch.randn(B, T, C, h, w, generator=g, dtype=torch.float64, requires_grad=True)
    query = torch.randn(B, N, (2 * r + 1) ** 2, C, generator=g, dtype=torch.float64, requires_grad=True)
    xy = (torch.rand(B, T, N, 2, generator=g, dtype=torch.float64) * 1.6 - 0.3) * cell * torch.tensor(
        [w, h], dtype=torch.float64)  # a fifth of the points beyond a border
    xy[0, 0, 0] = torch.tensor([4 * (w - 1.0), 0.0])  # exactly on cell centres, the last and first
    ours = neighbourhood_correlation(fmap.permute(0, 1, 3, 4, 2), query, xy, cell, r, align_corners)
    ref = _sampled_correlation(fmap, query, xy, cell, r, align_corners)
    torch.testing.assert_close(ours, ref)
    weights = torch.randn(ref.shape, generator=g, dtype=torch.float64)
    grads = [torch.autograd.grad((x * weights).sum(), (fmap, query)) for x in (ours, ref)]
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b)


def test_correlation_samples_the_right_feature_cells():
    """Input pixel x sits at feature coordinate (x + 0.5) / stride - 0.5 on every pyramid level."""
    from dynpt.correlation import feature_pyramid, neighbourhood_correlation, sample_query_neighbourhoods

    torch.manual_seed(0)
    fmap = torch.randn(1, 2, 5, 8, 10)  # (B,T,C,h,w) at stride 4
    xy = torch.tensor([[[4 * 3 + 1.5, 4 * 2 + 1.5]]]).expand(1, 2, 1, 2)  # cell (x=3, y=2)
    one_hot = torch.eye(5)[None, None, :1]  # a query neighbourhood of one offset: channel 0

    def sampled(level, at, cell, radius):  # channel 0 of the samples around `at`: (T, P)
        return neighbourhood_correlation(level.permute(0, 1, 3, 4, 2), one_hot, at, cell, radius)[0, 0]

    out = sampled(fmap, xy, 4, 1)
    assert torch.allclose(out[:, 4], fmap[0, :, 0, 2, 3])  # centre
    assert torch.allclose(out[:, 5], fmap[0, :, 0, 2, 4])  # one cell right
    assert torch.allclose(out[:, 1], fmap[0, :, 0, 1, 3])  # one cell up
    coarse = feature_pyramid(fmap, 2)[1]  # stride 8: cell (1, 1) averages cells x 2..3, y 2..3
    out = sampled(coarse, torch.full((1, 2, 1, 2), 8 * 1 + 3.5), 8, 0)
    assert torch.allclose(out[:, 0], fmap[0, :, 0, 2:4, 2:4].mean((-1, -2)), atol=1e-6)
    q = sample_query_neighbourhoods(fmap, torch.tensor([[1]]), xy[:, 0], cell=4, radius=1)  # (B,N,9,C)
    assert torch.allclose(q[0, 0, 4], fmap[0, 1, :, 2, 3])  # exactly frame 1, no blending in time


def test_tiny_model_learns_to_follow_a_translating_texture():
    """A few optimiser steps on one clip: the position error must fall well below the start."""
    T, H, W, N = 8, 40, 56, 16
    g = torch.Generator().manual_seed(2)
    low = torch.rand(1, 3, H // 6, (W + 2 * T) // 6, generator=g)
    big = 255 * torch.nn.functional.interpolate(low, size=(H, W + 2 * T), mode="bicubic").clamp(0, 1)
    video = torch.stack([big[0, :, :, 2 * T - 2 * t: 2 * T - 2 * t + W] for t in range(T)])[None]  # 2 px/frame right
    q = torch.stack([torch.zeros(N), 4 + torch.rand(N, generator=g) * (W - 24),
                     4 + torch.rand(N, generator=g) * (H - 8)], -1)[None]
    gt = q[:, None, :, 1:] + torch.stack([2 * torch.arange(T).float(),
                                          torch.zeros(T)], -1)[None, :, None]  # (1,T,N,2)
    model = make_model(seed=0).train()
    opt = torch.optim.AdamW(model.parameters(), lr=2e-3)
    errors = []
    for _ in range(25):
        out = model(video, q)
        loss = sum((c - gt).abs().mean() for c in out.coords)
        opt.zero_grad()
        loss.backward()
        opt.step()
        errors.append(float((out.coords[-1] - gt).norm(dim=-1).mean().detach()))
    assert errors[0] > 3 and min(errors[-5:]) < 0.4 * errors[0], errors
