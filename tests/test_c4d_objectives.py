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


def channels_first(points):
    """(n,P,3) -> (n,3,P), the layout of the GA and CMA kernels."""
    return points.transpose(1, 2)


def test_global_alignment_zero_at_truth_and_hand_value_off_it():
    g = torch.Generator().manual_seed(0)
    world = torch.randn(2, 5, 3, generator=g, dtype=torch.float64)  # (T,P,3)
    rot, scale, trans = rot_z(0.3)[None], torch.tensor([2.0], dtype=torch.float64), torch.tensor([[1.0, -2.0, 0.5]], dtype=torch.float64)
    inv = lambda x: ((x - trans) @ rot[0]) / scale  # world -> pair frame
    pts = torch.stack([inv(world[0]), inv(world[1])])  # views i and j of edge (0, 1)
    w = torch.full((2, 5), 0.5, dtype=torch.float64)
    frames, mat = torch.tensor([0, 1]), (scale[:, None, None] * rot).expand(2, 3, 3)
    ga = lambda x: obj.global_alignment_sum(channels_first(x), frames, channels_first(pts), w, mat, trans.expand(2, 3))  # noqa: E731
    assert ga(world) < 1e-12
    shifted = world.clone()
    shifted[1] += torch.tensor([0.0, 3.0, 4.0], dtype=torch.float64)  # 5 units off, 5 pixels
    assert ga(shifted).item() == pytest.approx(0.5 * 5 * 5.0)


def reference_ga(world, frames, pts, w, mat, trans):
    """GA written the straightforward way (autograd), channels-last: world (T,P,3), pts (n,P,3)."""
    return (w * (world[frames] - (pts @ mat.transpose(1, 2) + trans[:, None])).norm(dim=-1)).sum()


def reference_pts(world, targets, has_target):
    """PTS written the straightforward way: mean L1 distance between world pointmaps (T,H,W,3) and
    their targets on the frames with targets."""
    return (world[has_target] - targets[has_target]).abs().mean()


def reference_cma(depth, frames, mat, offset, pixels, target, static, max_px, px_scale):
    """CMA written the straightforward way (autograd), channels-last: depth (T,P), pixels (P,3)
    homogeneous, target (e,P,2)."""
    proj = depth[frames][..., None] * (pixels @ mat.transpose(1, 2)) + offset[:, None]
    z = proj[..., 2]
    err = px_scale * (proj[..., :2] / z.clamp_min(1e-6)[..., None] - target).abs()
    keep = static[..., None] & (z > 1e-6)[..., None] & (err < max_px).detach()
    return (err * keep).sum()


@pytest.mark.parametrize("t, n, distinct", [(4, 7, False), (6, 4, True)])
def test_hand_written_gradients_equal_autograd_of_the_plain_formulas(t, n, distinct):
    """Frames gathered with repeats (their rows summed) and distinct in no order (rows routed)."""
    g = torch.Generator().manual_seed(1)
    p = 60
    world = torch.randn(t, p, 3, generator=g, dtype=torch.float64)
    mat, trans = torch.randn(n, 3, 3, generator=g, dtype=torch.float64), torch.randn(n, 3, generator=g, dtype=torch.float64)
    frames = torch.tensor([4, 0, 5, 2]) if distinct else torch.randint(0, t, (n,), generator=g)
    pts, w = torch.randn(n, p, 3, generator=g, dtype=torch.float64), torch.rand(n, p, generator=g, dtype=torch.float64)
    depth = torch.rand(t, p, generator=g, dtype=torch.float64) + 2.5
    depth[0, :5] = -1.0  # behind the camera: ignored
    pixels = torch.cat([torch.rand(p, 2, generator=g, dtype=torch.float64) * 0.6 - 0.3,
                        torch.ones(p, 1, dtype=torch.float64)], 1)  # (P,3) homogeneous
    proj = torch.eye(3, dtype=torch.float64) * 40 + torch.randn(n, 3, 3, generator=g, dtype=torch.float64)
    proj[:, 2] = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    offset = torch.randn(n, 3, generator=g, dtype=torch.float64)
    target = torch.randn(n, p, 2, generator=g, dtype=torch.float64) * 10
    static = torch.rand(n, p, generator=g) > 0.2
    cases = [
        (lambda a, b, c: obj.global_alignment_sum(channels_first(a), frames, channels_first(pts), w, b, c),
         lambda a, b, c: reference_ga(a, frames, pts, w, b, c), (world, mat, trans)),
        (lambda a, b, c: obj.camera_motion_sum(a, frames, b, c, pixels.T, channels_first(target), static, 30.0, 2.0),
         lambda a, b, c: reference_cma(a, frames, b, c, pixels, target, static, 30.0, 2.0), (depth, proj, offset)),
    ]
    for fused, plain, inputs in cases:
        values, grads = [], []
        for fn in (fused, plain):
            leaves = [x.clone().requires_grad_() for x in inputs]
            value = fn(*leaves)
            value.backward()
            values.append(value.item())
            grads.append([leaf.grad for leaf in leaves])
        assert values[0] == pytest.approx(values[1], rel=1e-12)
        for a, b in zip(*grads):
            torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


def test_camera_motion_alignment_zero_for_ego_flow_and_l1_otherwise():
    h, w = 4, 5
    depth = torch.full((2, h * w), 3.0, dtype=torch.float64)
    poses = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    poses[1, 0, 3] = 0.3  # camera 1 moved 0.3 to the right: points move 10*0.3/3 = 1 px left
    k = torch.zeros(2, 3, 3, dtype=torch.float64)
    k[:, 0, 0] = k[:, 1, 1] = 10.0
    k[:, 0, 2], k[:, 1, 2], k[:, 2, 2] = 2.0, 1.5, 1.0
    v, u = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    pixels = torch.stack([u, v]).reshape(1, 2, -1).double()  # (1,2,P)
    grid = torch.cat([pixels[0], torch.ones(1, h * w, dtype=torch.float64)])  # (3,P) [u, v, 1]
    ei, ej = torch.tensor([0]), torch.tensor([1])
    mat, offset = obj.ego_projection(poses[:, :3, :3], poses[:, :3, 3], k, ei, ej)
    flow = torch.zeros(1, 2, h * w, dtype=torch.float64)
    flow[:, 0] = -1.0
    static = torch.ones(1, h * w, dtype=torch.bool)
    cma = lambda max_px, px_scale=1.0: obj.camera_motion_sum(depth, ei, mat, offset, grid, pixels + flow, static, max_px, px_scale)  # noqa: E731
    assert cma(50.0) < 1e-9
    flow[:, 1] += 0.5  # every static pixel off by 0.5 px in y
    static[0, :4] = False
    assert cma(50.0).item() == pytest.approx(0.5 * (h * w - 4))
    # errors beyond max_px are ignored
    assert cma(0.4).item() == pytest.approx(0.0)
    # in reference pixels: this 5-px-wide image seen as a 20-px one, errors (and max_px) 4x larger
    assert cma(50.0, 4.0).item() == pytest.approx(4 * 0.5 * (h * w - 4))
    assert cma(1.9, 4.0).item() == pytest.approx(0.0, abs=1e-9)
    # the map itself, with frames of different intrinsics: H = K_j R_j^T R_i K_i^-1
    k[1, 0, 0], k[1, 1, 1], k[1, 0, 2] = 14.0, 14.0, 2.5
    rot = torch.stack([rot_z(0.2), rot_z(-0.1)])
    mat, offset = obj.ego_projection(rot, poses[:, :3, 3], k, torch.tensor([0, 1]), torch.tensor([1, 0]))
    torch.testing.assert_close(mat[0], k[1] @ rot[1].T @ rot[0] @ torch.linalg.inv(k[0]))
    torch.testing.assert_close(mat[1], k[0] @ rot[0].T @ rot[1] @ torch.linalg.inv(k[1]))
    torch.testing.assert_close(offset[1], k[0] @ rot[0].T @ (poses[1, :3, 3] - poses[0, :3, 3]))


def test_objectives_registry_names_every_term_once():
    names = [(t.name, t.stage) for t in obj.OBJECTIVES]
    assert names == [("ga", 1), ("cma", 1), ("cts", 1), ("pts", 2)]
    assert {t.name for t in obj.OBJECTIVES if t.per_edge} == {"ga", "cma"}


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
    assert reference_pts(target, target, has).item() == 0.0


def test_fixed_camera_pts_equals_the_plain_formula_on_the_world_points_and_its_gradient():
    """Stage 2's PTS (cameras fixed, gradient by hand) against the plain formula on the world
    pointmaps by autograd, in float64: frames 0 and 3 without targets, rotated cameras."""
    from c4d_pipeline.optimize import fixed_camera_pts
    from c4d_pipeline.scene_params import SceneParams

    g = torch.Generator().manual_seed(3)
    t, h, w = 5, 6, 7
    pose = torch.eye(4, dtype=torch.float64).repeat(t, 1, 1)
    pose[:, :3, :3] = quat_to_rotation(torch.randn(t, 4, generator=g, dtype=torch.float64))
    pose[:, :3, 3] = torch.randn(t, 3, generator=g, dtype=torch.float64)
    params = SceneParams((1 + torch.rand(t, h, w, generator=g)).double(), pose,
                         torch.tensor([9.0, 8, 10, 9, 11], dtype=torch.float64), torch.ones(1, dtype=torch.float64),
                         torch.eye(3, dtype=torch.float64)[None], torch.zeros(1, 3, dtype=torch.float64)).double()
    with torch.no_grad():
        targets = params.world_points() + 0.1 * torch.randn(t, h, w, 3, generator=g, dtype=torch.float64)
    has = torch.tensor([False, True, True, False, True])
    reference = reference_pts(params.world_points(), targets, has)
    (expected,) = torch.autograd.grad(reference, params.log_depth)
    fast = obj.fixed_camera_point_smoothness(params.log_depth, *fixed_camera_pts(params, targets, has))
    (grad,) = torch.autograd.grad(fast, params.log_depth)
    torch.testing.assert_close(fast, reference, rtol=1e-12, atol=0)
    torch.testing.assert_close(grad, expected, rtol=1e-10, atol=1e-15)
    assert grad[0].abs().max() == 0 and grad[1].abs().min() > 0
    empty = fixed_camera_pts(params, targets, torch.zeros(t, dtype=torch.bool))
    assert obj.fixed_camera_point_smoothness(params.log_depth, *empty).item() == 0.0


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
