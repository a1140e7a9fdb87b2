"""Pairwise pointmaps: the interface every pointmap source implements, and the ground-truth source.

A pointmap source looks at two frames (i, j) of a video and returns, for every pixel of both, a 3-D
point expressed in view i's camera frame (OpenCV axes), up to an unknown per-pair scale, with a
confidence (DUSt3R convention: raw confidence >= 1, the optimiser weights by log(conf)).

Sources:
- `GroundTruthPointmaps` (here): from a datagen `Scene`, with a random per-pair scale, depth noise,
  a confidence map, and the *static-world bias* of DUSt3R-family networks (see its docstring).
- the DUSt3R-family network (`c4d_pipeline.dust3r_source`, helper c4d-net).
"""

from __future__ import annotations

import logging
import zlib
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
import torch
import torch.nn.functional as F

from c4d_core import geometry
from c4d_core.errors import UserError
from c4d_pipeline.procrustes import weighted_procrustes
from c4d_pipeline.flow import scene_point_motion

log = logging.getLogger(__name__)


@dataclass
class PairwisePointmaps:
    """Pointmaps of E directed image pairs, all at the same H x W.

    edges:  int64 (E,2) frame indices (i, j) of each pair
    pts_i:  float32 (E,H,W,3) view i's pixels as 3-D points in view i's camera frame
    pts_j:  float32 (E,H,W,3) view j's pixels as 3-D points in view i's camera frame
    conf_i: float32 (E,H,W) confidence of pts_i, >= 1 (DUSt3R raw confidence)
    conf_j: float32 (E,H,W) confidence of pts_j, >= 1
    The scale of each pair is arbitrary (the optimiser estimates one similarity per edge).
    """

    edges: np.ndarray
    pts_i: np.ndarray
    pts_j: np.ndarray
    conf_i: np.ndarray
    conf_j: np.ndarray

    @property
    def num_edges(self) -> int:
        return int(self.edges.shape[0])

    @property
    def image_size(self) -> tuple[int, int]:
        """(H, W)."""
        return int(self.pts_i.shape[1]), int(self.pts_i.shape[2])

    def validate(self, num_frames: int, image_size: tuple[int, int]) -> None:
        """Raise `UserError` unless shapes agree with a video of `num_frames` frames of `image_size`
        (H, W) and every value is finite. NaN/inf points must be given zero weight by the source,
        not passed on: replace them by any finite value and set their confidence to 1."""
        e = self.num_edges
        h, w = image_size
        expected = {
            "edges": (e, 2), "pts_i": (e, h, w, 3), "pts_j": (e, h, w, 3),
            "conf_i": (e, h, w), "conf_j": (e, h, w),
        }
        for name, shape in expected.items():
            got = tuple(getattr(self, name).shape)
            if got != shape:
                raise UserError(
                    f"pairwise pointmaps: `{name}` has shape {got}, expected {shape} for {e} pairs "
                    f"of {h}x{w} frames; give the pointmap source the same frames as the rest of "
                    "the pipeline"
                )
        if e and (self.edges.min() < 0 or self.edges.max() >= num_frames):
            raise UserError(
                f"pairwise pointmaps refer to frames outside 0..{num_frames - 1}; the pointmap "
                "source and the video disagree on the number of frames"
            )
        for name in ("pts_i", "pts_j", "conf_i", "conf_j"):
            if not np.isfinite(getattr(self, name)).all():
                raise UserError(
                    f"pairwise pointmaps: `{name}` contains NaN or inf; the pointmap source must "
                    "mark invalid pixels with confidence 1 and a finite point instead"
                )
        if (self.conf_i < 1).any() or (self.conf_j < 1).any():
            raise UserError("pairwise pointmaps: confidences must be >= 1 (DUSt3R convention)")

    def statistics(self) -> str:
        """One phrase on the outputs that make an optimisation fail: the share of points behind
        their camera (z <= 0; a trained DUSt3R-family network gives about none), the spread of
        depth over the pairs and the confidence range."""
        z = self.pts_i[..., 2]
        behind = float((z <= 0).mean())
        median_z = np.median(z.reshape(self.num_edges, -1), axis=1)  # (E,) one scale per pair
        conf = np.concatenate([self.conf_i.ravel(), self.conf_j.ravel()])
        return (f"{100 * behind:.0f} % of its points lie behind the camera (z <= 0), the pairs' "
                f"median depth spans {median_z.min():.3g} to {median_z.max():.3g}, confidence "
                f"{conf.min():.2f} to {conf.max():.2f} (median {np.median(conf):.2f})")


@runtime_checkable
class PointmapSource(Protocol):
    """Anything that turns image pairs into pairwise pointmaps."""

    def pointmaps(self, frames: np.ndarray, edges: np.ndarray) -> PairwisePointmaps:
        """frames: uint8 (T,H,W,3); edges: int (E,2) pairs (i, j). Returns pointmaps at (H,W)."""
        ...


def sanitize(points: np.ndarray, conf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Replace non-finite points by 0 with confidence 1, and non-finite or < 1 confidences by 1.

    points float (...,3), conf float (...). Returns float32 copies. Sources call this so that a NaN
    in the input becomes an ignored pixel, not a crash.
    """
    bad = ~np.isfinite(points).all(axis=-1) | ~np.isfinite(conf)
    points = np.where(bad[..., None], 0.0, points).astype(np.float32)
    conf = np.where(bad, 1.0, np.maximum(np.nan_to_num(conf, nan=1.0), 1.0)).astype(np.float32)
    if bad.any():
        log.warning("pointmaps: %d non-finite pixels ignored (confidence set to 1)", int(bad.sum()))
    return points, conf


# ----------------------------------------------------------------------------- ground truth


def _smooth_field(rng: np.random.Generator, height: int, width: int, cells: int) -> np.ndarray:
    """A zero-mean, unit-std random field varying smoothly over about `cells` cells per side."""
    coarse = torch.from_numpy(rng.standard_normal((1, 1, cells + 1, cells + 1)).astype(np.float32))
    field = F.interpolate(coarse, size=(height, width), mode="bicubic", align_corners=True)[0, 0]
    field = field.numpy()
    return (field - field.mean()) / max(float(field.std()), 1e-6)


def scene_key(scene) -> int:
    """CRC-32 of a scene's cameras (cam_to_world, intrinsics) and depth: a seed component that is
    equal for the same scene however it was loaded and differs between scenes."""
    key = 0
    for array in (scene.cam_to_world, scene.intrinsics, scene.depth):
        key = zlib.crc32(np.ascontiguousarray(array, np.float32).tobytes(), key)
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
        return geometry.unproject_depth_map(self.scene.depth[t], self.scene.intrinsics[t], np.eye(4))

    def correspondences(self, i: int, j: int) -> tuple[np.ndarray, np.ndarray]:
        """All 3-D correspondences of pair (i, j): the surface points seen by either view, at time
        j in camera j's frame (M,3) and at time i in camera i's frame (M,3), M = 2 H W."""
        to_i = geometry.invert_pose(self.scene.cam_to_world[i].astype(np.float64))
        to_j = geometry.invert_pose(self.scene.cam_to_world[j].astype(np.float64))
        at_i, at_j = scene_point_motion(self.scene, i, j)  # view i's pixels, world, times i and j
        bt_j, bt_i = scene_point_motion(self.scene, j, i)  # view j's pixels, world, times j and i
        src = geometry.transform_points(to_j, np.concatenate([at_j, bt_j]).reshape(-1, 3))
        dst = geometry.transform_points(to_i, np.concatenate([at_i, bt_i]).reshape(-1, 3))
        return src, dst

    def relative_pose(self, i: int, j: int) -> np.ndarray:
        """(4,4) similarity taking camera-j-frame points into camera i's frame, as used for pts_j."""
        sc = self.scene
        true = geometry.invert_pose(sc.cam_to_world[i].astype(np.float64)) @ sc.cam_to_world[j]
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
            pts_j = geometry.transform_points(self.relative_pose(i, j), pts_j)
            scale = np.exp(rng.uniform(-1.0, 1.0) * np.log(self.scale_range))
            out["pts_i"][e], out["conf_i"][e] = sanitize(scale * pts_i, conf_i)
            out["pts_j"][e], out["conf_j"][e] = sanitize(scale * pts_j, conf_j)
        result = PairwisePointmaps(edges=edges, **out)
        result.validate(sc.num_frames, (h, w))
        return result
