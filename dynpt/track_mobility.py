"""A track's "moving" probability from its epipolar geometry over time, fused with the head's.

D-ACC's label is geometric: a point moves at frame t when its world point moved since frame t-1.
A static point's track stays on the epipolar lines the camera's motion gives; a moving point's
leaves them. Frame by frame this cue is as noisy as the tracks (a tracker off by 1 px hides a
point moving 1 px a frame), so here it is pooled over time, as trajectory-level motion
segmentation does (ParticleSFM): the points of a moving object keep leaving the epipolar lines.

For a video's tracks (T,N,2):
  1. per frame pair (a, a + offset): the fundamental matrix of all tracks visible in both, by
     LMedS (`c4d_core.epipolar`, as C4D's masks fit it), and each track's Sampson distance to it
     in units of the pair's robust residual sigma (the noise of the static tracks, so the cue
     does not depend on the frame size);
  2. per frame t: the `quantile` of a track's distances over the pairs that lie within `window`
     frames of t (both ends visible), g (sigmas), and the mean of the head's logits over the
     frames within `window` of t where the track is visible, h;
  3. the fused logit  head_weight * h + log(g / residual_sigmas): with an undecided head (h = 0)
     a point is called moving when g > residual_sigmas.
Where a track has no visible pair within the window (or no matrix was found, e.g. fewer than 8
tracks), the frame keeps the head's own probability. Frames the tracker did not predict stay NaN.

The defaults are chosen for the paper's D-ACC protocol (24 frames, about a quarter of the
point-frames moving) on held-out generated scenes that no reported figure uses; where fewer
points move, a higher `residual_sigmas` keeps static points static (the demo scores its 12-frame
64x64 clips with 4; docs/results/demo_mobility.md, "Pooling the epipolar cue over time"). On
tracks refined by `dynpt.refine` and read only where it confirmed them, pairs of consecutive
frames do better (offset 1, residual_sigmas 0.55: the demo's paper-protocol setting).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from c4d_core.config import defaults_from
from c4d_core.epipolar import fundamental_lmeds, sampson_distance


@dataclass(frozen=True)
@defaults_from("dynpt", "eval.epipolar")
class EpipolarMobility:
    """Settings of the fused mobility: the keys of the dynpt configs' `eval.epipolar`, where each
    is explained; the defaults are that file's (the schema's)."""

    offset: int  # frames between the two ends of a pair
    window: int  # frames on each side of t whose pairs and head logits are pooled
    quantile: float  # percent, of a track's distances over the pooled pairs
    head_weight: float  # weight of the head's mean logit (0: geometry alone)
    residual_sigmas: float  # distance (pair sigmas) at which geometry alone is undecided


def pair_distances(tracks: np.ndarray, visible: np.ndarray, offset: int, seed: int = 0) -> np.ndarray:
    """float (T,N): row a holds each track's Sampson distance between frames a and a + offset to
    the fundamental matrix of all tracks visible in both, in units of that fit's robust sigma;
    NaN where the track is not visible in both, where no matrix is found, and for a > T - 1 - offset.
    tracks (T,N,2) px, visible bool (T,N)."""
    T, N = visible.shape
    distance = np.full((T, N), np.nan)
    for a in range(T - offset):
        both = visible[a] & visible[a + offset]  # (N,)
        fit = fundamental_lmeds(tracks[a, both], tracks[a + offset, both], seed + a)
        if fit is None:
            continue
        fundamental, sigma = fit
        row = sampson_distance(fundamental, tracks[a], tracks[a + offset]) / max(sigma, 1e-6)
        distance[a] = np.where(both, row, np.nan)
    return distance


def _window_nan_stat(values: np.ndarray, window: int, reach: int, stat) -> np.ndarray:
    """(T,N): `stat` over rows max(0, t - window) .. min(T - 1, t + window - reach) of values
    (T,N) (row a spans frames a .. a + reach), NaN where all of them are NaN."""
    T = len(values)
    out = np.full(values.shape, np.nan)
    for t in range(T):
        rows = values[max(0, t - window): max(0, min(T - 1, t + window - reach) + 1)]
        seen = np.isfinite(rows).any(0)  # (N,)
        if seen.any():
            out[t, seen] = stat(rows[:, seen])
    return out


def nanpercentile_columns(values: np.ndarray, q: float) -> np.ndarray:
    """(N,): the `q`-th percentile of each column of values (R,N) over its non-NaN entries, to
    the bit as `np.nanpercentile(values, q, axis=0)` (its default linear method) gives it, NaN
    where a column has none; one sort of the whole array instead of numpy's per-column loop (a
    256x256 video's post-processing: 0.42 s instead of 0.74, docs/results/demo_mobility.md)."""
    ordered = np.sort(values, axis=0)  # NaN last
    count = (~np.isnan(values)).sum(0)  # (N,)
    index = (count - 1) * (np.float64(q) / 100)  # numpy's virtual index of the linear method
    below = np.clip(np.floor(index), 0, np.maximum(count - 1, 0)).astype(np.intp)
    above = np.minimum(below + 1, np.maximum(count - 1, 0))
    gamma = index - below
    a = np.take_along_axis(ordered, below[None], 0)[0]
    b = np.take_along_axis(ordered, above[None], 0)[0]
    diff = b - a
    result = np.where(gamma >= 0.5, b - diff * (1 - gamma), a + diff * gamma)  # numpy's _lerp
    return np.where(count > 0, result, np.nan)


def fuse_mobility(tracks: np.ndarray, visible: np.ndarray, moving: np.ndarray,
                  settings: EpipolarMobility, seed: int = 0) -> np.ndarray:
    """float32 (T,N) probability that each point moves, from tracks (T,N,2) px, visible bool
    (T,N) (the positions it reads: the visible ones, or after `dynpt.refine` the confirmed ones)
    and the head's probability moving (T,N) (NaN where not predicted); see the module."""
    tracks = tracks.astype(np.float64)
    p = np.clip(moving, 1e-4, 1 - 1e-4)
    head = np.log(p / (1 - p))  # (T,N) logits
    distance = pair_distances(tracks, visible, settings.offset, seed)  # (T,N)
    with np.errstate(invalid="ignore", divide="ignore"):
        g = _window_nan_stat(distance, settings.window, settings.offset,
                             lambda r: nanpercentile_columns(r, settings.quantile))
        h = _window_nan_stat(np.where(visible, head, np.nan), settings.window, 0,
                             lambda r: np.nanmean(r, axis=0))
        geometry = np.log(np.maximum(g, 1e-6) / settings.residual_sigmas)
    fused = np.where(np.isfinite(g), np.nan_to_num(settings.head_weight * h) + geometry, head)
    return np.where(np.isfinite(moving), 1 / (1 + np.exp(-fused)), np.nan).astype(np.float32)

