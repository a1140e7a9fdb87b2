"""Ground truth read from a generated datagen `Scene`: the oracle inputs of the C4D pipeline.

Everything here knows the scene's depth, segmentation, cameras, object poses and track labels,
which a real video does not have; the pipeline's own estimators live in `pointmaps.py`
(interface), `dust3r_pointmaps.py`, `flow.py` and `motion_mask.py`, and each oracle below stands in
for one of them behind the same interface:
- `GroundTruthPointmaps`: a `PointmapSource` (noise, per-pair scale, static-world bias), spec 'gt'
  of `c4d_pipeline.pointmap_sources.build_pointmaps`;
- `GroundTruthFlow`: a flow estimator, spec 'gt' of `c4d_pipeline.flow.build_flow`;
- `oracle_tracks`: the scene's tracks and mobility labels as a tracker result (an oracle DynPT);
- `ground_truth_motion_masks`: the true per-pixel motion masks, the reference of mask IoU.
`scene_point_motion` (where each pixel's surface point is at another frame) is the geometry they
share; `resize_intrinsics` / `resize_nearest` resample a scene's cameras and labels.
"""

from __future__ import annotations

import zlib
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from c4d_core.errors import UserError
from c4d_core.geometry import invert_pose, pixel_grid, project, transform_points, unproject_depth_map
from c4d_pipeline.flow_inputs import Pair, check_flow_inputs
from c4d_pipeline.pointmaps import PairwisePointmaps, sanitize
from c4d_pipeline.procrustes import weighted_procrustes
from datagen.scene import Scene
from dynpt.inference import TrackResult


# ----------------------------------------------------------------------------- scene geometry


def resize_intrinsics(intrinsics: np.ndarray, src_hw: tuple[int, int], dst_hw: tuple[int, int]) -> np.ndarray:
    """K (...,3,3) for images resized from src_hw to dst_hw (pixel centres stay at integers)."""
    sy, sx = dst_hw[0] / src_hw[0], dst_hw[1] / src_hw[1]
    scale = np.array([[sx, 0, 0.5 * sx - 0.5], [0, sy, 0.5 * sy - 0.5], [0, 0, 1]], np.float64)
    return (scale @ intrinsics.astype(np.float64)).astype(np.float32)


def resize_nearest(image: np.ndarray, dst_hw: tuple[int, int]) -> np.ndarray:
    """(H,W,...) -> (h,w,...) by nearest neighbour at the new pixel centres (labels, depth, masks)."""
    height, width = image.shape[:2]
    rows = ((np.arange(dst_hw[0]) + 0.5) * height / dst_hw[0]).astype(int)  # (h,)
    cols = ((np.arange(dst_hw[1]) + 0.5) * width / dst_hw[1]).astype(int)  # (w,)
    return image[rows[:, None], cols[None, :]]


def scene_point_motion(scene: Scene, i: int, j: int, hw: tuple[int, int] | None = None):
    """Where the surface seen in frame i is at the time of frame j, in world coordinates.

    Returns (points_i, points_j), float64 (h,w,3) world positions at times i and j of the
    surface point at each pixel of frame i (background is static; object k moves rigidly with
    `object_to_world[k-1]`). `hw` resamples the frame to (h, w) first (default: scene size).
    """
    hw = hw or scene.image_size
    depth = resize_nearest(scene.depth[i], hw)  # (h,w)
    segmentation = resize_nearest(scene.segmentation[i], hw)  # (h,w) int32
    intrinsics = resize_intrinsics(scene.intrinsics[i], scene.image_size, hw)
    points_i = unproject_depth_map(depth, intrinsics, scene.cam_to_world[i].astype(np.float64))  # (h,w,3)
    points_j = points_i.copy()
    for k in np.unique(segmentation[segmentation > 0]):
        pose_i, pose_j = scene.object_to_world[k - 1, i], scene.object_to_world[k - 1, j]
        moved = pose_j.astype(np.float64) @ invert_pose(pose_i.astype(np.float64))  # world at i -> at j
        on_object = segmentation == k
        points_j[on_object] = transform_points(moved, points_i[on_object])
    return points_i, points_j


class GroundTruthFlow:
    """Exact flow of a datagen `Scene` between any two frames (i, j).

    Each pixel of frame i is lifted with its z-depth, moved with its object's rigid motion from
    time i to j (static for background), and projected with frame j's camera. Pixels whose
    point lies behind camera j get zero flow. Frames may be passed resized: the flow is then
    computed at their resolution (intrinsics rescaled, depth and labels sampled nearest).
    """

    def __init__(self, scene: Scene):
        missing = [n for n in ("depth", "segmentation", "object_to_world") if getattr(scene, n) is None]
        if missing:
            raise UserError(f"ground-truth flow needs the scene's {', '.join(missing)}; use flow 'dis'")
        self.scene = scene

    def flow(self, frames: np.ndarray, pairs: Sequence[Pair]) -> np.ndarray:
        check_flow_inputs(frames, pairs)
        if frames.shape[0] != self.scene.num_frames:
            raise UserError(
                f"ground-truth flow got {frames.shape[0]} frames for a scene of "
                f"{self.scene.num_frames}; pass the scene's own frames (or a scene cut to match)"
            )
        hw = frames.shape[1:3]
        grid = pixel_grid(*hw)  # (h,w,2)
        out = np.zeros((len(pairs), *hw, 2), np.float32)  # (P,h,w,2)
        for p, (i, j) in enumerate(pairs):
            _, points_j = scene_point_motion(self.scene, i, j, hw)  # (h,w,3) world at time j
            intrinsics_j = resize_intrinsics(self.scene.intrinsics[j], self.scene.image_size, hw)
            pixels_j, z_j = project(points_j, intrinsics_j.astype(np.float64), self.scene.cam_to_world[j].astype(np.float64))
            out[p] = np.where(z_j[..., None] > 1e-9, pixels_j - grid, 0.0)  # (h,w,2)
        return out


# ----------------------------------------------------------------------------- pointmaps


def _smooth_field(rng: np.random.Generator, height: int, width: int, cells: int) -> np.ndarray:
    """A zero-mean, unit-std random field varying smoothly over about `cells` cells per side."""
    coarse = torch.from_numpy(rng.standard_normal((1, 1, cells + 1, cells + 1)).astype(np.float32))
    field = F.interpolate(coarse, size=(height, width), mode="bicubic", align_corners=True)[0, 0]
    field = field.numpy()
    return (field - field.mean()) / max(float(field.std()), 1e-6)


def scene_key(scene) -> int:
    """CRC-32 of a scene's cameras (cam_to_world, intrinsics) and depth: a seed component that is
    equal for the same scene however it was loaded (arrays, or frames read from disk one at a time)
    and differs between scenes."""
    key = 0
    for array in (scene.cam_to_world, scene.intrinsics, scene.depth):
        for t in range(len(array)):  # frame by frame: the same CRC, and a depth kept on disk is read a frame at a time
            key = zlib.crc32(np.ascontiguousarray(array[t], np.float32).tobytes(), key)
    return key


class GroundTruthPointmaps:
    """Pairwise pointmaps computed from a datagen `Scene`'s depth, cameras and object motion.

    For a pair (i, j):
    - pts_i: view i's pixels unprojected with its true depth and K, in camera i's frame.
    - pts_j: view j's pixels unprojected in camera j's frame, then moved into camera i's frame.
      With `static_bias` on (the default), the move is the relative pose a static-world method
      would estimate: a confidence-weighted similarity (or rigid, `bias_fit`) fit over all 3-D
      correspondences of the pair in both directions, moving pixels included (a pixel of view i
      corresponds to the same surface point at time j, carried by its object's rigid motion, and
      vice versa). In a static scene this is the true relative pose; with moving objects it is
      pulled towards them, as DUSt3R-family networks are. With `static_bias` off the true relative
      pose is used (clean variant).
    - depth noise: every point is scaled along its ray by (1 + n), n = `depth_noise` * white
      noise + `smooth_noise` * a spatially smooth random field, drawn independently per pair and view.
    - confidence: 1 + (conf_max - 1) * exp(-n^2 / (2 s^2)), s the total noise std (conf_max where
      noise is off), so noisier pixels weigh less, as a network's confidence would.
    - both pointmaps of the pair are multiplied by one random scale, log-uniform in
      [1/scale_range, scale_range].
    Deterministic: pair (i, j) draws from a generator seeded by (seed, scene key, i, j), the scene
    key a CRC-32 of the scene's cameras and depth (`scene_key`), so every scene of a data set gets
    its own noise fields, confidences and pair scales.
    """

    def __init__(
        self,
        scene,
        depth_noise: float = 0.02,
        smooth_noise: float = 0.03,
        smooth_cells: int = 4,
        scale_range: float = 2.0,
        conf_max: float = 10.0,
        static_bias: bool = True,
        bias_fit: str = "similarity",
        seed: int = 0,
    ):
        if scene.depth is None:
            raise UserError("ground-truth pointmaps need the scene's depth; regenerate the scene "
                            "with a preset that renders depth")
        if bias_fit not in ("similarity", "rigid"):
            raise UserError(f"bias_fit must be 'similarity' or 'rigid', got {bias_fit!r}")
        if static_bias and (scene.segmentation is None or scene.object_to_world is None):
            raise UserError(
                "the static-world bias needs the scene's segmentation and object poses; use a "
                "scene that has them or set static_bias=false (clean pointmaps)"
            )
        self.scene = scene
        self.depth_noise = float(depth_noise)
        self.smooth_noise = float(smooth_noise)
        self.smooth_cells = int(smooth_cells)
        self.scale_range = float(scale_range)
        self.conf_max = float(conf_max)
        self.static_bias = bool(static_bias)
        self.bias_fit = bias_fit
        self.seed = int(seed)
        self.scene_key = scene_key(scene)

    @classmethod
    def from_config(cls, scene, cfg) -> "GroundTruthPointmaps":
        """Build from the `gt_pointmaps` section of a c4d config."""
        return cls(scene, **{k: cfg[k] for k in (
            "depth_noise", "smooth_noise", "smooth_cells", "scale_range", "conf_max",
            "static_bias", "bias_fit", "seed")})

    # -- geometry of the scene
    def _camera_points(self, t: int) -> np.ndarray:
        """(H,W,3) float64: frame t's pixels in its own camera frame."""
        return unproject_depth_map(self.scene.depth[t], self.scene.intrinsics[t], np.eye(4))

    def correspondences(self, i: int, j: int) -> tuple[np.ndarray, np.ndarray]:
        """All 3-D correspondences of pair (i, j): the surface points seen by either view, at time
        j in camera j's frame (M,3) and at time i in camera i's frame (M,3), M = 2 H W."""
        to_i = invert_pose(self.scene.cam_to_world[i].astype(np.float64))
        to_j = invert_pose(self.scene.cam_to_world[j].astype(np.float64))
        at_i, at_j = scene_point_motion(self.scene, i, j)  # view i's pixels, world, times i and j
        bt_j, bt_i = scene_point_motion(self.scene, j, i)  # view j's pixels, world, times j and i
        src = transform_points(to_j, np.concatenate([at_j, bt_j]).reshape(-1, 3))
        dst = transform_points(to_i, np.concatenate([at_i, bt_i]).reshape(-1, 3))
        return src, dst

    def relative_pose(self, i: int, j: int) -> np.ndarray:
        """(4,4) similarity taking camera-j-frame points into camera i's frame, as used for pts_j."""
        sc = self.scene
        true = invert_pose(sc.cam_to_world[i].astype(np.float64)) @ sc.cam_to_world[j]
        if not self.static_bias:
            return true
        src, dst = self.correspondences(i, j)
        weights = np.full(src.shape[0], self.conf_max)
        scale, rot, trans = weighted_procrustes(
            torch.from_numpy(src)[None], torch.from_numpy(dst)[None], torch.from_numpy(weights)[None],
            with_scale=self.bias_fit == "similarity",
        )
        sim = np.eye(4)
        sim[:3, :3] = scale[0].item() * rot[0].numpy()
        sim[:3, 3] = trans[0].numpy()
        return sim

    def _noisy(self, rng: np.random.Generator, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Scale points (H,W,3) along their rays by (1 + n); returns points and confidence (H,W)."""
        h, w = points.shape[:2]
        noise = np.zeros((h, w))
        if self.depth_noise > 0:
            noise += self.depth_noise * rng.standard_normal((h, w))
        if self.smooth_noise > 0:
            noise += self.smooth_noise * _smooth_field(rng, h, w, self.smooth_cells)
        total = float(np.hypot(self.depth_noise, self.smooth_noise))
        conf = 1.0 + (self.conf_max - 1.0) * (np.exp(-0.5 * (noise / total) ** 2) if total > 0 else 1.0)
        return points * (1.0 + noise)[..., None], np.broadcast_to(conf, (h, w))

    def pointmaps(self, frames: np.ndarray, edges: np.ndarray) -> PairwisePointmaps:
        """frames uint8 (T,H,W,3) must be the scene's frames (same T, H, W); edges int (E,2)."""
        sc = self.scene
        if tuple(frames.shape[:3]) != tuple(sc.depth.shape):
            raise UserError(
                f"ground-truth pointmaps: the video has shape {tuple(frames.shape[:3])} (T,H,W) "
                f"but the scene's depth has {tuple(sc.depth.shape)}; use the scene's own frames"
            )
        edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
        h, w = sc.depth.shape[1:]
        out = {k: np.empty((len(edges), h, w, 3), np.float32) for k in ("pts_i", "pts_j")}
        out |= {k: np.empty((len(edges), h, w), np.float32) for k in ("conf_i", "conf_j")}
        for e, (i, j) in enumerate(edges):
            rng = np.random.default_rng([self.seed, self.scene_key, int(i), int(j)])
            pts_i, conf_i = self._noisy(rng, self._camera_points(i))
            pts_j, conf_j = self._noisy(rng, self._camera_points(j))
            pts_j = transform_points(self.relative_pose(i, j), pts_j)
            scale = np.exp(rng.uniform(-1.0, 1.0) * np.log(self.scale_range))
            out["pts_i"][e], out["conf_i"][e] = sanitize(scale * pts_i, conf_i)
            out["pts_j"][e], out["conf_j"][e] = sanitize(scale * pts_j, conf_j)
        result = PairwisePointmaps(edges=edges, **out)
        result.validate(sc.num_frames, (h, w))
        return result


# ----------------------------------------------------------------------------- tracks and motion masks


def oracle_tracks(scene: Scene) -> TrackResult:
    """The scene's ground-truth tracks and mobility labels as a tracker result (an oracle DynPT)."""
    if scene.moving is None:
        raise UserError("the scene has no mobility labels; generate it with a preset that labels motion")
    n = np.arange(scene.num_tracks)
    clip = scene.tracks_time_major()  # (T,N,...) views
    return TrackResult(
        tracks=clip["tracks"].astype(np.float32),
        visible=~clip["occluded"],
        confidence=np.ones(clip["occluded"].shape, np.float32),
        moving=clip["moving"].astype(np.float32),
        queries=np.stack([scene.query_frame, *scene.tracks[n, scene.query_frame].T], -1).astype(np.float32),
    )


def ground_truth_motion_masks(scene: Scene, hw: tuple[int, int] | None = None) -> np.ndarray:
    """bool (T,h,w): pixels whose surface point moved more than the scene's mobility threshold
    in the world since the previous frame (frame 0: until frame 1), the per-pixel version of the
    tracks' `moving` label. `hw` resamples to (h, w) (default: scene size).
    """
    if scene.depth is None or scene.segmentation is None or scene.object_to_world is None:
        raise UserError("ground-truth motion masks need the scene's depth, segmentation and object poses")
    threshold = float(scene.meta.get("mobility_threshold", 0.01))
    hw = hw or scene.image_size
    masks = np.zeros((scene.num_frames, *hw), bool)
    for t in range(scene.num_frames):
        other = t - 1 if t > 0 else min(1, scene.num_frames - 1)
        points_t, points_other = scene_point_motion(scene, t, other, hw)
        masks[t] = np.linalg.norm(points_t - points_other, axis=-1) > threshold
    return masks
