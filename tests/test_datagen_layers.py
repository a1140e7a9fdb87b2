"""The optional Kubric layers (normals, object coordinates, instances, events) held against the
other labels and against physics, with real pybullet and real pyrender (EGL) on a small scene.

Each layer is checked by an independent route: normals against the gradient of the depth map,
object coordinates against depth, object poses and the meshes' bounds, 2-D boxes and visible
pixels against the segmentation, velocities against finite differences of the physics poses,
collision points against both bodies' collision surfaces.
"""

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from c4d.inspect.dataset_check import validate_scene
from c4d_core import geometry
from c4d_core.config import load_config
from datagen import annotate
from datagen.assets import load_asset_library
from datagen.generate import describe_and_simulate, generate_scene
from datagen.shards import decode_scene, encode_scene
from datagen.scene import EVENT_KEYS

SIZE = ["resolution=[96,96]", "frames=6", "tracks.num_points=64"]
ALL_LAYERS = ["layers.normal=true", "layers.object_coordinates=true", "layers.instances=true",
              "layers.events=true"]
INDEX = 0  # a scene with a tossed object that lands among the static ones


@pytest.fixture(scope="module")
def cfg():
    return load_config("datagen", "movi-e", overrides=SIZE + ALL_LAYERS)


@pytest.fixture(scope="module")
def assets(cfg):
    return load_asset_library(cfg)


@pytest.fixture(scope="module")
def scene(cfg, assets):
    return generate_scene(cfg, INDEX, assets)


@pytest.fixture(scope="module")
def sim(cfg, assets):
    return describe_and_simulate(cfg, INDEX, assets)


def world_points(scene, t: int) -> np.ndarray:
    """(H,W,3) world point seen at every pixel centre of frame t (from z-depth)."""
    cam = annotate.camera_points(scene.depth[t], scene.intrinsics[t].astype(np.float64))
    return geometry.transform_points(scene.cam_to_world[t].astype(np.float64), cam)


def same_segment_around(segmentation: np.ndarray) -> np.ndarray:
    """(H,W) True where the 3x3 neighbourhood holds one segment (the border is False)."""
    same = np.zeros(segmentation.shape, bool)
    centre = segmentation[1:-1, 1:-1]
    inner = np.ones(centre.shape, bool)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            inner &= segmentation[1 + dy:segmentation.shape[0] - 1 + dy,
                                  1 + dx:segmentation.shape[1] - 1 + dx] == centre
    same[1:-1, 1:-1] = inner
    return same


def test_layers_are_off_by_default_and_on_they_leave_the_other_labels_unchanged(scene, assets):
    plain = generate_scene(load_config("datagen", "movi-e", overrides=SIZE), INDEX, assets)
    assert plain.normal is None and plain.object_coordinates is None and plain.events is None
    assert plain.instances is not None  # cheap: on in the movi presets
    assert plain.meta["layers"] == {"normal": False, "object_coordinates": False,
                                    "instances": True, "events": False}
    for name in ("rgb", "depth", "segmentation", "flow_fwd", "tracks", "occluded", "object_to_world"):
        np.testing.assert_array_equal(getattr(plain, name), getattr(scene, name), err_msg=name)
    shapes = {"normal": (6, 96, 96, 3), "object_coordinates": (6, 96, 96, 3)}
    for name, shape in shapes.items():
        value = getattr(scene, name)
        assert value.shape == shape and value.dtype == np.float32
    assert validate_scene(scene, load_config("inspect", "default")) == []


def test_normals_are_unit_and_match_the_depth_gradient_on_flat_faces(scene):
    """Where a face is flat (the rendered normal constant around a pixel), the normal of the
    surface that the z-depth map describes (cross product of central differences) must be the
    rendered shading normal: both face the camera."""
    normal = scene.normal.astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(normal, axis=-1), 1.0, atol=1e-6)
    angles, on_objects = [], 0
    for t in range(scene.num_frames):
        seg, n = scene.segmentation[t], normal[t]
        flat = same_segment_around(seg)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                flat &= np.abs(np.roll(n, (dy, dx), axis=(0, 1)) - n).max(-1) < 1e-4
        y, x = np.nonzero(flat)
        from_depth, reliable = annotate.surface_normals(
            scene.depth[t].astype(np.float64), scene.intrinsics[t].astype(np.float64),
            scene.cam_to_world[t].astype(np.float64), x, y)
        cos = np.sum(from_depth[reliable] * n[y, x][reliable], -1)
        angles.append(np.degrees(np.arccos(np.clip(cos, -1, 1))))
        on_objects += int((seg[y, x][reliable] > 0).sum())
    angles = np.concatenate(angles)
    assert angles.size > 5000 and on_objects > 300  # floor and object faces both tested
    assert np.median(angles) < 0.1 and np.percentile(angles, 99) < 1.0, np.percentile(angles, 99)
    # The floor is flat at z = 0 with the normal +z (seen from above).
    points = world_points(scene, 0)
    floor = (scene.segmentation[0] == 0) & (np.abs(points[..., 2]) < 1e-3)
    assert floor.sum() > 1000
    np.testing.assert_allclose(normal[0][floor], np.broadcast_to([0, 0, 1], (floor.sum(), 3)),
                               atol=1e-6)


def test_object_coordinates_are_the_surface_point_in_the_object_box(scene, assets, sim):
    """Object coordinates = (object-frame point - box min) / box size, the point taken from the
    depth map and the object's pose, the box from the object's mesh at its scale."""
    description, simulation = sim
    boxes = np.stack([assets.get(description.objects[i].asset_id).bounds(description.objects[i].scale)
                      for i in simulation.placed])  # (K,2,3)
    coords = scene.object_coordinates
    assert coords.min() >= 0 and coords.max() <= 1
    assert not coords[scene.segmentation == 0].any()  # 0 on the backdrop
    errors = []
    for t in range(scene.num_frames):
        seg = scene.segmentation[t]
        inner = same_segment_around(seg) & (seg > 0)
        y, x = np.nonzero(inner)
        k = seg[y, x] - 1
        world = world_points(scene, t)[y, x]
        to_object = geometry.invert_pose(scene.object_to_world[k, t].astype(np.float64))
        local = geometry.transform_points(to_object, world)
        expected = (local - boxes[k, 0]) / (boxes[k, 1] - boxes[k, 0])
        errors.append(np.abs(coords[t][y, x] - expected).max(-1))
    errors = np.concatenate(errors)
    assert errors.size > 1000
    assert np.median(errors) < 2e-4 and np.percentile(errors, 99) < 2e-3, np.percentile(errors, 99)
    # The mesh's vertices span the box: each object's coordinates reach near 0 and 1 somewhere
    # along every axis it shows enough of; at least they spread over most of the box.
    spread = [np.ptp(coords[scene.segmentation == k + 1], axis=0).min()
              for k in range(len(boxes)) if (scene.segmentation == k + 1).sum() > 200]
    assert spread and np.median(spread) > 0.5


def test_3d_boxes_are_the_mesh_bounds_carried_by_the_pose(scene, assets, sim):
    description, simulation = sim
    corners = scene.instances["bbox_3d"].astype(np.float64)  # (K,T,8,3)
    for k, index in enumerate(simulation.placed):
        spec = description.objects[index]
        vertices = assets.get(spec.asset_id).vertices * spec.scale
        low, high = vertices.min(0), vertices.max(0)
        for t in (0, scene.num_frames - 1):
            local = geometry.transform_points(
                geometry.invert_pose(scene.object_to_world[k, t].astype(np.float64)), corners[k, t])
            np.testing.assert_allclose(local[0], low, atol=1e-4)  # corner order: x, y, z slowest..
            np.testing.assert_allclose(local[7], high, atol=1e-4)
            np.testing.assert_allclose(local[4], [high[0], low[1], low[2]], atol=1e-4)
            np.testing.assert_allclose(local[1], [low[0], low[1], high[2]], atol=1e-4)
            assert np.ptp(local, axis=0).max() == pytest.approx(spec.scale, rel=1e-4)
    position, _ = geometry.project(scene.object_to_world[:, :, :3, 3], scene.intrinsics[None],
                                   scene.cam_to_world[None])
    np.testing.assert_allclose(scene.instances["image_position"], position, atol=1e-3)
    np.testing.assert_array_equal(scene.instances["is_dynamic"],
                                  [obj["tossed"] for obj in scene.objects])


def test_2d_boxes_and_visible_pixels_match_the_segmentation(scene):
    boxes, visible = scene.instances["bbox_2d"], scene.instances["visible_pixels"]
    height, width = scene.image_size
    shown = 0
    for k in range(len(scene.objects)):
        for t in range(scene.num_frames):
            rows, cols = np.nonzero(scene.segmentation[t] == k + 1)
            assert visible[k, t] == rows.size
            if rows.size == 0:
                assert np.isnan(boxes[k, t]).all()
                continue
            shown += 1
            expected = [rows.min() / height, cols.min() / width, (rows.max() + 1) / height,
                        (cols.max() + 1) / width]
            np.testing.assert_allclose(boxes[k, t], expected, rtol=0, atol=1e-7)
    assert shown > 20
    assert visible.sum(axis=1).tolist() == [obj["visible_pixels"] for obj in scene.objects]


def test_velocities_are_pybullet_s_and_match_finite_differences_of_the_poses(scene, sim):
    """pybullet integrates semi-implicitly: the velocity after a step is exactly the position
    change of that step over its duration, and likewise for the rotation."""
    _, simulation = sim
    steps, dt = simulation.steps_per_frame, 1.0 / 240
    moving = 0
    for t in range(scene.num_frames):
        step = (t + 1) * steps  # frame t is at physics step (t + 1) * steps_per_frame
        linear = (simulation.positions[:, step] - simulation.positions[:, step - 1]) / dt
        np.testing.assert_allclose(scene.instances["velocity"][:, t], linear, atol=1e-4, rtol=1e-5)
        now = geometry.quat_to_matrix(simulation.quaternions[:, step])
        before = geometry.quat_to_matrix(simulation.quaternions[:, step - 1])
        q = geometry.matrix_to_quat(now @ np.swapaxes(before, -1, -2))  # world-frame rotation
        angle = 2 * np.arctan2(np.linalg.norm(q[:, 1:], axis=-1), q[:, 0])
        axis = q[:, 1:] / np.maximum(np.linalg.norm(q[:, 1:], axis=-1, keepdims=True), 1e-12)
        np.testing.assert_allclose(scene.instances["angular_velocity"][:, t],
                                   axis * (angle / dt)[:, None], atol=1e-3, rtol=1e-4)
        moving += int((np.linalg.norm(linear, axis=-1) > 1.0).sum())
    assert moving > 0  # the tossed object flies
    # At frame level the velocity also moves the pose: object positions one frame apart.
    tossed = np.flatnonzero(scene.instances["is_dynamic"])
    frame_step = np.diff(scene.object_to_world[tossed, :, :3, 3], axis=1) * 12  # units/s
    mean_velocity = (scene.instances["velocity"][tossed, 1:] + scene.instances["velocity"][tossed, :-1]) / 2
    assert np.abs(frame_step - mean_velocity).max() < 0.5 * np.abs(mean_velocity).max()


def test_collision_points_lie_on_both_bodies(scene, assets, sim):
    """Each event's point lies on the second body's collision hull (the floor: z = 0) and, up to
    the solver's penetration, on the first's, at the poses of its physics step."""
    description, simulation = sim
    events = scene.events
    instances, frames, positions = events["instances"], events["frame"], events["position"]
    assert len(frames) > 100 and -1 in instances[:, 1]
    assert (instances.min(axis=1) >= 0).any()  # object-object contacts too
    assert {key: (v.dtype, v.shape[1:]) for key, v in events.items()} == EVENT_KEYS
    hulls = [ConvexHull(assets.get(description.objects[i].asset_id).hull_vertices
                        * description.objects[i].scale).equations for i in simulation.placed]

    def distance(k: int, point: np.ndarray, step: int) -> float:
        """Signed distance (units) of a world point to object k's hull; the floor if k = -1."""
        if k < 0:
            return float(point[2])
        pose = geometry.make_pose(geometry.quat_to_matrix(simulation.quaternions[k, step]),
                                  simulation.positions[k, step])
        local = geometry.transform_points(geometry.invert_pose(pose), point)
        return float(np.max(hulls[k][:, :3] @ local + hulls[k][:, 3]))

    steps = simulation.steps_per_frame
    on_second, on_first = [], []
    for e in range(0, len(frames), max(1, len(frames) // 400)):
        step = int(round((float(frames[e]) + 1) * steps))
        point = positions[e].astype(np.float64)
        first, second = instances[e]
        on_second.append(distance(second, point, step))
        on_first.append(distance(first, point, step))
    assert (events["force"] > 0).all() and (-1 <= frames).all() and (frames <= scene.num_frames).all()
    np.testing.assert_allclose(np.linalg.norm(events["contact_normal"], axis=-1), 1.0, atol=1e-5)
    assert np.abs(on_second).max() < 2e-3
    assert np.abs(on_first).max() < 0.03  # penetration and the hull's margin
    # A point away from the bodies is far from both (the check can fail).
    assert abs(distance(0, positions[0] + [0, 0, 1.0], 0)) > 0.1
    # Image positions: the points seen by the camera at each event's time.
    camera = description.camera.pose_at(frames.astype(np.float64), scene.num_frames)  # (E,4,4)
    pixels, _ = geometry.project(positions.astype(np.float64), scene.intrinsics[0], camera)
    np.testing.assert_allclose(events["image_position"], pixels, atol=1e-3)


def test_camera_lens_record_agrees_with_k(scene):
    camera = scene.meta["camera"]
    focal_px = scene.intrinsics[0, 0, 0]
    width = scene.image_size[1]
    assert camera["focal_length"] == 35.0 and camera["sensor_width"] == 32.0
    assert focal_px == pytest.approx(camera["focal_length"] / camera["sensor_width"] * width)
    assert camera["field_of_view"] == pytest.approx(2 * np.arctan(width / 2 / focal_px), rel=1e-6)
    assert camera["field_of_view"] == pytest.approx(0.8575560, abs=1e-7)  # Kubric's 49.13 deg


def test_layers_survive_the_shard_round_trip_within_their_precision(scene):
    back = decode_scene(encode_scene(scene, "train-00000000"))
    half_step = 0.5 / 65535  # of [0, 1]; the normals' [-1, 1] has twice the step
    assert np.abs(back.normal - scene.normal).max() <= 2 * half_step * 1.02  # + float32 rounding
    assert np.abs(back.object_coordinates - scene.object_coordinates).max() <= half_step * 1.02
    assert not back.object_coordinates[scene.segmentation == 0].any()
    for key, value in scene.instances.items():
        assert back.instances[key].tobytes() == value.tobytes(), key
    for key, value in scene.events.items():
        assert back.events[key].tobytes() == value.tobytes(), key
    assert validate_scene(back, load_config("inspect", "default")) == []
