"""Each C4D objective on tiny hand-made cases with known values and minima."""

import math

import numpy as np
import pytest
import torch

from c4d_pipeline import objectives as obj
from c4d_pipeline.alignment import estimate_focal
from c4d_pipeline.procrustes import weighted_procrustes
from c4d_pipeline.scene_params import pixel_rays, quat_to_rotation



def rot_z(theta: float) -> torch.Tensor:
    c, s = math.cos(theta), math.sin(theta)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def test_global_alignment_zero_at_truth_and_hand_value_off_it():
    g = torch.Generator().manual_seed(0)
    world = torch.randn(2, 5, 3, generator=g, dtype=torch.float64)  # (T,P,3)
    rot, scale, trans = rot_z(0.3)[None], torch.tensor([2.0], dtype=torch.float64), torch.tensor([[1.0, -2.0, 0.5]], dtype=torch.float64)
    inv = lambda x: ((x - trans) @ rot[0]) / scale  # world -> pair frame
    pts_i, pts_j = inv(world[0])[None], inv(world[1])[None]
    w = torch.full((1, 5), 0.5, dtype=torch.float64)
    ei, ej = torch.tensor([0]), torch.tensor([1])
    assert obj.global_alignment_sum(world, ei, ej, pts_i, pts_j, w, w, scale, rot, trans) < 1e-12
    shifted = world.clone()
    shifted[1] += torch.tensor([0.0, 3.0, 4.0], dtype=torch.float64)  # 5 units off, 5 pixels
    value = obj.global_alignment_sum(shifted, ei, ej, pts_i, pts_j, w, w, scale, rot, trans)
    assert value.item() == pytest.approx(0.5 * 5 * 5.0)


def test_camera_motion_alignment_zero_for_ego_flow_and_l1_otherwise():
    h, w = 4, 5
    focal = torch.tensor([10.0, 10.0], dtype=torch.float64)
    principal = torch.tensor([2.0, 1.5], dtype=torch.float64)
    cam = (pixel_rays(h, w, focal, principal) * 3.0).reshape(2, -1, 3)  # depth 3
    poses = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    poses[1, 0, 3] = 0.3  # camera 1 moved 0.3 to the right: points move 10*0.3/3 = 1 px left
    k = torch.zeros(2, 3, 3, dtype=torch.float64)
    k[:, 0, 0] = k[:, 1, 1] = 10.0
    k[:, 0, 2], k[:, 1, 2], k[:, 2, 2] = 2.0, 1.5, 1.0
    v, u = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    pixels = torch.stack([u, v], -1).reshape(-1, 2).double()
    ei, ej = torch.tensor([0]), torch.tensor([1])
    flow = torch.zeros(1, h * w, 2, dtype=torch.float64)
    flow[..., 0] = -1.0
    static = torch.ones(1, h * w, dtype=torch.bool)
    assert obj.camera_motion_sum(cam, poses, k, ei, ej, flow, static, pixels, 50.0) < 1e-9
    flow[..., 1] += 0.5  # every static pixel off by 0.5 px in y
    static[0, :4] = False
    value = obj.camera_motion_sum(cam, poses, k, ei, ej, flow, static, pixels, 50.0)
    assert value.item() == pytest.approx(0.5 * (h * w - 4))
    # errors beyond max_px are ignored
    assert obj.camera_motion_sum(cam, poses, k, ei, ej, flow, static, pixels, 0.4).item() == pytest.approx(0.0)
    # in reference pixels: this 5-px-wide image seen as a 20-px one, errors (and max_px) 4x larger
    value = obj.camera_motion_sum(cam, poses, k, ei, ej, flow, static, pixels, 50.0, px_scale=4.0)
    assert value.item() == pytest.approx(4 * 0.5 * (h * w - 4))
    assert obj.camera_motion_sum(cam, poses, k, ei, ej, flow, static, pixels, 1.9, px_scale=4.0).item() == pytest.approx(0.0, abs=1e-9)


def test_camera_smoothness_hand_values():
    rots = torch.stack([rot_z(0.0), rot_z(0.2), rot_z(0.2)])
    trans = torch.tensor([[0.0, 0, 0], [3.0, 4.0, 0.0], [3.0, 4.0, 0.0]], dtype=torch.float64)
    expected = 2 * math.sqrt(1 - math.cos(0.2)) + 5.0  # ||Rz(a) - I||_F = 2 sqrt(1 - cos a)
    assert obj.camera_smoothness(rots, trans).item() == pytest.approx(expected)
    assert obj.camera_smoothness(rots[[1, 1, 1]], trans[[1, 1, 1]]).item() == pytest.approx(0.0)


def test_trajectory_smoothing_hand_computed():
    traj = torch.tensor([0.0, 0.0, 1.0, 0.0, 0.0], dtype=torch.float64).reshape(5, 1, 1)  # (T,N,C)
    out = obj.smooth_trajectories(traj, kernel=3, lam=1.0)
    e = math.exp(-1.0)
    weights = [1.0, 1.0, e, e, 1.0]  # W_t = exp(-|T_t - T_t-1|), W_0 = W_1
    x = [0.0, 0.0, 1.0, 0.0, 0.0]
    for t in range(5):
        idx = [s for s in (t - 1, t, t + 1) if 0 <= s < 5]
        num = sum(weights[s] * x[s] for s in idx)
        den = sum(weights[s] for s in idx)
        assert out[t, 0, 0].item() == pytest.approx(num / den)
    line = torch.linspace(0, 1, 7, dtype=torch.float64).reshape(7, 1, 1).repeat(1, 2, 3)
    np.testing.assert_allclose(obj.smooth_trajectories(line, 5, 1.0)[2:5], line[2:5], atol=1e-12)


def test_linear_blend_displacement_hand_computed():
    controls = torch.tensor([[0.0, 0, 0], [2.0, 0, 0], [10.0, 0, 0]], dtype=torch.float64)
    disp = torch.tensor([[1.0, 0, 0], [0.0, 1.0, 0], [0.0, 0, 5.0]], dtype=torch.float64)
    query = torch.tensor([[1.0, 1.0, 0.0], [2.0, 0.0, 0.0]], dtype=torch.float64)
    out = obj.linear_blend_displacement(query, controls, disp, k=2)
    # first query: distances^2 2 and 2 to the first two controls -> equal weights
    np.testing.assert_allclose(out[0], [1.5, 1.5, 0.0], atol=1e-9)
    # second query sits on control 1 -> its displacement
    np.testing.assert_allclose(out[1], [2.0, 1.0, 0.0], atol=1e-6)
    # k=3: weights 1/1, 1/9... for a query at x=1 on the axis: d^2 = 1, 1, 81
    q = torch.tensor([[1.0, 0, 0]], dtype=torch.float64)
    w = np.array([1.0, 1.0, 1 / 81])
    expected = q[0].numpy() + (w[:, None] * disp.numpy()).sum(0) / w.sum()
    np.testing.assert_allclose(obj.linear_blend_displacement(q, controls, disp, k=3)[0], expected, atol=1e-9)


def test_pts_windows_are_non_overlapping_and_extended():
    assert obj.pts_windows(45, 20, 5) == [(0, 20, 0, 25), (20, 40, 15, 45), (40, 45, 35, 45)]


def test_pts_targets_pull_a_jittered_static_plane_back():
    t, h, w = 9, 6, 8
    world = torch.zeros(t, h, w, 3, dtype=torch.float64)
    v, u = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    world[..., 0], world[..., 1], world[..., 2] = u.double(), v.double(), 5.0
    jitter = torch.tensor([0, 0.2, -0.2, 0.2, -0.2, 0.2, -0.2, 0.2, 0], dtype=torch.float64)
    noisy = world.clone()
    noisy[..., 2] += jitter[:, None, None]
    tracks = torch.tensor([[1.0, 1.0], [6.0, 1.0], [1.0, 4.0], [6.0, 4.0], [3.0, 2.0]], dtype=torch.float64)
    tracks = tracks[None].repeat(t, 1, 1)
    visible = torch.ones(t, 5, dtype=torch.bool)
    target, has = obj.pts_targets(noisy, tracks, visible, window=9, extend=0, kernel=5, lam=1.0, knn=4)
    assert has.all()
    before = (noisy - world)[2:7, ..., 2].abs().mean()
    after = (target - world)[2:7, ..., 2].abs().mean()
    assert after < 0.5 * before
    assert obj.point_smoothness(target, target, has).item() == 0.0


def test_weighted_procrustes_recovers_similarity_and_ignores_zero_weights():
    g = torch.Generator().manual_seed(1)
    src = torch.randn(1, 50, 3, generator=g, dtype=torch.float64)
    rot = quat_to_rotation(torch.tensor([0.9, 0.1, -0.3, 0.2], dtype=torch.float64))
    dst = 1.7 * src @ rot.T + torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    w = torch.ones(1, 50, dtype=torch.float64)
    dst[0, :5] += 100.0  # outliers with zero weight
    w[0, :5] = 0.0
    s, r, t = weighted_procrustes(src, dst, w)
    assert s.item() == pytest.approx(1.7)
    np.testing.assert_allclose(r[0], rot, atol=1e-9)
    np.testing.assert_allclose(t[0], [1.0, 2.0, 3.0], atol=1e-9)


def test_focal_from_pointmap():
    focal = torch.tensor([40.0], dtype=torch.float64)
    principal = torch.tensor([7.5, 5.5], dtype=torch.float64)
    pts = pixel_rays(12, 16, focal, principal) * torch.linspace(1, 3, 16, dtype=torch.float64)[:, None]
    est = estimate_focal(pts, torch.ones(1, 12, 16, dtype=torch.float64), principal)
    assert est.item() == pytest.approx(40.0, rel=1e-6)
