"""Analytic test scenes: a textured floor, a far dome and rigid boxes, ray-cast exactly in numpy.

`make_box_scene` returns a full `datagen.Scene` (depth, segmentation, flow, cameras, object poses,
tracks with occlusion and mobility labels) in well under a second at small sizes, so the
reconstruction can be tested and benchmarked where the truth is known, independent of the renderer.
Imported as `tests.synthetic_scenes` by the tests and the benchmarks (which put the repository root
on sys.path); no module of the project uses it.
"""

from __future__ import annotations

import numpy as np

from c4d_core import geometry
from datagen.scene import Scene

DOME_RADIUS = 40.0


def _box_hits(origin, dirs, half, obj_to_world):
    """Ray distances to an oriented box (half extents (3,)) or inf. origin (3,), dirs (P,3)."""
    world_to_obj = geometry.invert_pose(obj_to_world)
    o = geometry.transform_points(world_to_obj, origin)  # (3,)
    d = geometry.rotate_vectors(world_to_obj, dirs)  # (P,3)
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (-half - o) / d, (half - o) / d  # (P,3)
    near = np.nanmax(np.minimum(t1, t2), axis=-1)
    far = np.nanmin(np.maximum(t1, t2), axis=-1)
    hit = (near <= far) & (far > 0)
    return np.where(hit, np.where(near > 0, near, far), np.inf)


def _cast(cam_to_world, intrinsics, height, width, boxes, box_poses):
    """Ray distance, z-depth and segmentation (H,W) for one camera. box_poses (K,4,4)."""
    pix = geometry.pixel_grid(height, width).reshape(-1, 2)
    rays_cam = np.concatenate([pix, np.ones((len(pix), 1))], -1) @ np.linalg.inv(intrinsics).T
    dirs = geometry.rotate_vectors(cam_to_world, rays_cam)  # (P,3), z-component 1 in camera
    origin = cam_to_world[:3, 3]
    with np.errstate(divide="ignore"):
        t_floor = np.where(dirs[:, 2] < -1e-9, -origin[2] / dirs[:, 2], np.inf)
    # dome: |origin + t d| = R, largest root
    a, b = (dirs * dirs).sum(-1), 2 * dirs @ origin
    c = origin @ origin - DOME_RADIUS**2
    t_dome = (-b + np.sqrt(b * b - 4 * a * c)) / (2 * a)
    dist = np.minimum(t_floor, t_dome)
    seg = np.zeros(len(pix), np.int32)
    for k, half in enumerate(boxes):
        t_box = _box_hits(origin, dirs, half, box_poses[k])
        closer = t_box < dist
        dist, seg = np.where(closer, t_box, dist), np.where(closer, k + 1, seg)
    return dist.reshape(height, width), seg.reshape(height, width)  # t along rays with z=1 => z-depth


def _texture(points_obj: np.ndarray, seg: np.ndarray) -> np.ndarray:
    """Colour (P,3) uint8 from a checker pattern in object/world coordinates and a base per label."""
    base = np.array([[170, 160, 140], [200, 60, 50], [50, 90, 200], [60, 170, 80], [200, 180, 40]])
    checker = (np.floor(points_obj * 2.0).astype(np.int64).sum(-1) % 2)[:, None]
    fine = 0.5 + 0.5 * np.sin(points_obj[:, :1] * 7.3 + points_obj[:, 1:2] * 5.1 + points_obj[:, 2:] * 3.7)
    colour = base[seg % len(base)] * (0.55 + 0.3 * checker + 0.15 * fine)
    return np.clip(colour, 0, 255).astype(np.uint8)


def make_box_scene(
    num_frames: int = 12,
    height: int = 48,
    width: int = 64,
    moving: bool = True,
    num_tracks: int = 64,
    seed: int = 0,
    focal: float | None = None,
    intrinsics: np.ndarray | None = None,
) -> Scene:
    """A camera arcing around a floor with two static boxes and (if `moving`) one sliding box.

    Units follow the contract (Kubric scale: boxes ~1.5 units, camera ~8 units away). The camera
    matrix is `intrinsics` (3,3) if given, else focal `focal` (default 0.9 W) at the image centre.
    """
    rng = np.random.default_rng(seed)
    f = focal or 0.9 * width
    k = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]])
    k = k if intrinsics is None else np.asarray(intrinsics, np.float64)
    t = np.arange(num_frames)
    angle = 0.6 + 0.5 * t / max(num_frames - 1, 1) + 0.05 * rng.standard_normal()
    eyes = np.stack([7.5 * np.cos(angle), 7.5 * np.sin(angle), 3.5 + 0.3 * np.sin(t / 3)], -1)
    cams = np.stack([geometry.look_at(e, np.array([0.0, 0.0, 0.6])) for e in eyes])  # (T,4,4)
    boxes = [np.array([0.8, 0.6, 0.7]), np.array([0.5, 0.9, 0.5]), np.array([0.6, 0.6, 0.6])]
    static_at = [np.array([-1.5, 1.2, 0.7]), np.array([1.8, -1.0, 0.5])]
    poses = np.zeros((len(boxes), num_frames, 4, 4))
    for n, c in enumerate(static_at):
        poses[n] = geometry.make_pose(np.eye(3), c)
    slide = (t / max(num_frames - 1, 1) * 2.5 - 1.2) if moving else np.zeros(num_frames)
    yaw = 0.3 * slide if moving else np.zeros(num_frames)
    rot = np.stack([[np.cos(yaw), -np.sin(yaw), 0 * yaw], [np.sin(yaw), np.cos(yaw), 0 * yaw],
                    [0 * yaw, 0 * yaw, 1 + 0 * yaw]]).transpose(2, 0, 1)
    poses[2] = geometry.make_pose(rot, np.stack([0.3 + 0 * slide, slide, 0.6 + 0 * slide], -1))

    depth = np.zeros((num_frames, height, width), np.float32)
    seg = np.zeros((num_frames, height, width), np.int32)
    rgb = np.zeros((num_frames, height, width, 3), np.uint8)
    for n in range(num_frames):
        depth[n], seg[n] = _cast(cams[n], k, height, width, boxes, poses[:, n])
        world = geometry.unproject_depth_map(depth[n], k, cams[n]).reshape(-1, 3)
        s = seg[n].reshape(-1)
        local = world.copy()
        for b in range(len(boxes)):
            sel = s == b + 1
            local[sel] = geometry.transform_points(geometry.invert_pose(poses[b, n]), world[sel])
        rgb[n] = _texture(local, s).reshape(height, width, 3)

    def carry(points_world, labels, src, dst):
        out = points_world.copy()
        for b in range(len(boxes)):
            sel = labels == b + 1
            motion = poses[b, dst] @ geometry.invert_pose(poses[b, src])
            out[sel] = geometry.transform_points(motion, out[sel])
        return out

    flow_fwd = np.zeros((num_frames, height, width, 2), np.float32)
    flow_bwd = np.zeros_like(flow_fwd)
    grid = geometry.pixel_grid(height, width).reshape(-1, 2)
    for n in range(num_frames):
        world = geometry.unproject_depth_map(depth[n], k, cams[n]).reshape(-1, 3)
        for m, out in ((n + 1, flow_fwd), (n - 1, flow_bwd)):
            if 0 <= m < num_frames:
                uv, _ = geometry.project(carry(world, seg[n].reshape(-1), n, m), k, cams[m])
                out[n] = (uv - grid).reshape(height, width, 2)

    # tracks: query at random pixels of random frames, carried through time, occlusion by z-test
    q_frame = rng.integers(0, num_frames, num_tracks).astype(np.int32)
    q_pix = np.stack([rng.integers(0, width, num_tracks), rng.integers(0, height, num_tracks)], -1)
    labels = seg[q_frame, q_pix[:, 1], q_pix[:, 0]]
    q_world = geometry.unproject(q_pix.astype(float), depth[q_frame, q_pix[:, 1], q_pix[:, 0]],
                                 k, cams[q_frame])  # (N,3)
    tracks_world = np.zeros((num_tracks, num_frames, 3))
    for p in range(num_tracks):
        for n in range(num_frames):
            tracks_world[p, n] = carry(q_world[p:p + 1], labels[p:p + 1], q_frame[p], n)[0]
    tracks = np.zeros((num_tracks, num_frames, 2), np.float32)
    occluded = np.zeros((num_tracks, num_frames), bool)
    for n in range(num_frames):
        uv, z = geometry.project(tracks_world[:, n], k, cams[n])
        tracks[:, n] = uv
        inside = (uv[:, 0] > -0.5) & (uv[:, 0] < width - 0.5) & (uv[:, 1] > -0.5) & (uv[:, 1] < height - 0.5)
        col = np.clip(np.round(uv[:, 0]).astype(int), 0, width - 1)
        row = np.clip(np.round(uv[:, 1]).astype(int), 0, height - 1)
        occluded[:, n] = ~inside | (z <= 0) | (z > depth[n, row, col] * 1.02 + 0.02)
    occluded[np.arange(num_tracks), q_frame] = False
    step = np.linalg.norm(np.diff(tracks_world, axis=1), axis=-1)  # (N,T-1)
    displacement = np.concatenate([step[:, :1], step], axis=1).astype(np.float32)
    return Scene(
        rgb=rgb, depth=depth, segmentation=seg, flow_fwd=flow_fwd, flow_bwd=flow_bwd,
        intrinsics=np.repeat(k[None], num_frames, 0).astype(np.float32),
        cam_to_world=cams.astype(np.float32), object_to_world=poses.astype(np.float32),
        objects=[{"asset_id": f"box{b}", "scale": 1.0, "tossed": b == 2} for b in range(len(boxes))],
        tracks=tracks, occluded=occluded, query_frame=q_frame, track_object=labels.astype(np.int32),
        tracks_world=tracks_world.astype(np.float32), displacement=displacement,
        moving=displacement > 0.01,
        meta={"preset": "synthetic-boxes", "seed": seed, "mobility_threshold": 0.01},
    )
