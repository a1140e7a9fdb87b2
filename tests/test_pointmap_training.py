"""Pointmap-network training on generated scenes: exact targets, DUSt3R's loss, an official file
that DynPT and C4D load, resume."""

import json

import numpy as np
import pytest
import torch

from c4d.cli import main
from c4d_core.config import load_config
from c4d_core.errors import UserError
from c4d_pipeline.dust3r_pointmaps import Dust3rPointmaps
from c4d_pipeline.pointmap_training import (confidence_regression_loss, exact_pair, load_scenes,
                                            sample_batch, train_pointmap_net)
from c4d_core import geometry
from dynpt.dust3r.net import load_dust3r
from dynpt.model import build_model
from tests.dynpt_testdata import generated_shards

TINY = ["model.enc_embed_dim=16", "model.enc_depth=2", "model.dec_embed_dim=16", "model.dec_depth=1",
        "model.patch_size=8", "train.batch_size=4", "train.log_every=1", "train.ckpt_every=3",
        "train.lr=0.003"]


def _cfg(out_dir, *extra):
    return load_config("pointmaps", "tiny-cpu", overrides=[
        f"data.sources=[{generated_shards()}]", f"train.out_dir={out_dir}", *TINY, *extra])


def _log(out_dir):
    return [json.loads(line) for line in (out_dir / "log.jsonl").read_text().splitlines()]


def test_exact_pair_is_the_scene_geometry():
    """View 1's points have the frame's depth as z; view 2's, moved back by the true relative pose,
    have frame j's depth."""
    scene = load_scenes([str(generated_shards())], 1)[0]
    i, j = 2, 6
    pts1, pts2 = exact_pair(scene, i, j)
    np.testing.assert_allclose(pts1[..., 2], scene.depth[i], rtol=1e-5)
    i_from_j = geometry.invert_pose(scene.cam_to_world[i].astype(np.float64)) @ scene.cam_to_world[j]
    in_j = geometry.transform_points(geometry.invert_pose(i_from_j), pts2.astype(np.float64))
    np.testing.assert_allclose(in_j[..., 2], scene.depth[j], rtol=1e-4)
    assert not np.allclose(pts2[..., 2], scene.depth[j], rtol=1e-3)  # the camera moved


def test_flipped_pairs_are_mirrored_worlds():
    """A flipped sample is the mirror image: x negated and columns reversed, y and z unchanged."""
    scenes = load_scenes([str(generated_shards())], 1)
    plain = sample_batch(scenes, np.random.default_rng(3), 1, 2, hflip_prob=0.0)
    flipped = sample_batch(scenes, np.random.default_rng(3), 1, 2, hflip_prob=1.0)
    torch.testing.assert_close(flipped["img1"], plain["img1"].flip(-1))
    mirrored = plain["pts2"].flip(2) * torch.tensor([-1.0, 1.0, 1.0])
    torch.testing.assert_close(flipped["pts2"], mirrored)


def test_loss_is_scale_invariant_with_its_minimum_at_the_truth():
    g = torch.Generator().manual_seed(0)
    gt1, gt2 = torch.rand(2, 3, 5, 3, generator=g) + 0.5, torch.rand(2, 3, 5, 3, generator=g) + 0.5
    ones = torch.ones(2, 3, 5)
    loss, stats = confidence_regression_loss(2.5 * gt1, ones, 2.5 * gt2, ones, gt1, gt2, alpha=0.2)
    assert abs(float(loss)) < 1e-6 and stats["regression"] < 1e-6
    # conf = e everywhere at zero error: loss = -alpha * log(e) = -alpha
    loss, _ = confidence_regression_loss(gt1, ones * np.e, gt2, ones * np.e, gt1, gt2, alpha=0.2)
    assert float(loss) == pytest.approx(-0.2, abs=1e-6)
    # error in one pixel of view 2: regression > 0, and a confidence of 1 there beats a high one
    bad = gt2.clone()
    bad[0, 1, 2] += 0.5
    low, _ = confidence_regression_loss(gt1, ones, bad, ones, gt1, gt2, alpha=0.2)
    high_conf = ones.clone()
    high_conf[0, 1, 2] = 5.0
    high, _ = confidence_regression_loss(gt1, ones, bad, high_conf, gt1, gt2, alpha=0.2)
    assert 0 < float(low) < float(high)


def test_training_learns_and_writes_a_file_dynpt_and_c4d_load(tmp_path):
    out = tmp_path / "run"
    result = train_pointmap_net(_cfg(out, "train.steps=40", "train.ckpt_every=20"))
    log = _log(out)
    first, last = np.mean([r["regression"] for r in log[:5]]), np.mean([r["regression"] for r in log[-5:]])
    assert last < 0.7 * first, (first, last)

    net, report = load_dust3r(result["checkpoint"])  # the official loader reads it back
    assert report.config.patch_size == 8 and report.config.img_size == 64 and not report.ignored_keys
    state = torch.load(out / "last.pt", weights_only=False)["model"]
    for key, value in net.state_dict().items():
        torch.testing.assert_close(value, state[key])

    cfg = load_config("dynpt", "tiny-cpu", overrides=[
        f"model.encoder_3d.checkpoint={result['checkpoint']}", "model.encoder_3d.layers=[0]"])
    model = build_model(cfg.model)  # DynPT takes its frozen encoder
    torch.testing.assert_close(model.encoder_3d.patch_embed.proj.weight, net.patch_embed.proj.weight)
    frames = torch.rand(4, 3, 64, 64) * 2 - 1
    assert model.encode_frames(frames).shape[-2:] == (16, 16)

    scene = load_scenes([str(generated_shards())], 1)[0]
    source = Dust3rPointmaps.from_checkpoint(result["checkpoint"])  # and C4D its pointmaps
    pairs = source.pointmaps(scene.rgb, np.array([[0, 3], [3, 0]]))
    assert pairs.pts_i.shape == (2, 64, 64, 3) and np.isfinite(pairs.pts_j).all()


def test_resume_continues_the_same_run(tmp_path):
    train_pointmap_net(_cfg(tmp_path / "full", "train.steps=6"))
    split = _cfg(tmp_path / "split", "train.steps=6", "train.stop_after=3")
    assert train_pointmap_net(split)["checkpoint"] is None
    with pytest.raises(UserError, match="--resume"):
        train_pointmap_net(split)
    train_pointmap_net(_cfg(tmp_path / "split", "train.steps=6"), resume=True)
    full, parts = _log(tmp_path / "full"), _log(tmp_path / "split")
    assert [r["step"] for r in parts] == list(range(1, 7))
    np.testing.assert_allclose([r["loss"] for r in parts], [r["loss"] for r in full], rtol=1e-5)


def test_bad_input_is_one_clear_error(tmp_path):
    assert main(["pretrain-pointmaps", f"train.out_dir={tmp_path}/a"]) == 2  # no sources
    with pytest.raises(UserError, match="multiple of model.patch_size=12"):
        train_pointmap_net(_cfg(tmp_path / "b", "model.patch_size=12"))
