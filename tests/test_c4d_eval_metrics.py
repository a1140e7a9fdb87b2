"""Reconstruction metrics against hand-computed answers."""

import numpy as np
import pytest
from scipy.optimize import minimize

from c4d_core.errors import UserError
from c4d_core.geometry import make_pose, quat_to_matrix
from c4d_pipeline.eval_metrics import align_trajectory, depth_metrics, fit_depth_alignment, mask_iou, pose_metrics

CUBE = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)  # (8,3)


def rot_z(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def random_rotation(rng):
    return quat_to_matrix(rng.normal(size=4))  # normalised inside: uniform on SO(3)


def random_trajectory(rng, num_frames=12):
    return np.stack([make_pose(random_rotation(rng), rng.normal(size=3)) for _ in range(num_frames)])


def test_identical_trajectories_score_zero():
    gt = random_trajectory(np.random.default_rng(0))
    metrics = pose_metrics(gt, gt)
    assert metrics["ate"] < 1e-9 and metrics["rpe_trans"] < 1e-9 and metrics["rpe_rot"] < 1e-5
    assert metrics["sim3_scale"] == pytest.approx(1.0)


def test_a_similarity_transformed_trajectory_scores_zero_after_alignment():
    rng = np.random.default_rng(1)
    gt = random_trajectory(rng)
    rot, shift, scale = random_rotation(rng), np.array([4.0, -2.0, 7.0]), 0.3
    pred = gt.copy()
    pred[:, :3, :3] = rot @ gt[:, :3, :3]
    pred[:, :3, 3] = scale * gt[:, :3, 3] @ rot.T + shift
    metrics = pose_metrics(pred, gt)
    assert metrics["ate"] < 1e-9 and metrics["rpe_trans"] < 1e-9 and metrics["rpe_rot"] < 1e-5
    assert metrics["sim3_scale"] == pytest.approx(1 / scale)
    aligned, _ = align_trajectory(pred, gt)
    np.testing.assert_allclose(aligned, gt, atol=1e-9)


def test_known_offsets_give_the_known_ate():
    # centres at the cube's corners, pushed by d along x with the corner's parity sign: the offsets
    # have zero mean and zero covariance with the centres, so the Umeyama fit is R = I, t = 0,
    # s = 3 / (3 + d^2), and ATE^2 = 3 (s - 1)^2 + s^2 d^2
    d = 0.3
    parity = CUBE.prod(-1)  # (8,) +-1
    gt = make_pose(np.eye(3), CUBE)
    pred = make_pose(np.eye(3), CUBE + d * parity[:, None] * [1.0, 0, 0])
    s = 3 / (3 + d**2)
    metrics = pose_metrics(pred, gt)
    assert metrics["sim3_scale"] == pytest.approx(s)
    assert metrics["ate"] == pytest.approx(np.sqrt(3 * (s - 1) ** 2 + s**2 * d**2))


def test_known_rotation_wobble_gives_the_known_rpe():
    # every other camera is turned by theta about z; the centres are exact, so no alignment
    theta = np.radians(4.0)
    gt = make_pose(np.eye(3), CUBE)
    pred = make_pose(np.stack([rot_z(theta * (t % 2)) for t in range(8)]), CUBE)
    metrics = pose_metrics(pred, gt)
    assert metrics["ate"] < 1e-9
    assert metrics["rpe_rot"] == pytest.approx(4.0)
    # frames turned at t: the step (c_t+1 - c_t) is seen rotated by -theta: error 2 sin(theta/2) |step_xy|
    steps = np.diff(CUBE, axis=0)  # (7,3)
    errors = [2 * np.sin(theta / 2) * np.linalg.norm(steps[t, :2]) if t % 2 else 0.0 for t in range(7)]
    assert metrics["rpe_trans"] == pytest.approx(np.sqrt(np.mean(np.square(errors))))


def test_pose_metrics_reject_bad_input():
    gt = make_pose(np.eye(3), CUBE)
    with pytest.raises(UserError, match="equal length"):
        pose_metrics(gt[:5], gt)
    with pytest.raises(UserError, match="at least 2"):
        pose_metrics(gt[:1], gt[:1])
    bad = gt.copy()
    bad[2, 0, 3] = np.nan
    with pytest.raises(UserError, match="NaN"):
        pose_metrics(bad, gt)


def test_depth_up_to_scale_and_shift_scores_perfectly():
    gt = np.random.default_rng(0).uniform(1, 10, (3, 8, 8))
    shifted = depth_metrics(2 * gt + 1, gt, "scale_shift")
    assert shifted["abs_rel"] < 1e-7 and shifted["rmse"] < 1e-7 and shifted["delta_1_25"] == 1.0
    assert (shifted["scale"], shifted["shift"]) == pytest.approx((0.5, -0.5))
    scaled = depth_metrics(0.25 * gt, gt, "scale")
    assert scaled["abs_rel"] < 1e-12 and scaled["scale"] == pytest.approx(4.0) and scaled["shift"] == 0.0
    assert depth_metrics(2 * gt + 1, gt, "scale")["abs_rel"] > 0.01  # a shift is not a scale


def test_scale_only_depth_metrics_by_hand():
    # sum |s p - g| = 3 |s - 1| + |2 s - 1| is smallest at s = 1: errors (0, 0, 0, 1)
    gt = np.ones((1, 2, 2))
    pred = np.array([[[1.0, 1.0], [1.0, 2.0]]])
    metrics = depth_metrics(pred, gt, "scale")
    assert metrics["scale"] == 1.0
    assert metrics["abs_rel"] == pytest.approx(0.25)
    assert metrics["rmse"] == pytest.approx(0.5)
    assert metrics["delta_1_25"] == pytest.approx(0.75)


def test_scale_and_shift_fit_reaches_the_l1_optimum():
    rng = np.random.default_rng(3)
    gt = rng.uniform(1, 5, 400)
    pred = 0.7 * gt - 0.4 + rng.normal(0, 0.2, 400)
    pred[:40] += rng.uniform(2, 6, 40)  # outliers
    scale, shift = fit_depth_alignment(pred, gt, "scale_shift")
    l1 = lambda st: np.abs(st[0] * pred + st[1] - gt).sum()  # noqa: E731
    best = minimize(l1, [1.0, 0.0], method="Nelder-Mead", options={"xatol": 1e-10, "fatol": 1e-10, "maxiter": 4000})
    assert l1((scale, shift)) <= best.fun * (1 + 1e-6)


def test_depth_validity_and_max_depth():
    gt = np.array([[[1.0, 2.0], [0.0, 50.0]]])
    pred = np.array([[[1.0, 2.0], [5.0, 1.0]]])
    assert depth_metrics(pred, gt, "scale")["valid_pixels"] == 3  # gt 0 is invalid
    capped = depth_metrics(pred, gt, "scale", max_depth=10.0)
    assert capped["valid_pixels"] == 2 and capped["abs_rel"] < 1e-12
    with pytest.raises(UserError, match="equal shapes"):
        depth_metrics(pred[:, :1], gt)


def test_mask_iou_by_hand():
    gt = np.zeros((2, 2, 3), bool)
    gt[0, 0, :3] = True  # 3 pixels in frame 0, frame 1 empty
    pred = np.zeros_like(gt)
    pred[0, 0, 2] = pred[0, 1, 2] = True  # 2 pixels, 1 shared
    result = mask_iou(pred, gt)
    assert result["iou"] == pytest.approx(1 / 4)
    assert result["iou_frame_mean"] == pytest.approx((1 / 4 + 1.0) / 2)  # empty frame agrees: 1
    assert mask_iou(gt, gt)["iou"] == 1.0
    assert mask_iou(~gt, gt)["iou"] == 0.0


def evo_pose_metrics(pred, gt):
    """ATE, RPE trans and RPE rot as evo computes them: Sim(3) alignment, RMSE, delta 1 frame."""
    from evo.core import metrics, trajectory

    stamps = np.arange(len(gt), dtype=float)
    ref = trajectory.PoseTrajectory3D(poses_se3=list(gt.astype(np.float64)), timestamps=stamps)
    est = trajectory.PoseTrajectory3D(poses_se3=list(pred.astype(np.float64)), timestamps=stamps)
    est.align(ref, correct_scale=True)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    out = {"ate": ape.get_statistic(metrics.StatisticsType.rmse)}
    for name, relation in (("rpe_trans", metrics.PoseRelation.translation_part),
                           ("rpe_rot", metrics.PoseRelation.rotation_angle_deg)):
        rpe = metrics.RPE(relation, delta=1, delta_unit=metrics.Unit.frames, all_pairs=False)
        rpe.process_data((ref, est))
        out[name] = rpe.get_statistic(metrics.StatisticsType.rmse)
    return out


def noisy_copy(rng, gt, trans_sigma, rot_sigma):
    """gt (T,4,4) with centres moved by N(0, trans_sigma) and rotations turned by ~rot_sigma rad."""
    pred = gt.copy()
    pred[:, :3, 3] += rng.normal(0, trans_sigma, (len(gt), 3))
    turns = np.stack([quat_to_matrix(np.r_[1.0, rng.normal(0, rot_sigma / 2, 3)]) for _ in gt])
    pred[:, :3, :3] = turns @ gt[:, :3, :3]
    return pred


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("rot_sigma", [1e-4, 1e-2, 0.3])
def test_pose_metrics_equal_evo_on_random_trajectories(dtype, rot_sigma):
    rng = np.random.default_rng(int(rot_sigma * 1e4))
    gt = random_trajectory(rng, 40)
    gt[:, :3, 3] = np.cumsum(gt[:, :3, 3] * 0.1, 0)  # a path, not a cloud
    pred = noisy_copy(rng, gt, 0.01, rot_sigma)
    pred[:, :3, 3] = 3.0 * pred[:, :3, 3] @ random_rotation(rng).T + [1.0, 2.0, 3.0]  # another Sim(3) frame
    ours, evo = pose_metrics(pred.astype(dtype), gt.astype(dtype)), evo_pose_metrics(pred.astype(dtype), gt.astype(dtype))
    for name in ("ate", "rpe_trans", "rpe_rot"):
        assert ours[name] == pytest.approx(evo[name], rel=1e-6), name


def test_float32_ground_truth_against_itself_scores_zero_rotation_error():
    # near the identity arccos((tr R - 1) / 2) of a float32 rotation has a ~0.01 degree floor
    gt = random_trajectory(np.random.default_rng(5), 30).astype(np.float32)
    assert pose_metrics(gt, gt)["rpe_rot"] < 1e-6
    assert evo_pose_metrics(gt, gt)["rpe_rot"] < 1e-6


def test_pose_metrics_equal_evo_on_an_optimiser_trajectory():
    from c4d_core.config import load_config
    from c4d_pipeline.optimize import optimise
    from c4d_pipeline.ground_truth import GroundTruthPointmaps
    from c4d_pipeline.scene_graph import strided_window_pairs
    from tests.synthetic_scenes import make_box_scene

    scene = make_box_scene(num_frames=8, height=24, width=32, num_tracks=0, seed=2)
    edges = strided_window_pairs(8, window=3, stride=2)
    pw = GroundTruthPointmaps(scene, static_bias=False).pointmaps(scene.rgb, edges)
    cfg = load_config("c4d", "tiny", overrides=["graph.window=3", "weights.cma=0", "weights.pts=0"])
    res = optimise(pw, 8, cfg)
    assert res.cam_to_world.dtype == np.float32
    ours, evo = pose_metrics(res.cam_to_world, scene.cam_to_world), evo_pose_metrics(res.cam_to_world, scene.cam_to_world)
    assert ours["rpe_rot"] > 1e-4  # a real error, above any rounding floor
    for name in ("ate", "rpe_trans", "rpe_rot"):
        assert ours[name] == pytest.approx(evo[name], rel=1e-6), name
