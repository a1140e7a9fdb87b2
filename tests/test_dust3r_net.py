"""DUSt3R pointmap network: official checkpoint layout round trips, output parametrisation."""

import argparse
import math

import numpy as np
import pytest
import torch

from c4d_core.errors import UserError
from c4d_pipeline.dust3r_pointmaps import Dust3rPointmaps, to_network_input
from c4d_pipeline.pointmaps import PointmapSource
from dynpt.dust3r.net import Dust3rConfig, Dust3rNet, load_dust3r, postprocess

TINY = dict(enc_embed_dim=32, enc_depth=2, enc_num_heads=2, dec_embed_dim=24, dec_depth=4, dec_num_heads=2)
TINY_DPT = dict(dpt_layer_dims=(4, 8, 8, 16), dpt_feature_dim=8, dpt_last_dim=8)


def official_args(cfg: Dust3rConfig, name="AsymmetricCroCo3DStereo", extra="") -> str:
    return (f"{name}(pos_embed='RoPE100', patch_embed_cls='ManyAR_PatchEmbed', img_size=(512, 512), "
            f"head_type='{cfg.head_type}', output_mode='pts3d', depth_mode=('exp', -inf, inf), "
            f"conf_mode=('exp', 1, inf), enc_embed_dim={cfg.enc_embed_dim}, enc_depth={cfg.enc_depth}, "
            f"enc_num_heads={cfg.enc_num_heads}, dec_embed_dim={cfg.dec_embed_dim}, "
            f"dec_depth={cfg.dec_depth}, dec_num_heads={cfg.dec_num_heads}{extra})")


def tiny_net(head_type="dpt", seed=0, **kw):
    torch.manual_seed(seed)
    dpt = head_type == "dpt"
    cfg = Dust3rConfig(head_type=head_type, patch_size=16 if dpt else 4, **{**TINY, **(TINY_DPT if dpt else {}), **kw})
    net = Dust3rNet(cfg).eval()
    with torch.no_grad():  # random, not default, head biases so outputs vary
        for p in net.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return net


def images(seed, batch, h, w):
    g = torch.Generator().manual_seed(seed)
    return [torch.rand(batch, 3, h, w, generator=g) * 2 - 1 for _ in range(2)]


def test_official_vit_large_dpt_key_layout():
    keys = set(Dust3rNet(Dust3rConfig(enc_depth=1, dec_depth=12)).state_dict())
    for key in ("patch_embed.proj.weight", "enc_blocks.0.attn.qkv.weight", "enc_norm.bias",
                "decoder_embed.weight", "dec_blocks.11.cross_attn.projq.weight",
                "dec_blocks2.0.norm_y.weight", "dec_norm.weight",
                "downstream_head1.dpt.act_postprocess.0.1.weight",
                "downstream_head2.dpt.act_postprocess.3.1.weight",
                "downstream_head1.dpt.scratch.layer1_rn.weight", "downstream_head1.dpt.scratch.layer_rn.3.weight",
                "downstream_head1.dpt.scratch.refinenet4.resConfUnit1.conv2.bias",
                "downstream_head1.dpt.head.4.weight"):
        assert key in keys, key
    assert not any(k.startswith(("encoder.", "mask_token")) for k in keys)
    shapes = Dust3rNet(Dust3rConfig(enc_depth=1, dec_depth=12)).state_dict()
    assert shapes["decoder_embed.weight"].shape == (768, 1024)
    assert shapes["downstream_head1.dpt.act_postprocess.0.0.weight"].shape == (96, 1024, 1, 1)
    assert shapes["downstream_head1.dpt.act_postprocess.1.0.weight"].shape == (192, 768, 1, 1)
    assert shapes["downstream_head1.dpt.head.2.weight"].shape == (128, 128, 3, 3)
    linear = Dust3rNet(Dust3rConfig(enc_depth=1, dec_depth=1, head_type="linear")).state_dict()
    assert linear["downstream_head1.proj.weight"].shape == (4 * 16 * 16, 768)


def test_postprocess_matches_hand_computed_values():
    raw = torch.tensor([3.0, 0.0, 4.0, 0.0]).view(1, 4, 1, 1)
    pts, conf = postprocess(raw, ("exp", -math.inf, math.inf), ("exp", 1, math.inf))
    torch.testing.assert_close(pts[0, 0, 0], torch.tensor([0.6, 0.0, 0.8]) * math.expm1(5.0))
    assert conf.item() == pytest.approx(2.0)


@pytest.mark.parametrize("head_type", ["dpt", "linear"])
def test_outputs_shapes_ranges_and_batch_independence(head_type):
    net = tiny_net(head_type)
    img1, img2 = images(0, 2, 32, 48)
    with torch.no_grad():
        pts1, conf1, pts2, conf2 = net(img1, img2)
        single = net(img1[1:], img2[1:])
    assert pts1.shape == pts2.shape == (2, 32, 48, 3) and conf1.shape == conf2.shape == (2, 32, 48)
    assert torch.isfinite(pts1).all() and torch.isfinite(pts2).all()
    assert (conf1 >= 1).all() and (conf2 >= 1).all()
    torch.testing.assert_close(single[0][0], pts1[1], atol=1e-4, rtol=1e-4)
    # Cross-attention: view 1's pointmap depends on the other image.
    with torch.no_grad():
        other = net(img1, images(5, 2, 32, 48)[1])[0]
    assert not torch.allclose(other, pts1)


@pytest.mark.parametrize("head_type", ["dpt", "linear"])
def test_official_checkpoint_round_trip(tmp_path, head_type):
    net = tiny_net(head_type, seed=1)
    path = tmp_path / f"{head_type}.pth"
    torch.save({"model": net.state_dict(), "args": argparse.Namespace(model=official_args(net.cfg)),
                "epoch": 10}, path)
    loaded, report = load_dust3r(path)
    assert report.constructor == "AsymmetricCroCo3DStereo" and report.ignored_keys == []
    assert loaded.cfg == net.cfg
    img1, img2 = images(2, 1, 32, 32)
    with torch.no_grad():
        for a, b in zip(net(img1, img2), loaded(img1, img2)):
            torch.testing.assert_close(a, b, atol=0, rtol=0)


def test_mast3r_extra_heads_are_ignored_and_reported(tmp_path):
    net = tiny_net("dpt", seed=2)
    state = net.state_dict()
    extra = {"downstream_head1.head_local_features.fc1.weight": torch.zeros(8, 56),
             "downstream_head2.head_local_features.fc2.bias": torch.zeros(8)}
    path = tmp_path / "mast3r.pth"
    args = official_args(net.cfg, "AsymmetricMASt3R", ", desc_conf_mode=('exp', 0, inf), two_confs=True")
    torch.save({"model": {**state, **extra}, "args": argparse.Namespace(model=args.replace(
        "head_type='dpt'", "head_type='catmlp+dpt'"))}, path)
    loaded, report = load_dust3r(path)
    assert report.constructor == "AsymmetricMASt3R"
    assert report.ignored_keys == sorted(extra)
    img1, img2 = images(3, 1, 32, 32)
    with torch.no_grad():
        torch.testing.assert_close(net(img1, img2)[2], loaded(img1, img2)[2], atol=0, rtol=0)


def test_missing_second_decoder_is_copied_from_the_first(tmp_path):
    net = tiny_net("linear", seed=4)
    state = {k: v for k, v in net.state_dict().items() if not k.startswith("dec_blocks2.")}
    path = tmp_path / "croco_style.pth"
    torch.save({"model": state, "args": official_args(net.cfg)}, path)
    loaded, report = load_dust3r(path)
    assert report.copied_dec_blocks2
    torch.testing.assert_close(loaded.dec_blocks2[1].mlp.fc1.weight, net.dec_blocks[1].mlp.fc1.weight)


def test_bad_checkpoints_give_user_errors(tmp_path):
    net = tiny_net("linear")
    encoder_only = tmp_path / "encoder.pth"
    torch.save({"model": {k: v for k, v in net.state_dict().items() if k.startswith(("patch_", "enc_"))},
                "args": official_args(net.cfg)}, encoder_only)
    with pytest.raises(UserError, match="no DUSt3R decoder"):
        load_dust3r(encoder_only)
    incomplete = tmp_path / "incomplete.pth"
    torch.save({"model": {k: v for k, v in net.state_dict().items() if "dec_norm" not in k},
                "args": official_args(net.cfg)}, incomplete)
    with pytest.raises(UserError, match="lacks 2 weights"):
        load_dust3r(incomplete)
    with pytest.raises(UserError, match="does not exist"):
        load_dust3r(tmp_path / "nope.pth")


def test_pointmap_source_runs_the_requested_pairs_in_batches():
    net = tiny_net("dpt", seed=6)
    frames = np.random.default_rng(0).integers(0, 256, (3, 32, 48, 3), dtype=np.uint8)
    edges = np.array([[0, 1], [2, 0], [1, 2]])
    source = Dust3rPointmaps(net, device="cpu", batch_size=2)
    assert isinstance(source, PointmapSource)
    pw = source.pointmaps(frames, edges)
    assert pw.pts_i.shape == (3, 32, 48, 3) and pw.conf_j.shape == (3, 32, 48) and (pw.conf_i >= 1).all()
    images = to_network_input(frames)
    assert images.min() >= -1 and images.max() <= 1
    with torch.no_grad():
        pts1, conf1, pts2, conf2 = net(images[2:3], images[0:1])  # edge (2, 0)
    np.testing.assert_allclose(pw.pts_i[1], pts1[0].numpy(), atol=1e-5)
    np.testing.assert_allclose(pw.pts_j[1], pts2[0].numpy(), atol=1e-5)
    np.testing.assert_allclose(pw.conf_j[1], conf2[0].numpy(), atol=1e-5)
    with pytest.raises(UserError, match="multiples of 16"):
        source.pointmaps(frames[:, :30], edges)
    with pytest.raises(UserError, match="outside"):
        source.pointmaps(frames, np.array([[0, 3]]))
