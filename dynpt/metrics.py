"""Point-tracking metrics: the TAP-Vid benchmark metrics and DynPT's dynamic accuracy (D-ACC).

`tapvid_metrics` follows the public TAP-Vid evaluator's definitions exactly (see
docs/TRAINING.md and the TAP-Vid paper): per video, pooled over (query, frame) pairs; the query
frame never counts; 'first' counts only frames after it, 'strided' all other frames; a point is
within delta pixels only if its distance is strictly below delta; no NaN guarding (0/0 is NaN).
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

THRESHOLDS_PX = (1, 2, 4, 8, 16)
QUERY_MODES = ("first", "strided")


def evaluation_mask(query_frames: np.ndarray, num_frames: int, query_mode: str) -> np.ndarray:
    """Which (query, frame) pairs are scored: bool (..., T) from integer query frames (...)."""
    if query_mode not in QUERY_MODES:
        raise ValueError(f"query_mode must be one of {QUERY_MODES}, got {query_mode!r}")
    frames = np.arange(num_frames)  # (T,)
    q = query_frames[..., None]  # (..., 1)
    return frames > q if query_mode == "first" else frames != q  # (..., T)


def tapvid_metrics(
    query_points: np.ndarray,
    gt_occluded: np.ndarray,
    gt_tracks: np.ndarray,
    pred_occluded: np.ndarray,
    pred_tracks: np.ndarray,
    query_mode: str,
    get_trackwise_metrics: bool = False,
) -> Mapping[str, np.ndarray]:
    """TAP-Vid metrics per video (or per track).

    query_points (b,n,3) as (t, y, x) -- only t is used, rounded half-to-even; gt_occluded and
    pred_occluded (b,n,T) bool (True = occluded; 0/1 floats work too); gt_tracks and pred_tracks
    (b,n,T,2) as (x, y) in pixels of the 256x256 raster. Returns 13 arrays of shape (b,) -- or
    (b,n) with `get_trackwise_metrics` -- `occlusion_accuracy`, `pts_within_{1,2,4,8,16}`,
    `jaccard_{1,2,4,8,16}`, `average_jaccard`, `average_pts_within_thresh`, in [0, 1].
    """
    query_frames = np.round(np.asarray(query_points)[..., 0]).astype(np.int32)  # (b,n)
    gt_occ = np.asarray(gt_occluded).astype(bool)  # (b,n,T)
    pred_occ = np.asarray(pred_occluded).astype(bool)  # (b,n,T)
    evaluated = evaluation_mask(query_frames, gt_occ.shape[-1], query_mode)  # (b,n,T)
    axes = (2,) if get_trackwise_metrics else (1, 2)

    def count(mask: np.ndarray) -> np.ndarray:
        return np.sum(mask & evaluated, axis=axes)

    gt_vis, pred_vis = ~gt_occ, ~pred_occ
    out: dict[str, np.ndarray] = {
        "occlusion_accuracy": count(gt_occ == pred_occ) / count(np.ones_like(gt_occ))
    }
    sq_dist = np.sum((np.asarray(pred_tracks) - np.asarray(gt_tracks)) ** 2, axis=-1)  # (b,n,T)
    within_all, jaccard_all = [], []
    for delta in THRESHOLDS_PX:
        within = sq_dist < delta**2  # strict: exactly delta px away is outside
        true_pos = count(within & gt_vis & pred_vis)
        gt_pos = count(gt_vis)
        false_pos = count((gt_occ | ~within) & pred_vis)
        out[f"pts_within_{delta}"] = count(within & gt_vis) / gt_pos
        out[f"jaccard_{delta}"] = true_pos / (gt_pos + false_pos)
        within_all.append(out[f"pts_within_{delta}"])
        jaccard_all.append(out[f"jaccard_{delta}"])
    out["average_jaccard"] = np.mean(np.stack(jaccard_all, axis=1), axis=1)
    out["average_pts_within_thresh"] = np.mean(np.stack(within_all, axis=1), axis=1)
    return out


def dynamic_accuracy(
    pred_moving: np.ndarray, gt_moving: np.ndarray, valid: np.ndarray | None = None
) -> float:
    """D-ACC = (TP + TN) / (all counted) over the entries where `valid` is True.

    pred_moving and gt_moving: bool arrays of one shape (e.g. (T,N)); valid: bool of the same
    shape, or None for all. Returns NaN when nothing is counted.
    """
    pred = np.asarray(pred_moving).astype(bool)
    gt = np.asarray(gt_moving).astype(bool)
    if pred.shape != gt.shape:
        raise ValueError(f"pred_moving {pred.shape} and gt_moving {gt.shape} differ in shape")
    counted = np.ones_like(gt) if valid is None else np.asarray(valid).astype(bool)
    total = int(counted.sum())
    return float(np.sum((pred == gt) & counted) / total) if total else float("nan")


def _scores_and_labels(scores, labels) -> tuple[np.ndarray, np.ndarray]:
    scores, labels = np.asarray(scores, dtype=np.float64).ravel(), np.asarray(labels).astype(bool).ravel()
    if scores.shape != labels.shape:
        raise ValueError(f"scores {scores.shape} and labels {labels.shape} differ in size")
    if not labels.any() or labels.all():
        raise ValueError("ranking metrics need both positive and negative labels")
    return scores, labels


def average_precision(scores, labels) -> float:
    """Area under the precision-recall curve of `scores` ranking `labels` (both any shape, one size):
    sum over distinct score thresholds of (recall gained) x (precision there). Tied scores count
    as one threshold. 1.0 for a perfect ranking; about the positive rate for a random one."""
    scores, labels = _scores_and_labels(scores, labels)
    order = np.argsort(-scores, kind="stable")
    scores, labels = scores[order], labels[order]
    last_of_tie = np.r_[scores[1:] != scores[:-1], True]  # (n,) end of each group of equal scores
    true_pos = np.cumsum(labels)[last_of_tie]
    precision = true_pos / (np.flatnonzero(last_of_tie) + 1)
    recall_gained = np.diff(np.r_[0, true_pos]) / labels.sum()
    return float(np.sum(recall_gained * precision))


def roc_auc(scores, labels) -> float:
    """Area under the ROC curve: the probability that a random positive scores above a random
    negative (ties count one half), from the Mann-Whitney rank sum."""
    from scipy.stats import rankdata

    scores, labels = _scores_and_labels(scores, labels)
    num_pos, num_neg = labels.sum(), (~labels).sum()
    rank_sum = rankdata(scores)[labels].sum()  # average ranks for ties
    return float((rank_sum - num_pos * (num_pos + 1) / 2) / (num_pos * num_neg))


def paired_bootstrap_interval(
    correct_a, total_a, correct_b, total_b, level: float = 0.95, num_samples: int = 2000,
    seed: int = 0,
) -> tuple[float, float]:
    """Percentile interval of the pooled accuracy difference A - B when videos are resampled.

    Inputs are per-video counts (V,): entries scored right and entries counted, for two methods on
    the same V videos. Each of `num_samples` draws picks V videos with replacement (the same ones
    for both methods) and computes sum(correct_a)/sum(total_a) - sum(correct_b)/sum(total_b);
    returns the (1-level)/2 and (1+level)/2 quantiles, as fractions. An interval that contains 0
    means the difference is within the video-to-video variation.
    """
    counts = [np.asarray(c, dtype=np.float64) for c in (correct_a, total_a, correct_b, total_b)]
    if len({c.shape for c in counts}) != 1 or counts[0].ndim != 1 or len(counts[0]) == 0:
        raise ValueError("per-video counts must be four 1-D arrays of one non-zero length")
    draws = np.random.default_rng(seed).integers(0, len(counts[0]), (num_samples, len(counts[0])))
    ca, ta, cb, tb = (c[draws].sum(axis=1) for c in counts)  # (num_samples,) each
    with np.errstate(invalid="ignore", divide="ignore"):
        diff = ca / ta - cb / tb
    low, high = np.nanquantile(diff, [(1 - level) / 2, (1 + level) / 2])
    return float(low), float(high)
