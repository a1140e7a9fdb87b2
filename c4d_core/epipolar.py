"""Epipolar geometry of point correspondences between two frames: the fundamental matrix fitted
robustly (LMedS) and the Sampson distance of a correspondence to it.

Shared by C4D's motion masks (`c4d_pipeline.motion_mask`, correspondences from flow) and DynPT's
track-level mobility (`dynpt.track_mobility`, correspondences from tracks). Pixels follow
docs/FORMAT.md: (x, y), the centre of the top-left pixel at (0, 0).
"""

from __future__ import annotations

import cv2
import numpy as np


def sampson_distance(fundamental: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """First-order geometric distance (pixels) of correspondences x1 (...,2) <-> x2 (...,2) to F.

    d = |x2' F x1| / sqrt((F x1)_0^2 + (F x1)_1^2 + (F' x2)_0^2 + (F' x2)_1^2) (Hartley-Zisserman
    eq. 11.9, square root), with x' = (x, y, 1). Invariant to the scale of F.
    """
    h1 = np.concatenate([x1, np.ones_like(x1[..., :1])], -1)  # (...,3)
    h2 = np.concatenate([x2, np.ones_like(x2[..., :1])], -1)
    f_x1 = h1 @ fundamental.T  # (...,3) epipolar lines in image 2
    ft_x2 = h2 @ fundamental  # (...,3) epipolar lines in image 1
    algebraic = np.sum(h2 * f_x1, -1)
    gradient = np.sqrt(f_x1[..., 0] ** 2 + f_x1[..., 1] ** 2 + ft_x2[..., 0] ** 2 + ft_x2[..., 1] ** 2)
    return np.abs(algebraic) / np.maximum(gradient, 1e-12)


def fundamental_lmeds(x1: np.ndarray, x2: np.ndarray, seed: int) -> tuple[np.ndarray, float] | None:
    """(F (3,3), sigma) from correspondences (M,2) <-> (M,2) by LMedS, or None without a solution.

    As in Rousseeuw's LMedS, the minimal-sample solution is followed by a least-squares refit
    (normalised 8-point) on its inliers: residuals within 2.5 robust standard deviations
    sigma = 1.4826 (1 + 5 / (M - 7)) sqrt(median r^2). The refit matters on near-planar static
    sets (a floor), where many F fit the sampled points and only the off-plane points decide.
    sigma (pixels, of the final F's Sampson residuals) measures the flow's noise on these points.
    """
    if len(x1) < 8:
        return None
    x1, x2 = x1.astype(np.float64), x2.astype(np.float64)
    cv2.setRNGSeed(seed)
    fundamental, _ = cv2.findFundamentalMat(x1, x2, cv2.FM_LMEDS)
    if fundamental is None or fundamental.shape != (3, 3) or not np.isfinite(fundamental).all():
        return None

    def robust_sigma(f: np.ndarray) -> tuple[np.ndarray, float]:
        residual = sampson_distance(f, x1, x2)  # (M,) pixels
        return residual, 1.4826 * (1 + 5 / max(len(x1) - 7, 1)) * float(np.sqrt(np.median(residual**2)))

    residual, sigma = robust_sigma(fundamental)
    inliers = residual <= max(2.5 * sigma, 1e-6)
    if inliers.sum() >= 8:
        refit, _ = cv2.findFundamentalMat(x1[inliers], x2[inliers], cv2.FM_8POINT)
        if refit is not None and refit.shape == (3, 3) and np.isfinite(refit).all():
            fundamental = refit
            sigma = robust_sigma(fundamental)[1]
    return fundamental, sigma
