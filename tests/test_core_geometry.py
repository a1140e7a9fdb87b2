"""Camera geometry: look_at axes, intrinsics, project/unproject round trips, quaternions."""

import numpy as np
import pytest

from c4d_core import geometry


def test_look_at_axes_follow_opencv():
    eye, target = np.array([3.0, -4.0, 2.0]), np.array([0.5, 0.5, 0.0])
    pose = geometry.look_at(eye, target)
    rot = pose[:3, :3]
    np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-12)
    assert np.linalg.det(rot) == pytest.approx(1.0)
    forward = (target - eye) / np.linalg.norm(target - eye)
    np.testing.assert_allclose(rot[:, 2], forward, atol=1e-12)  # z looks at the target
    assert abs(rot[2, 0]) < 1e-12  # x (image right) is horizontal: no roll
    assert rot[2, 1] < 0  # y (image down) points down in the world
    np.testing.assert_allclose(pose[:3, 3], eye)
    # The target projects to the principal point.
    K = geometry.intrinsics_from_lens(35.0, 32.0, 48, 64)
    pixel, z = geometry.project(target, K, pose)
    np.testing.assert_allclose(pixel, [31.5, 23.5], atol=1e-9)
    assert z == pytest.approx(np.linalg.norm(target - eye))


def test_intrinsics_match_kubric_lens():
    K = geometry.intrinsics_from_lens(35.0, 32.0, 256, 256)
    assert K[0, 0] == pytest.approx(280.0) and K[1, 1] == pytest.approx(280.0)
    assert (K[0, 2], K[1, 2]) == (127.5, 127.5)


def test_project_unproject_round_trip():
    rng = np.random.default_rng(0)
    pose = geometry.look_at(np.array([6.0, 2.0, 5.0]), np.zeros(3))
    K = geometry.intrinsics_from_lens(35.0, 32.0, 120, 160)
    pixels = rng.uniform([0, 0], [159, 119], size=(50, 2))
    depth = rng.uniform(1.0, 20.0, size=50)
    world = geometry.unproject(pixels, depth, K, pose)
    back, z = geometry.project(world, K, pose)
    np.testing.assert_allclose(back, pixels, atol=1e-9)
    np.testing.assert_allclose(z, depth, atol=1e-9)
    # A depth map unprojects to the same points as pixel-by-pixel unprojection.
    dmap = rng.uniform(1, 5, size=(4, 6))
    points = geometry.unproject_depth_map(dmap, K, pose)
    np.testing.assert_allclose(points[2, 5], geometry.unproject(np.array([5.0, 2.0]), dmap[2, 5],
                                                                K, pose))


def test_pose_inverse_and_quaternions():
    rng = np.random.default_rng(1)
    quats = geometry.quat_normalize(rng.normal(size=(20, 4)))
    rot = geometry.quat_to_matrix(quats)
    np.testing.assert_allclose(np.einsum("nij,nkj->nik", rot, rot), np.broadcast_to(np.eye(3),
                               (20, 3, 3)), atol=1e-12)
    back = geometry.matrix_to_quat(rot)
    np.testing.assert_allclose(np.abs(np.sum(back * quats, -1)), 1.0, atol=1e-9)  # q == +-q
    pose = geometry.make_pose(rot, rng.normal(size=(20, 3)))
    np.testing.assert_allclose(pose @ geometry.invert_pose(pose), np.broadcast_to(np.eye(4),
                               (20, 4, 4)), atol=1e-12)
    np.testing.assert_allclose(geometry.quat_from_xyzw(geometry.quat_to_xyzw(quats)), quats)
    # Slerp: ends are exact and the middle of a 90 degree turn is a 45 degree turn.
    q0 = np.array([1.0, 0, 0, 0])
    q1 = np.array([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])
    np.testing.assert_allclose(geometry.quat_slerp(q0, q1, 0.0), q0, atol=1e-12)
    np.testing.assert_allclose(geometry.quat_slerp(q0, q1, 1.0), q1, atol=1e-12)
    half = geometry.quat_to_matrix(geometry.quat_slerp(q0, q1, 0.5))
    np.testing.assert_allclose(half[:2, 0], [np.cos(np.pi / 4), np.sin(np.pi / 4)], atol=1e-12)


def test_rescale_pixels_keeps_pixel_centres_for_numpy_and_torch():
    torch = pytest.importorskip("torch")
    # A 4-pixel row doubled: the outer edges (-0.5, 3.5) stay edges, pixel 0's centre lands
    # between the new pixels 0 and 1.
    row = np.array([-0.5, 0.0, 3.5], np.float32)
    np.testing.assert_array_equal(geometry.rescale_pixels(row, 2), [-0.5, 0.5, 7.5])
    np.testing.assert_array_equal(geometry.rescale_pixels(geometry.rescale_pixels(row, 2), 2, inverse=True),
                                  row)
    # (sx, sy) against (...,2); float32 stays float32; a tensor gives the very same bits.
    tracks = np.random.default_rng(0).uniform(-1, 60, (5, 7, 2)).astype(np.float32)
    scale = np.array([0.7, 1.3], np.float32)
    out = geometry.rescale_pixels(tracks, scale)
    assert out.dtype == np.float32
    np.testing.assert_array_equal(out[..., 1], geometry.rescale_pixels(tracks[..., 1], scale[1]))
    np.testing.assert_array_equal(geometry.rescale_pixels(torch.from_numpy(tracks[..., 0]), 0.7,
                                                          inverse=True).numpy(),
                                  geometry.rescale_pixels(tracks[..., 0], np.float32(0.7), inverse=True))


def test_swap_track_axes_and_the_scene_accessor_give_time_major_views():
    from datagen.scene import Scene

    rng = np.random.default_rng(1)
    tracks = rng.normal(size=(5, 7, 2)).astype(np.float32)  # (N,T,2)
    occluded, moving = rng.random((5, 7)) < 0.3, rng.random((5, 7)) < 0.5  # (N,T)
    swapped = geometry.swap_track_axes(tracks)
    assert swapped.shape == (7, 5, 2) and np.shares_memory(swapped, tracks)
    np.testing.assert_array_equal(swapped[3, 2], tracks[2, 3])
    np.testing.assert_array_equal(geometry.swap_track_axes(swapped), tracks)
    fields = dict.fromkeys(Scene.field_names())
    fields.update(rgb=np.zeros((7, 4, 4, 3), np.uint8), tracks=tracks, occluded=occluded, moving=moving,
                  meta={})
    scene = Scene(**fields)
    clip = scene.tracks_time_major(slice(1, 7, 2))  # frames 1, 3, 5
    np.testing.assert_array_equal(clip["tracks"], tracks[:, 1::2].transpose(1, 0, 2))
    np.testing.assert_array_equal(clip["occluded"], occluded[:, 1::2].T)
    np.testing.assert_array_equal(clip["moving"], moving[:, 1::2].T)
    assert all(np.shares_memory(clip[k], a) for k, a in (("tracks", tracks), ("occluded", occluded)))
    scene.moving = None
    assert scene.tracks_time_major()["moving"] is None
