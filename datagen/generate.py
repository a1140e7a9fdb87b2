"""One fully labelled scene: sample a description -> simulate -> render -> annotate.

    cfg = c4d_core.config.load_config("datagen", "movi-e", overrides=["resolution=[128,128]"])
    assets = datagen.assets.load_asset_library(cfg)   # once per worker process
    scene = generate_scene(cfg, scene_index=7, assets=assets)

The scene's randomness comes only from (cfg.seed, scene_index), so scene i of seed S is the same
whichever process, worker or shard makes it.
"""

from __future__ import annotations

import time

import numpy as np

import datagen
from c4d_core import geometry
from c4d_core.config import to_dict
from datagen import annotate, render
from datagen.assets import AssetLibrary, load_asset_library
from datagen.jobs import config_digest
from datagen.sampling import SceneDescription, sample_scene
from datagen.scene import OPTIONAL_LAYERS, Scene
from datagen.simulate import SimulationResult, simulate


def camera_lens(camera) -> dict[str, float]:
    """Kubric's camera record beside K: focal_length and sensor_width (mm, horizontal fit) and
    the horizontal field_of_view 2 atan(sensor / 2 focal) (rad), so K[0,0] = focal / sensor * W."""
    return {"focal_length": float(camera.focal_mm), "sensor_width": float(camera.sensor_mm),
            "field_of_view": float(2 * np.arctan(camera.sensor_mm / (2 * camera.focal_mm)))}


def scene_rngs(seed: int, scene_index: int) -> dict[str, np.random.Generator]:
    """Independent generators per stage, so changing one stage's draws leaves the others alone."""
    children = np.random.SeedSequence([int(seed), int(scene_index)]).spawn(2)
    return {"scene": np.random.default_rng(children[0]),
            "tracks": np.random.default_rng(children[1])}


# Peak bytes of one scene while `generate_scene` makes it and `datagen.shards.encode_scene`
# encodes it, per unit it grows with: tracemalloc's peak over movi-e scenes of 8-400 frames, 8x8
# to 256x256 pixels, 16-8192 tracks and 4-7 objects, rounded up. Per pixel of a frame: rgb,
# depth, segmentation and flow both ways (31 B), the camera points while flow is made (12 B) and
# the encoded sample (52 B measured); with `layers.normal` or `layers.object_coordinates` (made
# together) their float32 (T,H,W,3) arrays and encoding too (50 B measured). Per track and frame:
# `annotate.point_tracks`' float64 (N,T,4,4) poses and rotations (331 B measured). Per object and
# physics step: the poses kept while stepping (488 B measured), and with `layers.events` every
# contact point of every step (4,060 B more measured, objects at rest). Per object and placement
# try: its candidate pose and the rotated hull's bounds (123 B measured).
BYTES_PER = {"pixel": 64, "surface_pixel": 56, "track_frame": 384, "object_step": 512,
             "contact_step": 4096, "placement_try": 128}


def scene_memory(cfg) -> dict[str, int]:
    """Bytes one scene of `cfg` takes at its peak (`BYTES_PER`), by what they hold: 'frames' (the
    image layers of T frames of H x W pixels), 'tracks' (N tracks over T frames), 'physics' (the
    most objects the config allows, K, at each of the (T+1) x step_rate / fps + 1 recorded steps)
    and 'placement' (K objects' candidate poses). Exact integers, however large the config."""
    num_frames = int(cfg.frames)
    height, width = (int(side) for side in cfg.resolution)
    objects = int(cfg.objects.num_static[1]) + int(cfg.objects.num_tossed[1])
    steps = (num_frames + 1) * round(cfg.physics.step_rate / cfg.fps) + 1
    pixel = BYTES_PER["pixel"] + (BYTES_PER["surface_pixel"] if cfg.layers.normal
                                  or cfg.layers.object_coordinates else 0)
    step = BYTES_PER["object_step"] + (BYTES_PER["contact_step"] if cfg.layers.events else 0)
    return {"frames": num_frames * height * width * pixel,
            "tracks": int(cfg.tracks.num_points) * num_frames * BYTES_PER["track_frame"],
            "physics": objects * steps * step,
            "placement": objects * int(cfg.objects.placement_tries) * BYTES_PER["placement_try"]}


# The parts of a scene's cost that `generate_scene(timings=...)` reports, in CPU seconds of the
# process (all threads, Mesa's rasterizer included): drawing the description, physics, building
# the renderer (meshes, procedural textures, upload), the lit pass (with its shadow maps and
# motion-blur sub-frames), the label pass (depth, segmentation, and the normals and object
# coordinates when those layers are on), optical flow, point tracks, and the instance and event
# records.
PARTS = ("sample", "physics", "render_setup", "render_rgb", "render_labels", "flow", "tracks",
         "instances", "events")


class _Clock:
    """CPU seconds per part, added into `timings` (a dict, or None to keep nothing)."""

    def __init__(self, timings: dict | None):
        self.timings = timings
        self.start = time.process_time()

    def lap(self, part: str) -> None:
        now = time.process_time()
        if self.timings is not None:
            self.timings[part] = self.timings.get(part, 0.0) + now - self.start
        self.start = now


def describe_and_simulate(cfg, scene_index: int, assets: AssetLibrary,
                          timings: dict | None = None) -> tuple[SceneDescription, SimulationResult]:
    """The first two stages: the scene's description and its physics (poses at every step)."""
    clock = _Clock(timings)
    description = sample_scene(cfg, scene_rngs(cfg.seed, scene_index)["scene"], assets)
    clock.lap("sample")
    sim = simulate(description, assets, cfg)
    clock.lap("physics")
    return description, sim


def generate_scene(cfg, scene_index: int, assets: AssetLibrary | None = None,
                   timings: dict | None = None) -> Scene:
    """Scene `scene_index` of preset `cfg` (a DictConfig from `load_config("datagen", ...)`).

    `assets`: a library from `load_asset_library(cfg)` to reuse across scenes (built if None).
    `timings`: if a dict is given, it receives CPU seconds per part (`PARTS`).
    """
    assets = load_asset_library(cfg) if assets is None else assets
    description, sim = describe_and_simulate(cfg, scene_index, assets, timings)

    clock = _Clock(timings)
    num_frames, height, width = description.num_frames, description.height, description.width
    frame_times = np.arange(num_frames, dtype=np.float64)
    object_to_world = sim.poses_at(frame_times)  # (K,T,4,4)
    cam_to_world = description.camera.pose_at(frame_times, num_frames)  # (T,4,4)
    K = geometry.intrinsics_from_lens(description.camera.focal_mm, description.camera.sensor_mm,
                                      height, width)
    intrinsics = np.broadcast_to(K, (num_frames, 3, 3))
    renderer = render.SceneRenderer(description, sim.placed, assets, cfg)
    depth = np.zeros((num_frames, height, width), np.float32)
    segmentation = np.zeros((num_frames, height, width), np.int32)
    rgb = np.zeros((num_frames, height, width, 3), np.uint8)
    layers = cfg.layers
    surface = bool(layers.normal or layers.object_coordinates)
    normal = np.zeros((num_frames, height, width, 3), np.float32) if surface else None
    coordinates = np.zeros((num_frames, height, width, 3), np.float32) if surface else None
    num_samples = render.num_blur_samples(description.motion_blur, cfg)
    clock.lap("render_setup")
    for t in range(num_frames):
        depth[t], segmentation[t], frame_normal, frame_coordinates = renderer.render_labels(
            object_to_world[:, t], cam_to_world[t], surface=surface)
        if surface:
            normal[t], coordinates[t] = frame_normal, frame_coordinates
        clock.lap("render_labels")
        if num_samples == 1:
            rgb[t] = renderer.render_rgb(object_to_world[:, t], cam_to_world[t])
        else:
            times = render.shutter_times(t, description.motion_blur, num_samples)
            rgb[t] = render.render_blurred(
                renderer, sim.poses_at,
                lambda ts: description.camera.pose_at(ts, num_frames), times)
        clock.lap("render_rgb")

    flow_fwd, flow_bwd = annotate.optical_flow(depth, segmentation, intrinsics, cam_to_world,
                                               object_to_world)
    clock.lap("flow")
    threshold = float(cfg.mobility_threshold)
    tracks = annotate.point_tracks(depth, segmentation, intrinsics, cam_to_world, object_to_world,
                                   scene_rngs(cfg.seed, scene_index)["tracks"], cfg, threshold)
    clock.lap("tracks")
    instances = events = None
    if layers.instances:
        boxes = np.stack([assets.get(description.objects[i].asset_id)
                          .bounds(description.objects[i].scale) for i in sim.placed]
                         ).reshape(-1, 2, 3)  # (K,2,3)
        frames = slice(1, num_frames + 1)  # velocities are kept at frame times -1..T
        instances = annotate.instance_labels(
            segmentation, intrinsics, cam_to_world, object_to_world, boxes,
            sim.velocities[:, frames], sim.angular_velocities[:, frames],
            np.array([description.objects[i].tossed for i in sim.placed], bool))
        clock.lap("instances")
    if layers.events:
        events = annotate.collision_events(sim.contacts, sim.steps_per_frame, K,
                                           lambda ts: description.camera.pose_at(ts, num_frames))
        clock.lap("events")

    visible_pixels = (instances["visible_pixels"].sum(axis=1) if instances is not None else
                      np.bincount(segmentation.ravel(), minlength=len(sim.placed) + 1)[1:])
    objects = []
    for k, index in enumerate(sim.placed):
        spec = description.objects[index]
        objects.append({
            "asset_id": spec.asset_id, "scale": spec.scale, "mass": spec.mass,
            "friction": spec.friction, "restitution": spec.restitution, "tossed": spec.tossed,
            "start_velocity": sim.start_velocities[k].tolist(),
            "visible_pixels": int(visible_pixels[k]),
        })
    meta = {
        "preset": str(cfg.preset), "seed": int(cfg.seed), "scene_index": int(scene_index),
        "config_digest": config_digest(to_dict(cfg)),
        "fps": int(description.fps), "resolution": [height, width],
        "num_frames": num_frames, "split": str(cfg.split),
        "motion_blur": description.motion_blur, "blur_samples": num_samples,
        "generator": "datagen", "generator_version": datagen.__version__,
        "mobility_threshold": threshold,
        "physics": {"step_rate": int(cfg.physics.step_rate),
                    "steps_per_frame": sim.steps_per_frame, "settle_steps": sim.settle_steps},
        "flow_fwd_valid": [t < num_frames - 1 for t in range(num_frames)],
        "flow_bwd_valid": [t > 0 for t in range(num_frames)],
        **description.meta,
        "placed_objects": len(sim.placed),
        "layers": {name: bool(layers[name]) for name in OPTIONAL_LAYERS},
    }
    meta["camera"] = {**meta["camera"], **camera_lens(description.camera)}
    return Scene(
        rgb=rgb, depth=depth, segmentation=segmentation, flow_fwd=flow_fwd, flow_bwd=flow_bwd,
        intrinsics=intrinsics.astype(np.float32), cam_to_world=cam_to_world.astype(np.float32),
        object_to_world=object_to_world.astype(np.float32), objects=objects,
        tracks=tracks.tracks, occluded=tracks.occluded, query_frame=tracks.query_frame,
        track_object=tracks.track_object, tracks_world=tracks.tracks_world,
        displacement=tracks.displacement, moving=tracks.moving,
        normal=normal if layers.normal else None,
        object_coordinates=coordinates if layers.object_coordinates else None,
        instances=instances, events=events, meta=meta,
    )
