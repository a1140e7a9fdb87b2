"""Labels computed exactly from geometry: optical flow, point tracks, visibility and mobility.

Every pixel's surface point is known in 3-D (z-depth + camera), and so is the rigid pose of the
thing it lies on (segmentation: 0 = the static backdrop, k = object k-1). Moving that point with
its object's pose to another frame and projecting it gives flow (camera motion included) and point
tracks without any image matching.

Shapes: T frames, H x W pixels, K objects, N tracks. Poses: object_to_world (K,T,4,4),
cam_to_world (T,4,4) OpenCV, intrinsics (T,3,3).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from datagen import geometry


def segment_poses(object_to_world: np.ndarray) -> np.ndarray:
    """(K+1,T,4,4) pose of every segment: index 0 is the fixed backdrop (identity)."""
    num_frames = object_to_world.shape[1]
    backdrop = np.broadcast_to(np.eye(4), (1, num_frames, 4, 4))
    return np.concatenate([backdrop, object_to_world], axis=0)


def flow_between(depth: np.ndarray, segmentation: np.ndarray, intrinsics: np.ndarray,
                 cam_to_world: np.ndarray, poses: np.ndarray, src: int, dst: int) -> np.ndarray:
    """(H,W,2) (dx, dy) motion of the surface seen at each pixel of frame `src` to frame `dst`.

    poses: (K+1,T,4,4) from `segment_poses`.
    """
    points = geometry.unproject_depth_map(depth[src], intrinsics[src], cam_to_world[src])  # (H,W,3)
    relative = poses[:, dst] @ geometry.invert_pose(poses[:, src])  # (K+1,4,4) src -> dst
    moved = geometry.transform_points(relative[segmentation[src]], points)  # (H,W,3)
    pixels, _ = geometry.project(moved, intrinsics[dst], cam_to_world[dst])  # (H,W,2)
    return (pixels - geometry.pixel_grid(*depth.shape[1:])).astype(np.float32)


def optical_flow(depth, segmentation, intrinsics, cam_to_world, object_to_world):
    """Forward and backward flow (T,H,W,2); flow_fwd[T-1] and flow_bwd[0] are zero (invalid)."""
    poses = segment_poses(object_to_world)
    num_frames = depth.shape[0]
    fwd = np.zeros(depth.shape + (2,), np.float32)
    bwd = np.zeros(depth.shape + (2,), np.float32)
    for t in range(num_frames - 1):
        fwd[t] = flow_between(depth, segmentation, intrinsics, cam_to_world, poses, t, t + 1)
        bwd[t + 1] = flow_between(depth, segmentation, intrinsics, cam_to_world, poses, t + 1, t)
    return fwd, bwd


def allocate_points(counts: np.ndarray, total: int, max_fraction: float) -> np.ndarray:
    """How many tracks each segment gets: about equal shares, at most `max_fraction` of its count.

    Segments are visited from the smallest; a segment's unused share passes on to larger ones
    (TAP-Vid-Kubric's rule), so small objects are not drowned by the background.
    """
    alloc = np.zeros(len(counts), dtype=np.int64)
    order = np.argsort(counts, kind="stable")
    remaining = total
    for i, seg in enumerate(order):
        share = int(round(remaining / (len(order) - i)))
        alloc[seg] = min(share, int(np.ceil(max_fraction * counts[seg])), counts[seg])
        remaining -= alloc[seg]
    return alloc


def surface_normals(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (H,W,3) of a point map (H,W,3), and whether each is reliable (H,W).

    The normal is the cross product of central differences; it is reliable where the four
    one-sided normals agree (a smooth surface, not a depth edge), as TAP-Vid-Kubric requires.
    """
    pad = np.pad(points, ((1, 1), (1, 1), (0, 0)), mode="edge")
    right, left = pad[1:-1, 2:] - points, points - pad[1:-1, :-2]
    down, up = pad[2:, 1:-1] - points, points - pad[:-2, 1:-1]

    def unit(v):
        return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)

    normal = unit(np.cross(right + left, down + up))
    one_sided = [unit(np.cross(a, b)) for a in (right, left) for b in (down, up)]
    reliable = np.all([np.sum(n * normal, -1) > 0.95 for n in one_sided], axis=0)
    return normal, reliable


@dataclass
class Tracks:
    tracks: np.ndarray  # float32 (N,T,2) (x, y) pixels
    occluded: np.ndarray  # bool (N,T)
    query_frame: np.ndarray  # int32 (N,)
    track_object: np.ndarray  # int32 (N,) 0 = backdrop, k = object k-1
    tracks_world: np.ndarray  # float32 (N,T,3)
    displacement: np.ndarray  # float32 (N,T) world distance since t-1 (t=0: to t+1)
    moving: np.ndarray  # bool (N,T)


def sample_queries(segmentation: np.ndarray, rng: np.random.Generator, num_points: int,
                   frame_stride: int, pixel_stride: int, max_fraction: float):
    """Query (t, y, x) integer points spread over strided frames and evenly over segments.

    Candidates form a (frame, row, col) grid of the given strides with a random phase per axis;
    each segment (backdrop included) gets an about equal share (`allocate_points`), drawn without
    replacement. Returns int arrays t, y, x of length num_points (repeating points if the grid
    is too small, as TAP-Vid-Kubric pads).
    """
    num_frames, height, width = segmentation.shape
    t0, y0, x0 = (int(rng.integers(min(frame_stride, num_frames))),
                  int(rng.integers(min(pixel_stride, height))),
                  int(rng.integers(min(pixel_stride, width))))
    tt, yy, xx = np.meshgrid(np.arange(t0, num_frames, frame_stride),
                             np.arange(y0, height, pixel_stride),
                             np.arange(x0, width, pixel_stride), indexing="ij")
    tt, yy, xx = tt.ravel(), yy.ravel(), xx.ravel()
    seg = segmentation[tt, yy, xx]
    ids, inverse, counts = np.unique(seg, return_inverse=True, return_counts=True)
    alloc = allocate_points(counts, num_points, max_fraction)
    chosen = np.concatenate([
        rng.choice(np.flatnonzero(inverse == j), size=alloc[j], replace=False)
        for j in range(len(ids))
    ])
    chosen = rng.permutation(chosen)
    if len(chosen) < num_points:  # too few candidates: repeat some
        chosen = np.concatenate([chosen, rng.choice(chosen, num_points - len(chosen))])
    return tt[chosen], yy[chosen], xx[chosen]


def occlusion(pixels: np.ndarray, z: np.ndarray, track_object: np.ndarray, depth: np.ndarray,
              segmentation: np.ndarray, tolerance: float) -> np.ndarray:
    """bool (N,T): behind the camera, out of view, behind a nearer surface, or on another segment.

    pixels (N,T,2), z (N,T) z-depth of the track point; depth/segmentation (T,H,W). The depth and
    segment tests look at the 4 pixels around the point: it is hidden if all of them are nearer
    than z by more than `tolerance` (relative), or none of them shows its segment.
    """
    num_frames, height, width = depth.shape
    x, y = pixels[..., 0], pixels[..., 1]
    in_view = (z > 0) & (x >= -0.5) & (x <= width - 0.5) & (y >= -0.5) & (y <= height - 0.5)
    frame = np.broadcast_to(np.arange(num_frames), z.shape)
    x0 = np.floor(np.nan_to_num(x)).astype(np.int64)
    y0 = np.floor(np.nan_to_num(y)).astype(np.int64)
    max_depth = np.zeros(z.shape)
    same_segment = np.zeros(z.shape, dtype=bool)
    for dy in (0, 1):
        for dx in (0, 1):
            xi, yi = np.clip(x0 + dx, 0, width - 1), np.clip(y0 + dy, 0, height - 1)
            max_depth = np.maximum(max_depth, depth[frame, yi, xi])
            same_segment |= segmentation[frame, yi, xi] == track_object[:, None]
    hidden = max_depth < (1.0 - tolerance) * z
    return ~in_view | hidden | ~same_segment


def point_tracks(depth, segmentation, intrinsics, cam_to_world, object_to_world,
                 rng: np.random.Generator, cfg, mobility_threshold: float) -> Tracks:
    """TAP-Vid-Kubric-style tracks with world positions, displacement and mobility labels."""
    c = cfg.tracks
    num_frames = depth.shape[0]
    poses = segment_poses(object_to_world)  # (K+1,T,4,4)
    tq, yq, xq = sample_queries(segmentation, rng, int(c.num_points), int(c.query_stride),
                                int(c.grid_stride), float(c.max_sampled_fraction))
    obj = segmentation[tq, yq, xq]  # (N,)
    query_world = geometry.unproject(np.stack([xq, yq], -1), depth[tq, yq, xq],
                                     intrinsics[tq], cam_to_world[tq])  # (N,3)
    local = geometry.transform_points(geometry.invert_pose(poses[obj, tq]), query_world)  # (N,3)
    world = geometry.transform_points(poses[obj], local[:, None])  # (N,T,3)
    pixels, z = geometry.project(world, intrinsics[None], cam_to_world[None])  # (N,T,2), (N,T)
    occluded = occlusion(pixels, z, obj, depth, segmentation, float(c.depth_tolerance))

    # Facing away: the query-frame surface normal, carried with the object, points away from the
    # camera. Only on objects, where the normal at the query pixel is reliable and faces the camera.
    normals_q = np.zeros((len(obj), 3))
    reliable = np.zeros(len(obj), dtype=bool)
    for t in np.unique(tq):
        points = geometry.unproject_depth_map(depth[t], intrinsics[t], cam_to_world[t])
        normal, ok = surface_normals(points)
        sel = tq == t
        normals_q[sel], reliable[sel] = normal[yq[sel], xq[sel]], ok[yq[sel], xq[sel]]
    rel_rot = poses[obj] @ geometry.invert_pose(poses[obj, tq])[:, None]  # (N,T,4,4)
    normals = geometry.rotate_vectors(rel_rot, normals_q[:, None])  # (N,T,3)
    view = world - cam_to_world[None, :, :3, 3]  # (N,T,3) camera -> point
    facing_q = np.sum(normals_q * (query_world - cam_to_world[tq, :3, 3]), -1) < 0
    away = np.sum(normals * view, -1) > 0
    occluded |= away & (reliable & facing_q & (obj > 0))[:, None]
    # A query point is visible at its query frame by construction (its own pixel, depth, segment).
    occluded[np.arange(len(obj)), tq] = False

    step = np.linalg.norm(np.diff(world, axis=1), axis=-1)  # (N,T-1)
    displacement = np.concatenate([step[:, :1], step], axis=1) if num_frames > 1 \
        else np.zeros((len(obj), 1))
    return Tracks(
        tracks=pixels.astype(np.float32),
        occluded=occluded,
        query_frame=tq.astype(np.int32),
        track_object=obj.astype(np.int32),
        tracks_world=world.astype(np.float32),
        displacement=displacement.astype(np.float32),
        moving=displacement > mobility_threshold,
    )
