"""Reconstruction metrics: camera pose (ATE, RPE), video depth (Abs Rel, RMSE, delta < 1.25), masks.

Conventions follow the evaluation code of MonST3R that C4D reports against:
- Poses: camera-to-world (T,4,4). The predicted trajectory is first aligned to the ground truth by
  the Sim(3) Umeyama fit of the camera centres (evo's `align=True, correct_scale=True`): aligned
  pose = S @ pose with S = [s R | t], i.e. rotation R R_p, centre s R c_p + t.
  ATE = RMSE of the aligned centre errors; RPE between frames t and t + 1 (all such pairs):
  E = (G_t^-1 G_t+1)^-1 (A_t^-1 A_t+1), RPE trans = RMSE of |trans(E)| and RPE rot = RMSE of the
  rotation angle of E in degrees. ATE and RPE trans are in ground-truth units. These equal evo's
  APE / RPE (`evo.core.metrics`, delta 1 frame, RMSE) after `align(correct_scale=True)`; tested
  against evo in tests/test_c4d_eval_metrics.py. Both trajectories' rotations are first projected
  onto SO(3) in float64 (poses saved in float32 are orthonormal only to ~1e-7, and
  arccos((tr R - 1) / 2) of such a matrix has a floor of ~0.01 degrees near the identity), and the
  angle is atan2(|vee(R - R^T)| / 2, (tr R - 1) / 2), accurate at every angle.
- Depth: one alignment per sequence, fitted on all valid pixels of all frames at once (valid:
  finite prediction, finite ground truth > 0 and below `max_depth` if given), in the L1 sense
  (MonST3R's least-absolute-deviation fit, here solved exactly rather than by Adam):
  'scale_shift' minimises sum |s p + t - g|, 'scale' minimises sum |s p - g|. The aligned prediction is
  clamped to >= 1e-5, then Abs Rel = mean |p - g| / g, RMSE = sqrt(mean (p - g)^2),
  delta < 1.25 = fraction with max(p / g, g / p) < 1.25.
- Masks: IoU of dynamic pixels pooled over all frames of the sequence, and the mean of per-frame
  IoUs (a frame where both masks are empty counts as 1).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.optimize import minimize_scalar

from c4d_core.errors import UserError
from c4d_core.geometry import invert_pose
from c4d_pipeline.procrustes import weighted_procrustes

DEPTH_ALIGNMENTS = ("scale_shift", "scale")


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """(s, R (3,3), t (3,)) minimising sum ||dst - (s R src + t)||^2 for points (N,3) <-> (N,3)."""
    s, rot, trans = weighted_procrustes(
        torch.from_numpy(np.asarray(src, np.float64))[None],
        torch.from_numpy(np.asarray(dst, np.float64))[None],
        torch.ones(1, len(src), dtype=torch.float64),
        with_scale,
    )
    return float(s[0]), rot[0].numpy(), trans[0].numpy()


def _check_poses(pred: np.ndarray, gt: np.ndarray) -> None:
    if pred.shape != gt.shape or pred.ndim != 3 or pred.shape[1:] != (4, 4):
        raise UserError(f"pose metrics need two (T,4,4) trajectories of equal length, got {pred.shape} and {gt.shape}")
    if pred.shape[0] < 2:
        raise UserError("pose metrics need at least 2 frames; reconstruct a longer video")
    if not (np.isfinite(pred).all() and np.isfinite(gt).all()):
        raise UserError("a trajectory contains NaN or infinite values; check the reconstruction's poses_tum.txt")


def orthonormalise(poses: np.ndarray) -> np.ndarray:
    """float64 copy of poses (...,4,4) whose rotation blocks are the nearest rotations (SVD polar
    factor, determinant +1) to the given ones."""
    poses = np.array(poses, dtype=np.float64)
    u, _, vt = np.linalg.svd(poses[..., :3, :3])
    signs = np.ones(u.shape[:-2] + (1, 3))  # (...,1,3): scales u's columns
    signs[..., 0, 2] = np.sign(np.linalg.det(u @ vt))  # -1 where the polar factor is a reflection
    poses[..., :3, :3] = (u * signs) @ vt
    return poses


def align_trajectory(pred: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, float]:
    """Predicted camera-to-world poses (T,4,4) Sim(3)-aligned to gt (T,4,4); returns (aligned, s),
    aligned in float64 with orthonormal rotations."""
    _check_poses(pred, gt)
    pred, gt = orthonormalise(pred), orthonormalise(gt)
    s, rot, trans = umeyama(pred[:, :3, 3], gt[:, :3, 3], with_scale=True)
    aligned = pred.copy()
    aligned[:, :3, :3] = rot @ pred[:, :3, :3]  # (T,3,3)
    aligned[:, :3, 3] = s * pred[:, :3, 3] @ rot.T + trans  # (T,3)
    return aligned, s


def rotation_angle_deg(rot: np.ndarray) -> np.ndarray:
    """Angle in degrees of rotations (...,3,3): atan2(sin, cos) with sin = |vee(R - R^T)| / 2 and
    cos = (tr R - 1) / 2 (no loss of precision near 0 or 180 degrees, unlike arccos alone)."""
    rot = np.asarray(rot, np.float64)
    axis = np.stack([rot[..., 2, 1] - rot[..., 1, 2], rot[..., 0, 2] - rot[..., 2, 0],
                     rot[..., 1, 0] - rot[..., 0, 1]], -1)  # (...,3) = 2 sin(angle) * unit axis
    cos = (np.trace(rot, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arctan2(np.linalg.norm(axis, axis=-1) / 2.0, cos))


def pose_metrics(pred: np.ndarray, gt: np.ndarray) -> dict[str, float]:
    """ATE, RPE trans (ground-truth units), RPE rot (degrees) after Sim(3) alignment, and the scale."""
    aligned, scale = align_trajectory(pred, gt)
    gt = orthonormalise(gt)
    ate = np.sqrt(np.mean(np.sum((aligned[:, :3, 3] - gt[:, :3, 3]) ** 2, -1)))
    rel_pred = invert_pose(aligned[:-1]) @ aligned[1:]  # (T-1,4,4) motion t -> t+1
    rel_gt = invert_pose(gt[:-1]) @ gt[1:]
    error = invert_pose(rel_gt) @ rel_pred  # (T-1,4,4)
    rpe_trans = np.sqrt(np.mean(np.sum(error[:, :3, 3] ** 2, -1)))
    rpe_rot = np.sqrt(np.mean(rotation_angle_deg(error[:, :3, :3]) ** 2))
    return {"ate": float(ate), "rpe_trans": float(rpe_trans), "rpe_rot": float(rpe_rot), "sim3_scale": float(scale)}


def _weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    order = np.argsort(values)
    cumulative = np.cumsum(weights[order])
    return float(values[order][np.searchsorted(cumulative, 0.5 * cumulative[-1])])


def fit_depth_alignment(pred: np.ndarray, gt: np.ndarray, mode: str = "scale_shift") -> tuple[float, float]:
    """(scale, shift) minimising sum |scale * pred + shift - gt| over valid pixels (1-D arrays).

    'scale' fixes shift = 0 and is exact (a weighted median). 'scale_shift': for a given scale
    the best shift is median(gt - scale * pred), and the remaining L1 cost is convex in the
    scale, so Brent's bounded search over log-scale (1e-3 to 1e3 times the median ratio) finds it.
    """
    if mode not in DEPTH_ALIGNMENTS:
        raise UserError(f"unknown depth alignment {mode!r}; choose one of {', '.join(DEPTH_ALIGNMENTS)}")
    pred, gt = pred.astype(np.float64), gt.astype(np.float64)
    if mode == "scale":
        positive = pred > 0
        return _weighted_median(gt[positive] / pred[positive], pred[positive]), 0.0

    def cost(log_scale: float) -> float:
        residual = gt - np.exp(log_scale) * pred
        return float(np.abs(residual - np.median(residual)).sum())

    start = np.log(np.median(gt) / max(np.median(pred), 1e-12))
    best = minimize_scalar(cost, bounds=(start - 7.0, start + 7.0), method="bounded", options={"xatol": 1e-10})
    scale = float(np.exp(best.x))
    return scale, float(np.median(gt - scale * pred))


def depth_metrics(pred: np.ndarray, gt: np.ndarray, mode: str = "scale_shift", max_depth: float | None = None) -> dict[str, float]:
    """Abs Rel, RMSE (ground-truth units), delta < 1.25 of a depth video (T,H,W) after one
    per-sequence alignment (`mode` 'scale_shift' or 'scale'); also the fitted scale and shift."""
    if pred.shape != gt.shape:
        raise UserError(f"depth metrics need equal shapes, got prediction {pred.shape} and ground truth {gt.shape}; resize first")
    valid = np.isfinite(pred) & np.isfinite(gt) & (gt > 0)
    if valid.sum() < 2:
        which = "reconstruction's" if np.isfinite(gt).any() and (gt > 0).any() else "ground truth's"
        raise UserError(f"fewer than 2 depth pixels where both are valid (finite, ground truth > 0); "
                        f"the {which} depth maps hold almost none")
    if max_depth is not None:
        kept = valid & (gt < max_depth)
        if kept.sum() < 2:
            raise UserError(f"--max-depth {max_depth:g} leaves fewer than 2 depth pixels: the ground "
                            f"truth's depth is {gt[valid].min():.3g} .. {gt[valid].max():.3g}; raise "
                            "it or leave it out")
        valid = kept
    p, g = pred[valid].astype(np.float64), gt[valid].astype(np.float64)
    scale, shift = fit_depth_alignment(p, g, mode)
    p = np.maximum(scale * p + shift, 1e-5)
    return {
        "abs_rel": float(np.mean(np.abs(p - g) / g)),
        "rmse": float(np.sqrt(np.mean((p - g) ** 2))),
        "delta_1_25": float(np.mean(np.maximum(p / g, g / p) < 1.25)),
        "scale": scale,
        "shift": shift,
        "valid_pixels": int(valid.sum()),
    }


def mask_iou(pred: np.ndarray, gt: np.ndarray) -> dict[str, float]:
    """IoU of boolean motion masks (T,H,W): pooled over the sequence and mean over frames."""
    if pred.shape != gt.shape:
        raise UserError(f"mask IoU needs equal shapes, got {pred.shape} and {gt.shape}; resize first")
    pred, gt = pred.astype(bool), gt.astype(bool)
    inter = (pred & gt).reshape(len(pred), -1).sum(-1)  # (T,)
    union = (pred | gt).reshape(len(pred), -1).sum(-1)
    per_frame = np.where(union > 0, inter / np.maximum(union, 1), 1.0)
    pooled = inter.sum() / union.sum() if union.sum() > 0 else 1.0
    return {"iou": float(pooled), "iou_frame_mean": float(per_frame.mean())}
