"""Pairwise pointmaps: the ground-truth source (geometry, per-pair scale, noise/confidence, static-world
bias) and the source factory."""

import numpy as np
import pytest

from c4d_core import geometry
from c4d_core.errors import UserError
from c4d_pipeline.ground_truth import GroundTruthPointmaps
from c4d_pipeline.pointmaps import PairwisePointmaps, PointmapSource, sanitize
from tests.synthetic_scenes import make_box_scene


@pytest.fixture(scope="module")
def dynamic_scene():
    return make_box_scene(num_frames=6, height=24, width=32, num_tracks=16, seed=3)


@pytest.fixture(scope="module")
def static_scene():
    return make_box_scene(num_frames=6, height=24, width=32, moving=False, num_tracks=16, seed=3)


def camera_points(scene, t):
    return geometry.unproject_depth_map(scene.depth[t], scene.intrinsics[t], np.eye(4))


def test_clean_pointmaps_are_both_views_in_view_i_frame_up_to_one_scale(dynamic_scene):
    sc = dynamic_scene
    src = GroundTruthPointmaps(sc, depth_noise=0, smooth_noise=0, scale_range=2.0, static_bias=False)
    assert isinstance(src, PointmapSource)
    pw = src.pointmaps(sc.rgb, np.array([[1, 4], [4, 1]]))
    rel = geometry.invert_pose(sc.cam_to_world[1].astype(np.float64)) @ sc.cam_to_world[4]
    expect_i, expect_j = camera_points(sc, 1), geometry.transform_points(rel, camera_points(sc, 4))
    scale = pw.pts_i[0, ..., 2].mean() / expect_i[..., 2].mean()
    assert scale != pytest.approx(1.0)  # a random per-pair scale was applied ...
    np.testing.assert_allclose(pw.pts_i[0], scale * expect_i, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(pw.pts_j[0], scale * expect_j, rtol=1e-4, atol=1e-4)  # ... to both
    np.testing.assert_allclose(pw.conf_i, 10.0)  # noise-free: maximal confidence


def test_noise_lowers_confidence_and_is_deterministic(dynamic_scene):
    sc = dynamic_scene
    edges = np.array([[0, 1], [1, 0]])
    a = GroundTruthPointmaps(sc, depth_noise=0.05, smooth_noise=0.05, static_bias=False, seed=4).pointmaps(sc.rgb, edges)
    b = GroundTruthPointmaps(sc, depth_noise=0.05, smooth_noise=0.05, static_bias=False, seed=4).pointmaps(sc.rgb, edges)
    np.testing.assert_array_equal(a.pts_i, b.pts_i)
    assert (a.conf_i >= 1).all() and a.conf_i.min() < 5.0
    # the noise is along rays: x/z and y/z are unchanged
    clean = GroundTruthPointmaps(sc, depth_noise=0, smooth_noise=0, static_bias=False, seed=4).pointmaps(sc.rgb, edges)
    np.testing.assert_allclose(a.pts_i[..., :2] / a.pts_i[..., 2:], clean.pts_i[..., :2] / clean.pts_i[..., 2:], atol=1e-4)
    ratio = a.pts_i[0, ..., 2] / clean.pts_i[0, ..., 2]  # per-pair scales differ: normalise
    rel = np.abs(ratio / np.median(ratio) - 1)
    assert 0.02 < rel.mean() < 0.15


def test_every_scene_gets_its_own_noise(dynamic_scene):
    # two scenes of one data set, same seed and pairs: different noise fields, confidences, scales
    other = make_box_scene(num_frames=6, height=24, width=32, num_tracks=16, seed=4)
    edges = np.array([[0, 1], [1, 0]])
    a, b = (GroundTruthPointmaps(sc, static_bias=False, seed=4).pointmaps(sc.rgb, edges) for sc in (dynamic_scene, other))
    assert np.abs(a.conf_i - b.conf_i).max() > 1.0
    reloaded = make_box_scene(num_frames=6, height=24, width=32, num_tracks=16, seed=3)  # same scene again
    again = GroundTruthPointmaps(reloaded, static_bias=False, seed=4).pointmaps(reloaded.rgb, edges)
    np.testing.assert_array_equal(a.conf_i, again.conf_i)


def test_static_world_bias_vanishes_in_a_static_scene(static_scene):
    sc = static_scene
    biased = GroundTruthPointmaps(sc, static_bias=True)
    clean = GroundTruthPointmaps(sc, static_bias=False)
    np.testing.assert_allclose(biased.relative_pose(0, 5), clean.relative_pose(0, 5), atol=1e-4)


def test_static_world_bias_is_the_weighted_fit_over_all_correspondences(dynamic_scene):
    sc = dynamic_scene
    biased = GroundTruthPointmaps(sc, static_bias=True, bias_fit="rigid").relative_pose(0, 5)
    truth = GroundTruthPointmaps(sc, static_bias=False).relative_pose(0, 5)
    assert np.abs(biased - truth).max() > 1e-3  # the moving box pulls the fit
    # the fit is optimal: the true pose has a larger residual over the correspondences
    y, x = GroundTruthPointmaps(sc, static_bias=True).correspondences(0, 5)  # cam 5, cam 0
    resid = lambda pose: np.sum((geometry.transform_points(pose, y) - x) ** 2)
    assert resid(biased) < resid(truth)


def test_bad_inputs(dynamic_scene):
    sc = dynamic_scene
    src = GroundTruthPointmaps(sc)
    with pytest.raises(UserError, match="shape"):
        src.pointmaps(sc.rgb[:4], np.array([[0, 1]]))
    with pytest.raises(UserError, match="bias_fit"):
        GroundTruthPointmaps(sc, bias_fit="affine")
    pts = np.array([[np.nan, 0, 1], [1, 2, 3]])
    fixed, conf = sanitize(pts, np.array([5.0, np.inf]))
    assert np.isfinite(fixed).all() and conf.tolist() == [1.0, 1.0]
    pw = PairwisePointmaps(np.array([[0, 9]]), *(np.zeros((1, 2, 2, 3), np.float32),) * 2,
                           *(np.ones((1, 2, 2), np.float32),) * 2)
    with pytest.raises(UserError, match="outside"):
        pw.validate(5, (2, 2))


def test_build_pointmaps_names_every_source_and_refuses_unknown_ones(dynamic_scene, tmp_path):
    """'gt' is the config's ground-truth source, 'dust3r:PATH' a network file; anything else is
    one `UserError` that lists the registered specs."""
    import torch

    from c4d_core.config import load_config
    from dynpt.dust3r.net import Dust3rConfig, Dust3rNet
    from c4d_pipeline.dust3r_pointmaps import Dust3rPointmaps
    from c4d_pipeline.pointmap_sources import POINTMAP_SOURCES, build_pointmaps
    from c4d_pipeline.pointmap_training import save_official

    sc = dynamic_scene
    cfg = load_config("c4d", "default", overrides=["gt_pointmaps.seed=5", "pointmaps.batch=3"])
    edges = np.array([[0, 2], [3, 1]])
    built = build_pointmaps("gt", cfg, scene=sc).pointmaps(sc.rgb, edges)
    direct = GroundTruthPointmaps.from_config(sc, cfg.gt_pointmaps).pointmaps(sc.rgb, edges)
    assert np.array_equal(built.pts_j, direct.pts_j) and np.array_equal(built.conf_i, direct.conf_i)

    torch.manual_seed(0)
    net = Dust3rNet(Dust3rConfig(enc_embed_dim=32, enc_depth=1, enc_num_heads=2, dec_embed_dim=32,
                                 dec_depth=1, dec_num_heads=2, dpt_layer_dims=(8, 8, 16, 16),
                                 dpt_feature_dim=16, dpt_last_dim=8))
    path = save_official(net, (32, 32), tmp_path / "net.pth")
    source = build_pointmaps(f"dust3r:{path}", cfg, device="cpu")
    assert isinstance(source, Dust3rPointmaps) and source.batch_size == 3
    assert isinstance(source, PointmapSource)

    with pytest.raises(UserError, match="unknown pointmap source 'monst3r:x'; choose one of 'gt', 'dust3r:PATH'"):
        build_pointmaps("monst3r:x", cfg)
    assert set(POINTMAP_SOURCES) == {"gt", "dust3r"}
    with pytest.raises(UserError, match="needs a generated scene"):
        build_pointmaps("gt", cfg)
    with pytest.raises(UserError, match="needs weights"):
        build_pointmaps("dust3r", cfg)
    with pytest.raises(UserError, match="does not exist"):
        build_pointmaps(f"dust3r:{tmp_path / 'missing.pth'}", cfg)
