"""Pairwise pointmaps: the interface every pointmap source implements.

A pointmap source looks at two frames (i, j) of a video and returns, for every pixel of both, a 3-D
point expressed in view i's camera frame (OpenCV axes), up to an unknown per-pair scale, with a
confidence (DUSt3R convention: raw confidence >= 1, the optimiser weights by log(conf)).

Sources, built from a spec string by `c4d_pipeline.pointmap_sources.build_pointmaps`:
- 'gt': `c4d_pipeline.ground_truth.GroundTruthPointmaps`, from a datagen `Scene`, with a random
  per-pair scale, depth noise, a confidence map, and the *static-world bias* of DUSt3R-family
  networks (see its docstring);
- 'dust3r:PATH': `c4d_pipeline.dust3r_pointmaps.Dust3rPointmaps`, the DUSt3R-family network.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from c4d_core.errors import UserError

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
