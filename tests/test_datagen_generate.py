"""End-to-end scene generation with real pybullet and real pyrender (EGL), on tiny scenes.

Each scene is generated once per module; the tests check that the labels agree with each other
and with the rendered depth and segmentation, as exact geometry says they must.
"""

import hashlib
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from c4d_core import geometry
from c4d_core.config import load_config
from datagen import render
from datagen.assets import load_asset_library
from datagen.generate import describe_and_simulate, generate_scene
from datagen.scene import Scene

TINY = ["resolution=[64,64]", "frames=8", "tracks.num_points=160"]
MOVIE_INDEX = 0  # a scene with tracks on a resting object and on a tossed object
MOVIF_INDEX = 2  # a scene whose shutter is open for more than a third of a frame


@pytest.fixture(scope="module")
def cfg():
    return load_config("datagen", "movi-e", overrides=TINY)


@pytest.fixture(scope="module")
def assets(cfg):
    return load_asset_library(cfg)


@pytest.fixture(scope="module")
def scene(cfg, assets) -> Scene:
    return generate_scene(cfg, MOVIE_INDEX, assets)


def bilinear(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Sample (H,W) `image` at (n,2) sub-pixel points (pixel centres at integers)."""
    h, w = image.shape
    x, y = np.clip(xy[:, 0], 0, w - 1), np.clip(xy[:, 1], 0, h - 1)
    x0, y0 = np.minimum(np.floor(x).astype(int), w - 2), np.minimum(np.floor(y).astype(int), h - 2)
    ax, ay = x - x0, y - y0
    return ((1 - ay) * ((1 - ax) * image[y0, x0] + ax * image[y0, x0 + 1])
            + ay * ((1 - ax) * image[y0 + 1, x0] + ax * image[y0 + 1, x0 + 1]))


def test_every_field_is_present_with_the_contract_shapes(scene):
    T, H, W, K, N = 8, 64, 64, len(scene.objects), scene.num_tracks
    assert N == 160 and K >= 11
    expected = {
        "rgb": ((T, H, W, 3), np.uint8), "depth": ((T, H, W), np.float32),
        "segmentation": ((T, H, W), np.int32), "flow_fwd": ((T, H, W, 2), np.float32),
        "flow_bwd": ((T, H, W, 2), np.float32), "intrinsics": ((T, 3, 3), np.float32),
        "cam_to_world": ((T, 4, 4), np.float32), "object_to_world": ((K, T, 4, 4), np.float32),
        "tracks": ((N, T, 2), np.float32), "occluded": ((N, T), np.bool_),
        "query_frame": ((N,), np.int32), "track_object": ((N,), np.int32),
        "tracks_world": ((N, T, 3), np.float32), "displacement": ((N, T), np.float32),
        "moving": ((N, T), np.bool_),
    }
    for name, (shape, dtype) in expected.items():
        value = getattr(scene, name)
        assert value.shape == shape and value.dtype == dtype, name
    assert scene.segmentation.max() <= K and scene.rgb.std() > 10
    for key in ("preset", "seed", "scene_index", "fps", "resolution", "motion_blur",
                "generator_version", "mobility_threshold", "camera", "sampled_objects"):
        assert key in scene.meta
    for obj in scene.objects:
        assert {"asset_id", "scale", "mass", "friction", "restitution", "tossed"} <= set(obj)
        assert 0.75 <= obj["scale"] <= 3.0
    assert not scene.flow_fwd[-1].any() and not scene.flow_bwd[0].any()


def test_backdrop_depth_lies_on_the_floor_or_the_dome(scene, cfg):
    radius = cfg.backdrop.dome_radius
    for t in (0, 7):
        points = geometry.unproject_depth_map(scene.depth[t], scene.intrinsics[t],
                                              scene.cam_to_world[t])[scene.segmentation[t] == 0]
        on_floor = np.abs(points[:, 2]) < 2e-3
        on_dome = np.abs(np.linalg.norm(points, axis=-1) - radius) < 0.05
        assert np.mean(on_floor | on_dome) > 0.995 and on_floor.mean() > 0.5


def test_backdrop_track_unprojects_to_the_same_world_point_in_every_frame(scene):
    background = np.flatnonzero(scene.track_object == 0)
    assert len(background) > 10
    checked = 0
    for n in background:
        world = scene.tracks_world[n]
        np.testing.assert_allclose(world, np.broadcast_to(world[0], world.shape), atol=1e-5)
        for t in np.flatnonzero(~scene.occluded[n]):
            xy = scene.tracks[n, t][None].astype(np.float64)
            x0, y0 = np.floor(xy[0]).astype(int)
            patch = scene.segmentation[t, max(y0, 0):y0 + 2, max(x0, 0):x0 + 2]
            if patch.size < 4 or patch.any():  # next to an object: bilinear depth would mix
                continue
            depth = bilinear(scene.depth[t], xy)
            point = geometry.unproject(xy, depth, scene.intrinsics[t], scene.cam_to_world[t])[0]
            assert np.linalg.norm(point - world[0]) < 0.01 * depth[0]
            checked += 1
    assert checked > 5 * 20


def test_visible_track_points_agree_with_depth_and_segmentation(scene):
    n = np.arange(scene.num_tracks)
    tq = scene.query_frame
    # At its query frame a track sits exactly on a pixel showing its segment at its depth.
    xq, yq = scene.tracks[n, tq].T
    np.testing.assert_array_equal(xq, np.round(xq))
    np.testing.assert_array_equal(yq, np.round(yq))
    xq, yq = xq.astype(int), yq.astype(int)
    assert not scene.occluded[n, tq].any()
    np.testing.assert_array_equal(scene.segmentation[tq, yq, xq], scene.track_object)
    _, z = geometry.project(scene.tracks_world[n, tq], scene.intrinsics[tq], scene.cam_to_world[tq])
    np.testing.assert_allclose(z, scene.depth[tq, yq, xq], rtol=1e-4)
    # In all frames: visible points are on their segment at the rendered depth.
    ni, ti = np.nonzero(~scene.occluded)
    xy = scene.tracks[ni, ti]
    xi, yi = np.clip(np.round(xy).astype(int), 0, 63).T
    _, z = geometry.project(scene.tracks_world[ni, ti], scene.intrinsics[ti],
                            scene.cam_to_world[ti])
    assert np.mean(scene.segmentation[ti, yi, xi] == scene.track_object[ni]) > 0.9
    assert np.median(np.abs(scene.depth[ti, yi, xi] - z) / z) < 0.01
    # Occluded points in view are behind something or off their segment.
    assert scene.occluded.any() and (~scene.occluded).mean() > 0.5


def test_forward_and_backward_flow_equal_track_motion(scene):
    n = np.arange(scene.num_tracks)
    tq = scene.query_frame
    xq, yq = scene.tracks[n, tq].astype(int).T
    fwd = tq < 7
    np.testing.assert_allclose(scene.flow_fwd[tq, yq, xq][fwd],
                               (scene.tracks[n, tq + 1] - scene.tracks[n, tq])[fwd], atol=1e-3)
    bwd = tq > 0
    np.testing.assert_allclose(scene.flow_bwd[tq, yq, xq][bwd],
                               (scene.tracks[n, tq - 1] - scene.tracks[n, tq])[bwd], atol=1e-3)
    # The camera moves, so the static backdrop has non-zero flow.
    assert np.abs(scene.flow_fwd[0][scene.segmentation[0] == 0]).mean() > 0.01


def test_mobility_labels_follow_world_motion(scene):
    threshold = scene.meta["mobility_threshold"]
    steps = np.linalg.norm(np.diff(scene.tracks_world, axis=1), axis=-1)
    np.testing.assert_allclose(scene.displacement[:, 1:], steps, atol=1e-5)
    np.testing.assert_allclose(scene.displacement[:, 0], steps[:, 0], atol=1e-5)
    np.testing.assert_array_equal(scene.moving, scene.displacement > threshold)
    assert not scene.moving[scene.track_object == 0].any()
    poses = scene.object_to_world
    # Resting objects: pose entries change by < 1e-3 per frame (solver jitter only).
    pose_change = np.abs(np.diff(poses, axis=1)).max(axis=(1, 2, 3))  # (K,)
    resting = np.flatnonzero(pose_change < 1e-3) + 1
    on_resting = np.isin(scene.track_object, resting)
    assert on_resting.sum() > 0 and not scene.moving[on_resting].any()
    tossed = [k + 1 for k, obj in enumerate(scene.objects) if obj["tossed"]]
    on_tossed = np.isin(scene.track_object, tossed)
    assert on_tossed.sum() > 0 and scene.moving[on_tossed, 0].all()  # in flight at frame 0


def assert_same_fields(a: Scene, b: Scene) -> None:
    """Every field of `a` and `b` equal: arrays (and the arrays of `instances`) bit for bit."""
    for name in Scene.field_names():
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, np.ndarray):
            np.testing.assert_array_equal(x, y, err_msg=name)
        elif isinstance(x, dict) and name == "instances":
            assert list(x) == list(y)
            for key in x:
                assert x[key].tobytes() == y[key].tobytes(), key
        else:
            assert x == y, name


def test_generation_is_deterministic_per_seed_and_index(cfg, assets, scene):
    again = generate_scene(cfg, MOVIE_INDEX, assets)
    assert_same_fields(scene, again)
    other = generate_scene(cfg, MOVIE_INDEX + 1, assets)
    assert other.meta["camera"] != scene.meta["camera"]
    assert not np.array_equal(other.rgb, scene.rgb)


def scene_digest(scene: Scene) -> str:
    digest = hashlib.sha1()
    for name in Scene.field_names():
        value = getattr(scene, name)
        for array in (value.values() if isinstance(value, dict) and name in ("instances", "events")
                      else [value]):
            if isinstance(array, np.ndarray):
                digest.update(array.tobytes())
    return digest.hexdigest()


def test_another_process_makes_the_identical_scene(scene):
    """Nothing may depend on process state (hash order, caches, which scenes came before)."""
    code = (
        "import sys; sys.path.insert(0, 'tests');"
        "from test_datagen_generate import *;"
        "cfg = load_config('datagen', 'movi-e', overrides=TINY);"
        "generate_scene(cfg, MOVIE_INDEX + 5);"  # a different scene first
        "print(scene_digest(generate_scene(cfg, MOVIE_INDEX)))"
    )
    root = Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip().splitlines()[-1] == scene_digest(scene)


def test_movi_f_blur_is_the_mean_of_sub_frame_renders(assets):
    cfg = load_config("datagen", "movi-f", overrides=TINY)
    scene = generate_scene(cfg, MOVIF_INDEX, assets)
    shutter = scene.meta["motion_blur"]
    assert shutter > 0.33 and scene.meta["blur_samples"] >= 2
    description, sim = describe_and_simulate(cfg, MOVIF_INDEX, assets)
    renderer = render.SceneRenderer(description, sim.placed, assets, cfg)
    t = 3
    times = render.shutter_times(t, shutter, scene.meta["blur_samples"])
    poses = sim.poses_at(times)  # (K,n,4,4)
    cameras = description.camera.pose_at(times, 8)  # (n,4,4)
    subs = np.stack([renderer.render_rgb(poses[:, i], cameras[i]) for i in range(len(times))])
    np.testing.assert_array_equal(scene.rgb[t], np.round(subs.astype(np.float64).mean(0)))
    at_frame = sim.poses_at(np.array([t]))[:, 0], description.camera.pose_at(np.array(t), 8)
    sharp = renderer.render_rgb(*at_frame)
    assert np.abs(sharp.astype(int) - scene.rgb[t]).max() > 20  # blur is visible
    # Labels stay sharp, at the frame time.
    depth, segmentation, _, _ = renderer.render_labels(*at_frame)
    np.testing.assert_array_equal(depth, scene.depth[t])
    np.testing.assert_array_equal(segmentation, scene.segmentation[t])


def _shadow_map(renderer) -> np.ndarray:
    """The first sun's shadow map as float32 (S,S), read back from its texture."""
    from OpenGL import GL as gl

    renderer.sun_nodes[0].light.shadow_texture._bind()
    return np.asarray(gl.glGetTexImage(gl.GL_TEXTURE_2D, 0, gl.GL_DEPTH_COMPONENT, gl.GL_FLOAT))


def test_shadow_map_from_the_kept_backdrop_depth_is_the_whole_scene_drawn(cfg, assets, scene):
    """The backdrop's shadow depth is drawn once per scene and copied into each frame's map:
    the map must hold exactly the bits of drawing every mesh, and the depth another scene's
    renderer kept must not leak into a later renderer's frames."""
    description, sim = describe_and_simulate(cfg, MOVIE_INDEX, assets)
    renderer = render.SceneRenderer(description, sim.placed, assets, cfg)
    poses = sim.poses_at(np.arange(8.0))  # (K,8,4,4)
    cameras = description.camera.pose_at(np.arange(8.0), 8)  # (8,4,4)
    first = renderer.render_rgb(poses[:, 0], cameras[0])
    kept = renderer.render_rgb(poses[:, 5], cameras[5])
    np.testing.assert_array_equal(kept, scene.rgb[5])
    kept_map = _shadow_map(renderer)
    pyrender = render._pyrender()
    flags = pyrender.RenderFlags.OFFSCREEN | pyrender.RenderFlags.SHADOWS_DIRECTIONAL
    offscreen = renderer.renderer._renderer
    sun = renderer.sun_nodes[0]
    offscreen._configure_shadow_mapping_viewport(sun.light, flags)
    V, P = renderer.shadow_cameras[0]
    renderer._opaque_state()
    renderer._pass(offscreen, renderer.draw_order, flags, pyrender.constants.ProgramFlags.NONE,
                   V, P)  # every mesh, the backdrop among them in pyrender's order
    np.testing.assert_array_equal(kept_map, _shadow_map(renderer))
    assert (kept_map < 1).mean() > 0.5  # the floor and the objects are in it
    other_description, other_sim = describe_and_simulate(cfg, MOVIE_INDEX + 1, assets)
    other = render.SceneRenderer(other_description, other_sim.placed, assets, cfg)
    other.render_rgb(other_sim.poses_at(np.zeros(1))[:, 0],
                     other_description.camera.pose_at(np.zeros(1), 8)[0])
    again = render.SceneRenderer(description, sim.placed, assets, cfg)
    np.testing.assert_array_equal(again.render_rgb(poses[:, 0], cameras[0]), first)


def test_panning_camera_moves_its_look_at_point(assets):
    cfg = load_config("datagen", "movi-e-panning", overrides=TINY)
    description, _ = describe_and_simulate(cfg, 0, assets)
    camera = description.camera
    assert np.linalg.norm(camera.lookat_end - camera.lookat_start) > 0.1
    assert np.linalg.norm(camera.end - camera.start) <= 8.0
    for point in (camera.start, camera.end):
        assert 8.0 <= np.linalg.norm(point) <= 12.0 and point[2] > 0.1
    poses = camera.pose_at(np.array([-1.0, 9.0]), 8)  # the path's ends: times -1 and T + 1
    for pose, target in zip(poses, (camera.lookat_start, camera.lookat_end)):
        _, z = geometry.project(target, np.eye(3), pose)
        ray = geometry.transform_points(geometry.invert_pose(pose), target)
        np.testing.assert_allclose(ray[:2] / z, 0.0, atol=1e-9)  # look-at point on the axis
