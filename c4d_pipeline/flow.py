"""Optical flow behind one interface: OpenCV DIS (weight-free default), exact ground truth, RAFT.

Every estimator has one method:

    flow(frames, pairs) -> float32 (P,H,W,2)

`frames` is uint8 (T,H,W,3) RGB; `pairs` is a list of P (i, j) frame indices; entry p is the
(dx, dy) pixel displacement of the surface seen at each pixel of frame i to frame j (pixel
centres at integer coordinates, x the column), camera motion included, as in the contract.

`build_flow(spec, scene=None, device=None)` picks one from a string:
  'dis' or 'dis:PRESET'  OpenCV DIS, PRESET one of ultrafast | fast | medium (default medium)
  'gt'                    exact flow of a datagen `Scene` for ANY pair (i, j), from depth,
                          segmentation, camera and object poses (needs `scene=`)
  'raft:PATH'             RAFT weights at PATH (`c4d_pipeline.raft.RaftFlow`, imported lazily)
"""

from __future__ import annotations

from pathlib import Path
from typing import Protocol, Sequence

import cv2
import numpy as np

from c4d_core.errors import UserError
from c4d_core.geometry import invert_pose, pixel_grid, project, transform_points, unproject_depth_map
from c4d_pipeline.flow_inputs import Pair, check_flow_inputs
from datagen.scene import Scene

DIS_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}


class FlowEstimator(Protocol):
    def flow(self, frames: np.ndarray, pairs: Sequence[Pair]) -> np.ndarray:
        """frames uint8 (T,H,W,3), pairs P x (i, j) -> float32 (P,H,W,2) (dx, dy) from i to j."""
        ...


def build_flow(spec: str, scene: Scene | None = None, device=None) -> FlowEstimator:
    """The flow estimator named by `spec` ('dis[:PRESET]', 'gt', 'raft:PATH'); see the module doc.

    `scene` is required by 'gt' (its frames must be the frames later passed to `flow`, at any
    resolution); `device` is only used by 'raft'.
    """
    name, _, arg = spec.partition(":")
    if name == "dis":
        return DISFlow(arg or "medium")
    if name == "gt":
        if scene is None:
            raise UserError("flow 'gt' needs a datagen scene; use flow 'dis' for a plain video")
        return GroundTruthFlow(scene)
    if name == "raft":
        if not arg:
            raise UserError("flow 'raft' needs weights: write 'raft:PATH/TO/raft.pth'")
        if not Path(arg).is_file():
            raise UserError(f"RAFT weights {arg!r} do not exist; give the path of a local .pth file")
        from c4d_pipeline.raft import RaftFlow  # torch model: imported only when asked for

        return RaftFlow(arg, device)
    raise UserError(f"unknown flow {spec!r}; choose 'dis', 'dis:fast', 'gt' or 'raft:PATH'")


class DISFlow:
    """OpenCV's Dense Inverse Search flow on grey-level frames (no weights, CPU)."""

    def __init__(self, preset: str = "medium"):
        if preset not in DIS_PRESETS:
            raise UserError(f"unknown DIS preset {preset!r}; choose one of {', '.join(DIS_PRESETS)}")
        self.preset = preset

    def flow(self, frames: np.ndarray, pairs: Sequence[Pair]) -> np.ndarray:
        check_flow_inputs(frames, pairs)
        dis = cv2.DISOpticalFlow_create(DIS_PRESETS[self.preset])
        grey = [cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in frames]  # T x (H,W) uint8
        out = np.zeros((len(pairs), *frames.shape[1:3], 2), np.float32)  # (P,H,W,2)
        for p, (i, j) in enumerate(pairs):
            out[p] = dis.calc(grey[i], grey[j], None)
        return out


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
