"""Labels computed exactly from geometry: optical flow, point tracks, visibility and mobility;
per-object boxes, image positions and velocities; collision events.

Every pixel's surface point is known in 3-D (z-depth + camera), and so is the rigid pose of the
thing it lies on (segmentation: 0 = the static backdrop, k = object k-1). Moving that point with
its object's pose to another frame and projecting it gives flow (camera motion included) and point
tracks without any image matching.

Shapes: T frames, H x W pixels, K objects, N tracks. Poses: object_to_world (K,T,4,4),
cam_to_world (T,4,4) OpenCV, intrinsics (T,3,3).
"""

from __future__ import annotations

import functools
import types
from dataclasses import dataclass

import numpy as np

from c4d_core import geometry
from datagen.scene import EVENT_KEYS, INSTANCE_KEYS


def segment_poses(object_to_world: np.ndarray) -> np.ndarray:
    """(K+1,T,4,4) pose of every segment: index 0 is the fixed backdrop (identity)."""
    num_frames = object_to_world.shape[1]
    backdrop = np.broadcast_to(np.eye(4), (1, num_frames, 4, 4))
    return np.concatenate([backdrop, object_to_world], axis=0)


@functools.lru_cache(maxsize=1)
def _pixel_rays(intrinsics: bytes, height: int, width: int) -> np.ndarray:
    """(H,W,3) float64 K^-1 [x, y, 1] of every pixel centre (z = 1), read-only; `intrinsics`
    the bytes of a float64 (3,3) K. Cached: a scene's frames share one K."""
    K = np.frombuffer(intrinsics, np.float64).reshape(3, 3)
    pixels = np.concatenate([geometry.pixel_grid(height, width), np.ones((height, width, 1))], -1)
    rays = pixels @ np.linalg.inv(K).T
    rays.flags.writeable = False
    return rays


@functools.lru_cache(maxsize=1)
def _pixel_grid32(height: int, width: int) -> np.ndarray:
    """`geometry.pixel_grid` as float32 (H,W,2), read-only (cached for the flow of every frame)."""
    grid = geometry.pixel_grid(height, width).astype(np.float32)
    grid.flags.writeable = False
    return grid


def camera_points(depth: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
    """(H,W,3) float32 camera-frame point seen at every pixel centre of a z-depth map (H,W)."""
    K = np.ascontiguousarray(intrinsics, np.float64)
    rays = _pixel_rays(K.tobytes(), *depth.shape)  # (H,W,3) with z = 1
    return (rays * depth[..., None]).astype(np.float32)


def flow_between(points_src: np.ndarray, segmentation_src: np.ndarray, intrinsics_dst: np.ndarray,
                 cam_to_world: np.ndarray, poses: np.ndarray, src: int, dst: int) -> np.ndarray:
    """(H,W,2) (dx, dy) motion of the surface seen at each pixel of frame `src` to frame `dst`.

    points_src: (H,W,3) from `camera_points` for frame src; segmentation_src (H,W);
    cam_to_world (T,4,4); poses (K+1,T,4,4) from `segment_poses`.
    """
    # Per segment: src camera -> world -> the segment's motion src -> dst -> dst camera.
    motion = poses[:, dst] @ geometry.invert_pose(poses[:, src])  # (K+1,4,4)
    cam_motion = geometry.invert_pose(cam_to_world[dst]) @ motion @ cam_to_world[src]
    # Each entry of the segments' [R | t] (3,4) gathered per pixel as its own (H,W) array.
    entries = np.ascontiguousarray(cam_motion[:, :3].astype(np.float32).reshape(-1, 12).T)
    m = np.take(entries, segmentation_src, axis=1)  # (12,H,W) float32
    x, y, z = points_src[..., 0], points_src[..., 1], points_src[..., 2]  # (H,W) each
    # R p + t row by row, in einsum's float32 order ((r0 x + r1 y) + r2 z) + t
    points_dst = np.stack([m[4 * i] * x + m[4 * i + 1] * y + m[4 * i + 2] * z + m[4 * i + 3]
                           for i in range(3)], axis=-1)  # (H,W,3)
    projected = points_dst @ intrinsics_dst.T.astype(np.float32)  # (H,W,3)
    z_dst = projected[..., 2]
    pixels = np.stack([projected[..., 0] / z_dst, projected[..., 1] / z_dst], axis=-1)  # (H,W,2)
    return pixels - _pixel_grid32(*segmentation_src.shape)


def optical_flow(depth, segmentation, intrinsics, cam_to_world, object_to_world):
    """Forward and backward flow (T,H,W,2); flow_fwd[T-1] and flow_bwd[0] are zero (invalid)."""
    poses = segment_poses(object_to_world)
    fwd = np.zeros(depth.shape + (2,), np.float32)
    bwd = np.zeros(depth.shape + (2,), np.float32)
    points = [camera_points(depth[t], intrinsics[t]) for t in range(depth.shape[0])]
    for t in range(depth.shape[0] - 1):
        fwd[t] = flow_between(points[t], segmentation[t], intrinsics[t + 1], cam_to_world, poses,
                              t, t + 1)
        bwd[t + 1] = flow_between(points[t + 1], segmentation[t + 1], intrinsics[t], cam_to_world,
                                  poses, t + 1, t)
    return fwd, bwd


def allocate_points(counts: np.ndarray, total: int, max_fraction: float,
                    exact_kubric: bool = False) -> np.ndarray:
    """How many tracks each segment gets: about equal shares, at most `max_fraction` of its count.

    Segments are visited from the smallest; a segment's unused share passes on to larger ones
    (TAP-Vid-Kubric's rule), so small objects are not drowned by the background. The cap is
    ceil(max_fraction * count) and never more than the count (our generator draws without
    replacement); `exact_kubric` caps at round(max_fraction * count) as `get_num_to_sample` does.
    """
    alloc = np.zeros(len(counts), dtype=np.int64)
    order = np.argsort(counts, kind="stable")
    remaining = total
    for i, seg in enumerate(order):
        share = int(round(remaining / (len(order) - i)))
        cap = int(round(max_fraction * counts[seg])) if exact_kubric \
            else min(int(np.ceil(max_fraction * counts[seg])), int(counts[seg]))
        alloc[seg] = min(share, cap)
        remaining -= alloc[seg]
    return alloc


def surface_normals(depth: np.ndarray, intrinsics: np.ndarray, cam_to_world: np.ndarray,
                    x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World unit normals (n,3), facing the camera, of the depth map's surface at integer pixels
    (x, y), and whether each is reliable (n,).

    The normal is the cross product of central differences of unprojected neighbours; it is
    reliable where the four one-sided normals agree (a smooth surface, not a depth edge), as
    TAP-Vid-Kubric requires before testing whether a point faces away.
    """
    height, width = depth.shape
    offsets = np.array([[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1]])  # centre, right, left, down, up
    px = np.clip(x[:, None] + offsets[:, 0], 0, width - 1)  # (n,5)
    py = np.clip(y[:, None] + offsets[:, 1], 0, height - 1)
    points = geometry.unproject(np.stack([px, py], -1), depth[py, px], intrinsics, cam_to_world)
    centre = points[:, 0]
    right, left = points[:, 1] - centre, centre - points[:, 2]
    down, up = points[:, 3] - centre, centre - points[:, 4]

    def unit(v):
        return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)

    # Image x right and y down span the surface; (down x right) points back toward the camera.
    normal = unit(np.cross(down + up, right + left))
    one_sided = [unit(np.cross(b, a)) for a in (right, left) for b in (down, up)]
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
                   frame_stride: int, pixel_stride: int, max_fraction: float,
                   exact_kubric: bool = False):
    """Query (t, y, x) integer points spread over strided frames and evenly over segments.

    Candidates form a (frame, row, col) grid of the given strides with a random phase per axis;
    each segment (backdrop included) gets an about equal share (`allocate_points`). Our generator
    draws a segment's share without replacement, in random order, and repeats random points if
    the grid is too small. `exact_kubric` follows TAP-Vid-Kubric's sampler instead (reference
    kubric_movi.md 3.2): with replacement, segments in ascending id order, and a short draw padded
    by repeating its second-to-last point. Returns int arrays t, y, x of length num_points.
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
    alloc = allocate_points(counts, num_points, max_fraction, exact_kubric)
    chosen = np.concatenate([
        rng.choice(np.flatnonzero(inverse == j), size=alloc[j], replace=exact_kubric)
        for j in range(len(ids))
    ])
    if exact_kubric:
        if 0 < len(chosen) < num_points:
            pad = chosen[-2:-1] if len(chosen) > 1 else chosen[-1:]
            chosen = np.concatenate([chosen, np.repeat(pad, num_points - len(chosen))])
        return tt[chosen], yy[chosen], xx[chosen]
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


def world_motion(world: np.ndarray, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """displacement float32 (N,T) and moving bool (N,T) of world points (N,T,3): the distance
    each point moved since frame t-1 (t = 0: to frame 1; 0 in a one-frame video), and whether it
    exceeds `threshold` (world units a frame; compared before the float32 cast). The mobility
    label of our scenes (`point_tracks`) and of readers that lift tracks to the world."""
    step = np.linalg.norm(np.diff(world, axis=1), axis=-1)  # (N,T-1)
    displacement = np.concatenate([step[:, :1], step], axis=1) if world.shape[1] > 1 \
        else np.zeros(world.shape[:2])
    return displacement.astype(np.float32), displacement > threshold


# Box corner order (8,3) of 0/1 = min/max per axis: x slowest, then y, then z (Kubric's order).
BOX_CORNERS = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)])


def box_corners(boxes: np.ndarray) -> np.ndarray:
    """(K,8,3) corners of axis-aligned boxes (K,2,3) given as (min, max) corners."""
    return boxes[:, BOX_CORNERS, np.arange(3)]


def box_frames(boxes_3d: np.ndarray) -> np.ndarray:
    """float64 (...,4,4) affine maps from box-local coordinates to world, of boxes given by their
    world corners (...,8,3) in `BOX_CORNERS` order.

    Box-local coordinates are Kubric's object coordinates minus 0.5: the box is the cube
    [-0.5, 0.5]^3, scaled, rotated and moved. The map is the least-squares affine fit to the 8
    corners, as TAP-Vid-Kubric's `reproject` fits it (exact for a box's corners)."""
    unit = np.concatenate([BOX_CORNERS - 0.5, np.ones((8, 1))], axis=1)  # (8,4) homogeneous
    fit = np.linalg.pinv(unit) @ np.asarray(boxes_3d, np.float64)  # (...,4,3): world = unit @ fit
    frames = np.zeros(fit.shape[:-2] + (4, 4))
    frames[..., :3, :] = np.swapaxes(fit, -1, -2)
    frames[..., 3, 3] = 1.0
    return frames


@dataclass(frozen=True)
class BoxLift:
    """Object points lifted as TAP-Vid-Kubric lifts them: from their object coordinates in the
    object's 3-D box (`box_frames`), which moves with the object, instead of from depth.

    object_coordinates: indexable by integer arrays [t, y, x] -> (N,3) coordinates in [0, 1]
    (a (T,H,W,3) array, or a reader's lazy frames); boxes_3d: (K,T,8,3) world box corners of
    objects 1..K (segment k = row k-1). Where depth is stored coarsely (16 bits over the scene's
    range in Kubric's records) this is the more exact lift."""

    object_coordinates: object
    boxes_3d: np.ndarray

    def world(self, obj: np.ndarray, tq: np.ndarray, yq: np.ndarray, xq: np.ndarray
              ) -> np.ndarray:
        """float64 (N,T,3) world positions over all frames of the query points (tq, yq, xq)
        on segments `obj` >= 1."""
        local = np.asarray(self.object_coordinates[tq, yq, xq], np.float64) - 0.5  # (N,3)
        frames = box_frames(self.boxes_3d[obj - 1])  # (N,T,4,4)
        return geometry.transform_points(frames, local[:, None])


def point_tracks(depth, segmentation, intrinsics, cam_to_world, object_to_world,
                 rng: np.random.Generator, cfg, mobility_threshold: float,
                 exact_kubric: bool = False, box_lift: BoxLift | None = None) -> Tracks:
    """TAP-Vid-Kubric-style tracks with world positions, displacement and mobility labels.

    `cfg.tracks` holds the sampling settings (num_points, query_stride, grid_stride,
    max_sampled_fraction, depth_tolerance); `exact_kubric` samples the queries exactly as
    TAP-Vid-Kubric does (`sample_queries`). Query points are lifted to 3-D from the depth at
    their pixel and carried by their object's pose; with `box_lift`, points on objects are
    lifted from their object coordinates in the object's 3-D box instead (`BoxLift`), as
    TAP-Vid-Kubric lifts them."""
    c = cfg.tracks
    poses = segment_poses(object_to_world)  # (K+1,T,4,4)
    tq, yq, xq = sample_queries(segmentation, rng, int(c.num_points), int(c.query_stride),
                                int(c.grid_stride), float(c.max_sampled_fraction), exact_kubric)
    obj = segmentation[tq, yq, xq]  # (N,)
    query_world = geometry.unproject(np.stack([xq, yq], -1), depth[tq, yq, xq],
                                     intrinsics[tq], cam_to_world[tq])  # (N,3)
    local = geometry.transform_points(geometry.invert_pose(poses[obj, tq]), query_world)  # (N,3)
    world = geometry.transform_points(poses[obj], local[:, None])  # (N,T,3)
    on_object = obj > 0
    if box_lift is not None and on_object.any():
        world[on_object] = box_lift.world(obj[on_object], tq[on_object], yq[on_object],
                                          xq[on_object])
        query_world[on_object] = world[on_object, tq[on_object]]
    pixels, z = geometry.project(world, intrinsics[None], cam_to_world[None])  # (N,T,2), (N,T)
    occluded = occlusion(pixels, z, obj, depth, segmentation, float(c.depth_tolerance))

    # Facing away: the query-frame surface normal, carried with the object, points away from the
    # camera. Only on objects, where the normal at the query pixel is reliable and faces the camera.
    normals_q = np.zeros((len(obj), 3))
    reliable = np.zeros(len(obj), dtype=bool)
    for t in np.unique(tq):
        sel = tq == t
        normals_q[sel], reliable[sel] = surface_normals(depth[t], intrinsics[t], cam_to_world[t],
                                                        xq[sel], yq[sel])
    rel_rot = poses[obj] @ geometry.invert_pose(poses[obj, tq])[:, None]  # (N,T,4,4)
    normals = geometry.rotate_vectors(rel_rot, normals_q[:, None])  # (N,T,3)
    view = world - cam_to_world[None, :, :3, 3]  # (N,T,3) camera -> point
    facing_q = np.sum(normals_q * (query_world - cam_to_world[tq, :3, 3]), -1) < 0
    away = np.sum(normals * view, -1) > 0
    occluded |= away & (reliable & facing_q & (obj > 0))[:, None]
    # A query point is visible at its query frame by construction (its own pixel, depth, segment).
    occluded[np.arange(len(obj)), tq] = False

    displacement, moving = world_motion(world, mobility_threshold)
    return Tracks(
        tracks=pixels.astype(np.float32),
        occluded=occluded,
        query_frame=tq.astype(np.int32),
        track_object=obj.astype(np.int32),
        tracks_world=world.astype(np.float32),
        displacement=displacement,
        moving=moving,
    )


# TAP-Vid-Kubric's defaults (kubric challenges/point_tracking/dataset.py, as tapnet calls it;
# reference kubric_movi.md 3.2-3.4): 256 tracks, a stride-4 (t, y, x) grid, at most 10 % of a
# segment's grid points, 1 % depth tolerance.
TAPVID_KUBRIC_TRACKS = {"num_points": 256, "query_stride": 4, "grid_stride": 4,
                        "max_sampled_fraction": 0.1, "depth_tolerance": 0.01}


def tapvid_kubric_tracks(scene, seed, num_tracks: int = 256,
                         box_lift: BoxLift | None = None) -> Tracks:
    """`num_tracks` tracks of a Scene drawn afresh as TAP-Vid-Kubric draws them, seeded.

    Needs the scene's depth, segmentation, cameras and object poses (datagen shards, or a reader
    of Kubric's data); its mobility threshold is `scene.meta['mobility_threshold']` (world units
    a frame). `seed`: an int or a sequence of ints for `np.random.default_rng` (e.g. [seed,
    video index]). Object points are lifted from their object coordinates in their 3-D boxes
    (`BoxLift`, as TAP-Vid-Kubric lifts them: what Kubric's records hold exactly) where the
    scene has both layers (`object_coordinates`, `instances`) or `box_lift` is given, else
    from depth. Raises ValueError when a layer is missing.
    """
    missing = [name for name in ("depth", "segmentation", "object_to_world")
               if getattr(scene, name) is None]
    if missing:
        raise ValueError(f"drawing TAP-Vid-Kubric tracks needs the scene's {', '.join(missing)}")
    if box_lift is None and scene.object_coordinates is not None and scene.instances is not None:
        box_lift = BoxLift(scene.object_coordinates, scene.instances["bbox_3d"])
    cfg = types.SimpleNamespace(tracks=types.SimpleNamespace(
        **{**TAPVID_KUBRIC_TRACKS, "num_points": num_tracks}))
    return point_tracks(scene.depth, scene.segmentation, scene.intrinsics, scene.cam_to_world,
                        scene.object_to_world, np.random.default_rng(seed), cfg,
                        float(scene.meta["mobility_threshold"]), exact_kubric=True,
                        box_lift=box_lift)




def segment_boxes(segmentation: np.ndarray, num_objects: int) -> tuple[np.ndarray, np.ndarray]:
    """Visible pixels int32 (K,T) and 2-D boxes float32 (K,T,4) of segments 1..K per frame.

    A box is [ymin, xmin, ymax, xmax] of the outermost pixels of the segment, as pixel edges
    divided by (H, W, H, W): ymin = first row / H, ymax = (last row + 1) / H, so it lies in [0,1]
    and a one-pixel object has a box of one pixel's size. NaN where the segment is not visible.
    """
    num_frames, height, width = segmentation.shape
    labels = segmentation + (num_objects + 1) * np.arange(num_frames)[:, None, None]  # (T,H,W)
    count = num_frames * (num_objects + 1)
    pixels = np.bincount(labels.ravel(), minlength=count).reshape(num_frames, num_objects + 1)
    extents = []
    for axis, size in ((1, height), (2, width)):
        index = np.arange(size).reshape((1, size, 1) if axis == 1 else (1, 1, size))
        present = np.bincount((labels * size + index).ravel(), minlength=count * size)
        present = present.reshape(num_frames, num_objects + 1, size) > 0  # (T,K+1,size)
        first = np.argmax(present, axis=-1)
        last = size - np.argmax(present[..., ::-1], axis=-1)
        extents.append((first / size, last / size))
    (y0, y1), (x0, x1) = extents
    boxes = np.stack([y0, x0, y1, x1], axis=-1).astype(np.float32)  # (T,K+1,4)
    boxes[pixels == 0] = np.nan
    return (np.ascontiguousarray(pixels[:, 1:].T).astype(np.int32),
            np.ascontiguousarray(boxes[:, 1:].transpose(1, 0, 2)))


def instance_labels(segmentation, intrinsics, cam_to_world, object_to_world, boxes, velocities,
                    angular_velocities, dynamic) -> dict[str, np.ndarray]:
    """`Scene.instances` (keys and dtypes of `INSTANCE_KEYS`) of K objects over T frames.

    segmentation (T,H,W); intrinsics (T,3,3); cam_to_world (T,4,4); object_to_world (K,T,4,4);
    boxes (K,2,3) the (min, max) corners of each object's box in its own frame (units);
    velocities and angular_velocities (K,T,3) world, units/s and rad/s; dynamic (K,) bool.
    `image_position` is the projection of the object's origin (its centre of mass, Kubric's
    object position), NaN where it lies behind the camera.
    """
    corners = box_corners(boxes)  # (K,8,3)
    pixels, z = geometry.project(object_to_world[..., :3, 3], intrinsics[None], cam_to_world[None])
    pixels[z <= 0] = np.nan
    visible, boxes_2d = segment_boxes(segmentation, len(object_to_world))
    values = {
        "bbox_3d": geometry.transform_points(object_to_world[:, :, None], corners[:, None]),
        "bbox_2d": boxes_2d, "visible_pixels": visible, "image_position": pixels,
        "velocity": velocities, "angular_velocity": angular_velocities, "is_dynamic": dynamic,
    }
    return {key: np.ascontiguousarray(values[key], dtype) for key, (dtype, _) in INSTANCE_KEYS.items()}


def collision_events(contacts: np.ndarray, steps_per_frame: int, intrinsics: np.ndarray,
                     camera_pose_at) -> dict[str, np.ndarray]:
    """`Scene.events` (keys and dtypes of `EVENT_KEYS`, (E,...) each) from pybullet contacts
    (`datagen.simulate.CONTACT_DTYPE`, (E,)).

    Per event: the two instances (object indices, -1 the floor), the frame time
    (step / steps_per_frame - 1), the normal force (N), the contact point on the second instance
    (world), its (x, y) pixel in the camera at that time (intrinsics (3,3);
    camera_pose_at(times (E,)) -> (E,4,4)) and the contact normal on the second instance,
    pointing to the first (world).
    """
    frame = contacts["step"] / steps_per_frame - 1.0  # (E,)
    pixels, _ = geometry.project(contacts["position"], intrinsics, camera_pose_at(frame))
    values = {"instances": contacts["bodies"], "frame": frame, "force": contacts["force"],
              "position": contacts["position"], "image_position": pixels,
              "contact_normal": contacts["normal"]}
    return {key: np.ascontiguousarray(values[key], dtype).reshape((len(contacts),) + shape)
            for key, (dtype, shape) in EVENT_KEYS.items()}
