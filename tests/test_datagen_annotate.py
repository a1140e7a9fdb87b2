"""Label geometry on hand-made cases: flow of known motions, normals, occlusion, sampling."""

import numpy as np

from c4d_core import geometry
from datagen import annotate

H, W = 24, 32
K = geometry.intrinsics_from_lens(35.0, 32.0, H, W)


def fronto_parallel(depth: float, frames: int, step: np.ndarray):
    """A camera looking down -Z at the plane z = 0 from height `depth`, moving by `step`/frame."""
    cams = []
    for t in range(frames):
        eye = np.array([0.0, 0.0, depth]) + t * step
        pose = geometry.make_pose(np.diag([1.0, -1.0, -1.0]), eye)  # x right, y down, z down
        cams.append(pose)
    return np.stack(cams), np.full((frames, H, W), depth, np.float32)


def test_flow_of_a_sideways_camera_over_a_plane():
    step = np.array([0.1, 0.0, 0.0])
    cams, depth = fronto_parallel(5.0, 3, step)
    seg = np.zeros((3, H, W), np.int32)
    fwd, bwd = annotate.optical_flow(depth, seg, np.broadcast_to(K, (3, 3, 3)), cams,
                                     np.zeros((0, 3, 4, 4)))
    expected = -K[0, 0] * 0.1 / 5.0  # the scene slides left as the camera moves right
    np.testing.assert_allclose(fwd[:2, ..., 0], expected, atol=1e-4)
    np.testing.assert_allclose(fwd[:2, ..., 1], 0.0, atol=1e-4)
    np.testing.assert_allclose(bwd[1:, ..., 0], -expected, atol=1e-4)
    assert not fwd[2].any() and not bwd[0].any()


def test_flow_follows_an_object_pose_not_the_backdrop():
    cams, depth = fronto_parallel(5.0, 2, np.zeros(3))
    seg = np.zeros((2, H, W), np.int32)
    seg[:, 5:10, 5:10] = 1
    obj = np.broadcast_to(np.eye(4), (1, 2, 4, 4)).copy()
    obj[0, 1, :3, 3] = [0.0, 0.2, 0.0]  # the object moves +y in the world = image up here
    fwd, _ = annotate.optical_flow(depth, seg, np.broadcast_to(K, (2, 3, 3)), cams, obj)
    np.testing.assert_allclose(fwd[0, 7, 7], [0.0, -K[1, 1] * 0.2 / 5.0], atol=1e-4)
    np.testing.assert_allclose(fwd[0, 20, 20], [0.0, 0.0], atol=1e-5)


def test_surface_normals_face_the_camera_on_a_tilted_plane():
    cam = geometry.look_at(np.array([0.0, -6.0, 4.0]), np.zeros(3))
    pixels = geometry.pixel_grid(H, W)
    rays = geometry.unproject(pixels, np.ones((H, W)), K, cam) - cam[:3, 3]  # world rays, z = 1
    depth = -cam[2, 3] / rays[..., 2]  # hits z = 0 (rays have unit camera z, so this is z-depth)
    x, y = np.array([3, 16, 30]), np.array([20, 12, 2])
    normal, reliable = annotate.surface_normals(depth, K, cam, x, y)
    np.testing.assert_allclose(normal, np.tile([0.0, 0.0, 1.0], (3, 1)), atol=1e-6)
    assert reliable.all()


def test_occlusion_reasons():
    cams, depth = fronto_parallel(10.0, 1, np.zeros(3))
    seg = np.zeros((1, H, W), np.int32)
    seg[0, :, 16:] = 2
    pixels = np.array([[[4.0, 4.0]], [[4.0, 4.0]], [[20.0, 4.0]], [[20.0, 4.0]], [[-3.0, 4.0]],
                       [[4.0, 4.0]]])  # (6,1,2)
    z = np.array([[10.0], [12.0], [10.05], [10.0], [10.0], [-1.0]])
    obj = np.array([0, 0, 2, 1, 0, 0])
    occluded = annotate.occlusion(pixels, z, obj, depth, seg, tolerance=0.01)
    # visible; behind the surface; within the 1% tolerance; wrong segment; out of view;
    # behind the camera
    np.testing.assert_array_equal(occluded[:, 0], [False, True, False, True, True, True])


def test_allocation_gives_small_segments_equal_shares_capped_by_their_size():
    alloc = annotate.allocate_points(np.array([1000, 5, 100]), total=60, max_fraction=0.1)
    np.testing.assert_array_equal(alloc, [49, 1, 10])
    rng = np.random.default_rng(0)
    seg = np.zeros((8, H, W), np.int32)
    seg[:, :8, :8] = 1
    t, y, x = annotate.sample_queries(seg, rng, 40, frame_stride=4, pixel_stride=2,
                                      max_fraction=0.5)
    assert len(t) == 40 and set(np.unique(t)) <= {0, 1, 2, 3, 4, 5, 6, 7}
    assert 10 <= np.sum(seg[t, y, x] == 1) <= 20  # about half on the small segment
    assert len(set(zip(t, y, x))) == 40  # no duplicates while the grid is large enough


def test_box_frames_recover_an_affine_box_map():
    """A box scaled, rotated and moved: its 8 corners give back the map of box-local points."""
    rng = np.random.default_rng(0)
    rotation = geometry.quat_to_matrix(geometry.quat_normalize(rng.normal(size=4)))  # (3,3)
    size, centre = np.array([0.4, 1.5, 0.7]), np.array([2.0, -1.0, 0.5])
    corners = (annotate.BOX_CORNERS - 0.5) * size @ rotation.T + centre  # (8,3)
    frame = annotate.box_frames(corners[None])[0]  # (4,4)
    local = rng.uniform(-0.5, 0.5, (10, 3))
    np.testing.assert_allclose(geometry.transform_points(frame, local),
                               (local * size) @ rotation.T + centre, atol=1e-12)


def test_box_lift_of_exact_object_coordinates_equals_the_depth_lift():
    """On a generated scene with float object coordinates, lifting object queries through their
    boxes (TAP-Vid-Kubric's way) gives the tracks the depth lift gives: the corner order, the
    -0.5 offset and segment k = box k-1 agree with our scenes' conventions."""
    from c4d_core.config import load_config
    from datagen.generate import generate_scene

    cfg = load_config("datagen", "movi-e", overrides=[
        "resolution=[64,64]", "frames=6", "objects.num_static=[3,3]", "objects.num_tossed=[2,2]",
        "layers.object_coordinates=true"])
    scene = generate_scene(cfg, 1)
    lift = annotate.BoxLift(scene.object_coordinates, scene.instances["bbox_3d"].astype(np.float64))
    by_depth = annotate.tapvid_kubric_tracks(scene, 5)
    by_box = annotate.tapvid_kubric_tracks(scene, 5, box_lift=lift)
    assert (by_box.track_object > 0).sum() > 50  # object tracks were drawn
    np.testing.assert_array_equal(by_box.track_object, by_depth.track_object)
    np.testing.assert_allclose(by_box.tracks, by_depth.tracks, atol=1e-3)  # px
    np.testing.assert_allclose(by_box.tracks_world, by_depth.tracks_world, atol=1e-4)  # units
    assert (by_box.occluded == by_depth.occluded).mean() > 0.99  # a point at an edge may flip
