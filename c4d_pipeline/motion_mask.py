"""Motion masks: which pixels move in the world (C4D sec. 3.2.2), and a flow-only baseline.

C4D's correspondence-guided mask, for every directed pair (t, t') of the scene graph:
  1. static points: tracker points visible at frame t whose mobility probability is below a
     threshold (DynPT's `moving`; the tracker's output already holds, for every frame, the
     estimate of the latest sliding window that covers it);
  2. their correspondences in frame t' through the optical flow t -> t' (bilinear sampling);
  3. a fundamental matrix from these correspondences by LMedS (cv2.findFundamentalMat), refit
     by least squares on the LMedS inliers; it describes the camera motion only;
  4. the Sampson distance (pixels) of every dense flow correspondence of frame t to it, and a
     threshold: pixels that break the epipolar constraint are dynamic. The threshold is
     `sampson_threshold_px`, raised to `noise_sigmas` robust standard deviations of the static
     points' own distances when the flow is noisier than that; pixels whose flow leaves frame t'
     are not judged (their flow is unreliable) unless `judge_out_of_view`; with
     `forward_backward_px` > 0 and the pair (t', t) in the graph, neither are pixels whose flow
     t -> t' and the flow t' -> t back from where it lands disagree by more than that many pixels
     (occlusions and flow failures: estimated flow, e.g. DIS, is wrong there, and a wrong flow
     breaks the epipolar constraint as a moving object does);
  5. the mask of frame t is the union over all pairs (t, t') of the graph (optionally only
     those with |t - t'| <= `max_pair_offset`, for flows that fail on distant frames); then, where `open_px` / `close_px` > 0, a morphological opening (specks of
     flow noise go) and closing (holes in objects fill) with squares of that side;
  6. where `temporal_neighbours` n > 0 or `guided_radius_px` > 0, a vote refines the masks
     (off by default, as the paper; `refine_masks`): frame t's score is the share of frames
     t - n .. t + n whose masks call a pixel dynamic, each brought to frame t by the flow
     t -> t' of the graph (frames without that pair do not vote); a colour guided filter (He,
     Sun and Tang, ECCV 2010) with frame t as its guide, radius `guided_radius_px`, smooths the
     score, so the mask's edges move to the frame's colour edges (an estimated flow such as DIS
     smooths motion across the objects' outlines: its masks spill onto the background there and
     stop short inside the objects); the mask is where the score is at least `min_vote`.
Fallbacks, listed in `MotionMasks.pair_info` and logged in one line per call (once per process
for the same pairs with the same static-point counts: two runs on one video, as `c4d demo`'s
C4D and GA only, compute the same masks):
  - fewer than `min_static_points` static points (or LMedS fails on them): the fundamental
    matrix is estimated by LMedS from a regular grid of ALL flow correspondences of the pair,
    which stays right while less than half of the frame moves;
  - the static points barely move (90 % of them by less than `still_camera_px`: the camera
    stands still and F is undefined): a pixel is dynamic where its flow exceeds the threshold;
  - if every estimate fails the pair contributes an empty mask (never an exception).

The flow-only baseline (MonST3R-style): per pair, the ego-flow (the flow camera motion alone
would cause) is compared with the optical flow; the error is min-max normalised per pair,
averaged over the pairs that start at a frame, and thresholded (0.35 in MonST3R). The ego-flows
are its geometry input, from either
  - `pairwise_ego_flow`: a pair's own pointmaps, camera j placed by PnP-RANSAC (MonST3R's route);
  - `ego_flow`: per-frame depth (H,W), K (3,3) and camera-to-world poses (4,4), e.g. an
    optimiser's output or the ground truth (an oracle).
The oracles (tracks from a scene's labels, true motion masks) are in `c4d_pipeline.ground_truth`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, Sequence

import cv2
import numpy as np

from c4d_core.config import defaults_from
from c4d_core.epipolar import fundamental_lmeds, sampson_distance
from c4d_core.errors import UserError
from c4d_core.geometry import pixel_grid, project, unproject_depth_map
from c4d_pipeline.flow import compose_flows, sample_flow, warp_back

log = logging.getLogger(__name__)
Pair = tuple[int, int]
LISTED_PAIRS = 8  # a warning names at most this many pairs, then "..."
_reported: set[tuple] = set()  # the pair infos whose fallbacks were logged in this process


@dataclass(frozen=True)
@defaults_from("c4d", "motion_mask.c4d")
class MotionMaskConfig:
    """Settings of the correspondence-guided mask: the keys of configs/c4d `motion_mask.c4d`,
    where each is explained; the defaults are that file's (the schema's)."""

    mobility_threshold: float
    min_confidence: float
    sampson_threshold_px: float
    min_static_points: int
    fallback_grid_points: int
    still_camera_px: float
    seed: int
    max_pair_offset: int
    noise_sigmas: float
    judge_out_of_view: bool
    forward_backward_px: float
    open_px: int
    close_px: int
    temporal_neighbours: int
    guided_radius_px: int
    guided_eps: float
    min_vote: float


@dataclass
class MotionMasks:
    """masks bool (T,H,W), True = dynamic; pair_info: one dict per pair (method, point count)."""

    masks: np.ndarray
    pair_info: list[dict[str, Any]] = field(default_factory=list)


def _numpy(x) -> np.ndarray:
    """A numpy array from a numpy array or a (CPU/GPU) torch tensor."""
    return x.detach().cpu().numpy() if hasattr(x, "detach") else np.asarray(x)


def track_arrays(tracks) -> dict[str, np.ndarray]:
    """tracks (T,N,2), visible, confidence, moving (T,N) as numpy, a leading batch of one dropped."""
    arrays = {name: _numpy(getattr(tracks, name)) for name in ("tracks", "visible", "confidence", "moving")}
    if arrays["tracks"].ndim == 4:  # (1,T,N,2): batched tracker output
        arrays = {name: a[0] for name, a in arrays.items()}
    return arrays


def static_points(tracks, t: int, cfg: MotionMaskConfig = MotionMaskConfig()) -> np.ndarray:
    """(x, y) float64 (M,2) of the tracker's points visible and static at frame t.

    `tracks`: any object with tracks (T,N,2), visible (T,N), confidence (T,N), moving (T,N).
    """
    arrays = track_arrays(tracks)
    xy, visible = arrays["tracks"][t], arrays["visible"][t].astype(bool)  # (N,2), (N,)
    static = (
        visible
        & (arrays["moving"][t] < cfg.mobility_threshold)
        & (arrays["confidence"][t] >= cfg.min_confidence)
        & np.isfinite(xy).all(-1)
    )
    return xy[static].astype(np.float64)


def _grid_points(height: int, width: int, count: int) -> np.ndarray:
    """About `count` pixel centres (M,2) on a regular grid over the image."""
    step = max(1, int(np.sqrt(height * width / max(count, 1))))
    return pixel_grid(height, width)[step // 2 :: step, step // 2 :: step].reshape(-1, 2)


def pair_motion_mask(flow: np.ndarray, static_xy: np.ndarray, cfg: MotionMaskConfig = MotionMaskConfig()):
    """Dynamic pixels of frame t from the flow t -> t' (H,W,2) and static points (M,2) of frame t.

    Returns (mask bool (H,W), info dict with 'method' in {'static', 'all-flow', 'still',
    'failed'} and 'static_points', the number of usable static points).
    """
    height, width = flow.shape[:2]
    grid = pixel_grid(height, width)  # (H,W,2)
    targets = static_xy + sample_flow(flow, static_xy)  # (M,2) correspondences in frame t'
    inside = (targets[:, 0] > -0.5) & (targets[:, 0] < width - 0.5) & (targets[:, 1] > -0.5) & (targets[:, 1] < height - 0.5)
    src, dst = static_xy[inside], targets[inside]
    info = {"method": "static", "static_points": int(len(src))}

    if len(src) >= cfg.min_static_points:
        if np.percentile(np.linalg.norm(dst - src, axis=-1), 90) < cfg.still_camera_px:  # F undefined
            info["method"] = "still"
            return np.linalg.norm(flow, axis=-1) > cfg.sampson_threshold_px, info
        fit = fundamental_lmeds(src, dst, cfg.seed)
    else:
        fit = None
    if fit is None:
        info["method"] = "all-flow"
        src = _grid_points(height, width, cfg.fallback_grid_points)  # (M,2)
        dst = src + flow[src[:, 1].astype(int), src[:, 0].astype(int)]
        fit = fundamental_lmeds(src, dst, cfg.seed)
    if fit is None:
        info["method"] = "failed"
        return np.zeros((height, width), bool), info
    fundamental, sigma = fit
    threshold = max(cfg.sampson_threshold_px, cfg.noise_sigmas * sigma)
    info |= {"sigma_px": sigma, "threshold_px": threshold}
    target = grid + flow  # (H,W,2)
    distance = sampson_distance(fundamental, grid, target)  # (H,W) pixels
    in_view = (target[..., 0] > -0.5) & (target[..., 0] < width - 0.5) & (target[..., 1] > -0.5) & (target[..., 1] < height - 0.5)
    return (distance > threshold) & (in_view | cfg.judge_out_of_view), info


def forward_backward_error(flow: np.ndarray, back: np.ndarray) -> np.ndarray:
    """Pixels (H,W) by which the flow i -> j (H,W,2) and the flow j -> i (H,W,2), sampled where
    the first lands (bilinear, edges replicated), fail to cancel: |f_ij(x) + f_ji(x + f_ij(x))|."""
    return np.linalg.norm(compose_flows(flow, back), axis=-1)


def guided_filter(guide: np.ndarray, image: np.ndarray, radius: int, eps: float) -> np.ndarray:
    """He et al.'s colour guided filter: `image` float (H,W) smoothed within windows of side
    2 radius + 1 by the local linear model image ~ a . guide + b, guide float (H,W,3) in [0, 1];
    `eps` (in guide units squared) regularises a, so flat regions are averaged. -> float32 (H,W).
    """
    side = (2 * radius + 1, 2 * radius + 1)

    def mean(x: np.ndarray) -> np.ndarray:  # the mean over each pixel's window, edges reflected
        return cv2.boxFilter(x, -1, side)

    guide, image = guide.astype(np.float32), image.astype(np.float32)
    mean_guide, mean_image = mean(guide), mean(image)  # (H,W,3), (H,W)
    covariance_gi = mean(guide * image[..., None]) - mean_guide * mean_image[..., None]  # (H,W,3)
    variance = np.empty((*image.shape, 3, 3), np.float32)  # (H,W,3,3) of the guide's channels
    for a in range(3):
        for b in range(a, 3):
            variance[..., a, b] = variance[..., b, a] = mean(guide[..., a] * guide[..., b]) - mean_guide[..., a] * mean_guide[..., b]
    slope = np.linalg.solve(variance + eps * np.eye(3, dtype=np.float32), covariance_gi[..., None])[..., 0]  # (H,W,3)
    offset = mean_image - np.sum(slope * mean_guide, -1)  # (H,W)
    return np.sum(mean(slope) * guide, -1) + mean(offset)


def refine_masks(masks: np.ndarray, flows: np.ndarray, index: dict[Pair, int], frames: np.ndarray | None,
                 cfg: MotionMaskConfig) -> np.ndarray:
    """Step 6 of the module doc: masks bool (T,H,W) voted over `temporal_neighbours` frames on
    each side through flows (P,H,W,2) (index: pair (t, t') -> its row), smoothed by a guided
    filter on frames uint8 (T,H,W,3) when `guided_radius_px` > 0, kept where >= `min_vote`."""
    num_frames = masks.shape[0]
    refined = np.zeros_like(masks)
    for t in range(num_frames):
        votes, voters = masks[t].astype(np.float32), 1  # (H,W) dynamic votes, frames voting
        for other in range(t - cfg.temporal_neighbours, t + cfg.temporal_neighbours + 1):
            if other != t and (t, other) in index:  # frame t' seen from t through the flow t -> t'
                votes += warp_back(masks[other], flows[index[(t, other)]], cv2.BORDER_CONSTANT)
                voters += 1
        score = votes / voters  # (H,W) in [0, 1]
        if cfg.guided_radius_px > 0:
            score = guided_filter(frames[t] / np.float32(255), score, cfg.guided_radius_px, cfg.guided_eps)
        refined[t] = score >= cfg.min_vote
    return refined


def _check_flows(flows: np.ndarray, pairs: Sequence[Pair], num_frames: int) -> None:
    if flows.ndim != 4 or flows.shape[-1] != 2 or flows.shape[0] != len(pairs):
        raise UserError(f"got flows of shape {flows.shape} for {len(pairs)} pairs; expected (P,H,W,2) with P = pairs")
    bad = [p for p in pairs if not (0 <= p[0] < num_frames and 0 <= p[1] < num_frames)]
    if bad:
        raise UserError(f"pairs {bad[:3]} index frames outside 0..{num_frames - 1}; build the graph on the same frames")
    if not np.isfinite(flows).all():
        raise UserError("the optical flow contains NaN or infinite values; check the flow estimator's input")


def _warn_frames_without_pairs(pairs: Sequence[Pair], num_frames: int) -> None:
    lonely = sorted(set(range(num_frames)) - {i for i, _ in pairs})
    if lonely:
        log.warning("frames %s start no pair of the graph: their motion masks are empty", lonely)


def correspondence_motion_masks(
    tracks, flows: np.ndarray, pairs: Sequence[Pair], cfg: MotionMaskConfig = MotionMaskConfig(),
    frames: np.ndarray | None = None,
) -> MotionMasks:
    """C4D's motion masks (T,H,W) from a tracker result, flows (P,H,W,2) and their pairs (i, j).

    `tracks` has tracks (T,N,2), visible (T,N), confidence (T,N), moving (T,N) (dynpt's
    TrackResult, from the tracker or `ground_truth.oracle_tracks`); flows[p] is the flow from
    pairs[p][0] to pairs[p][1] at the tracker's pixel coordinates. Frame t's mask is the union
    over the pairs that start at t. `frames` uint8 (T,H,W,3), the video the flows were estimated
    on, guide step 6's filter (needed only when `guided_radius_px` > 0).
    """
    num_frames = track_arrays(tracks)["tracks"].shape[0]
    _check_flows(flows, pairs, num_frames)
    if cfg.guided_radius_px > 0 and (frames is None or frames.shape[:3] != (num_frames, *flows.shape[1:3])):
        raise UserError(f"motion_mask.c4d.guided_radius_px={cfg.guided_radius_px} needs the video's frames "
                        f"({num_frames},{flows.shape[1]},{flows.shape[2]},3) beside the flows; pass frames= "
                        "or set guided_radius_px=0")
    index = {(int(i), int(j)): p for p, (i, j) in enumerate(pairs)}
    pair_masks, infos = [], []
    for flow, (i, j) in zip(flows, pairs):
        if cfg.max_pair_offset and abs(j - i) > cfg.max_pair_offset:
            continue
        mask, info = pair_motion_mask(flow, static_points(tracks, i, cfg), cfg)
        if cfg.forward_backward_px > 0 and (int(j), int(i)) in index:
            inconsistent = forward_backward_error(flow, flows[index[(int(j), int(i))]]) > cfg.forward_backward_px
            mask &= ~inconsistent
            info["inconsistent_fraction"] = float(inconsistent.mean())
        pair_masks.append(mask)
        infos.append({"pair": [int(i), int(j)], **info})
    fallbacks = [tuple(f["pair"]) for f in infos if f["method"] in ("all-flow", "failed")]
    seen = tuple((tuple(f["pair"]), f["static_points"]) for f in infos)
    if fallbacks and seen not in _reported:
        _reported.add(seen)
        listed = ", ".join(f"({i}, {j})" for i, j in fallbacks[:LISTED_PAIRS])
        log.warning(
            "%d of %d pairs had fewer than %d static points or no LMedS solution; their fundamental "
            "matrix came from all flow correspondences (or the pair was skipped): %s%s",
            len(fallbacks), len(pairs), cfg.min_static_points, listed,
            ", ..." if len(fallbacks) > LISTED_PAIRS else "",
        )
    masks = np.zeros((num_frames, *flows.shape[1:3]), bool)  # (T,H,W)
    for mask, info in zip(pair_masks, infos):
        masks[info["pair"][0]] |= mask  # union over the pairs that start at frame i
    for size, operation in ((cfg.open_px, cv2.MORPH_OPEN), (cfg.close_px, cv2.MORPH_CLOSE)):
        if size > 0:
            kernel = np.ones((size, size), np.uint8)
            masks = np.stack([cv2.morphologyEx(m.astype(np.uint8), operation, kernel) > 0 for m in masks])
    if cfg.temporal_neighbours > 0 or cfg.guided_radius_px > 0:
        masks = refine_masks(masks, flows, index, frames, cfg)
    _warn_frames_without_pairs([info["pair"] for info in infos], num_frames)
    return MotionMasks(masks, infos)


def ego_flow(depth: np.ndarray, intrinsics_i: np.ndarray, intrinsics_j: np.ndarray,
             cam_to_world_i: np.ndarray, cam_to_world_j: np.ndarray) -> np.ndarray:
    """Flow (H,W,2) that camera motion alone causes: pixels of frame i lifted with z-depth (H,W),
    K_i (3,3) and camera-to-world pose_i (4,4), projected with K_j and pose_j. Points that land
    behind camera j get NaN.
    """
    points = unproject_depth_map(depth, intrinsics_i.astype(np.float64), cam_to_world_i.astype(np.float64))  # (H,W,3)
    pixels, z = project(points, intrinsics_j.astype(np.float64), cam_to_world_j.astype(np.float64))  # (H,W,2), (H,W)
    return np.where(z[..., None] > 1e-9, pixels - pixel_grid(*depth.shape), np.nan)


def pairwise_ego_flow(pts_i: np.ndarray, pts_j: np.ndarray, conf_j: np.ndarray, intrinsics_j: np.ndarray,
                      min_conf: float = 3.0) -> np.ndarray:
    """Ego-flow (H,W,2) i -> j from one pair's pointmaps, as MonST3R's pair viewer gets it.

    pts_i, pts_j (H,W,3): both views' pixels in camera i's frame (any common scale); conf_j
    (H,W) their raw confidence (>= 1). Camera j's pose in that frame comes from PnP-RANSAC
    (SQPnP, 100 iterations, 5 px) of pts_j against its own pixels with K_j (3,3), on pixels of
    confidence > `min_conf` (all pixels if fewer than 6 pass); pts_i is then projected into it.
    """
    grid = pixel_grid(*pts_i.shape[:2])  # (H,W,2)
    usable = conf_j > min_conf if (conf_j > min_conf).sum() >= 6 else np.ones(conf_j.shape, bool)
    ok, rvec, tvec, _ = cv2.solvePnPRansac(
        pts_j[usable].astype(np.float64), grid[usable], intrinsics_j.astype(np.float64), None,
        iterationsCount=100, reprojectionError=5.0, flags=cv2.SOLVEPNP_SQPNP,
    )
    if not ok:
        return np.full(grid.shape, np.nan)
    rot = cv2.Rodrigues(rvec)[0]  # camera-i frame -> camera j
    points_j = pts_i.astype(np.float64) @ rot.T + tvec[:, 0]  # (H,W,3)
    uvw = points_j @ intrinsics_j.astype(np.float64).T
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(points_j[..., 2:] > 1e-9, uvw[..., :2] / uvw[..., 2:], np.nan) - grid


def flow_only_motion_masks(
    flows: np.ndarray, ego_flows: np.ndarray, pairs: Sequence[Pair], num_frames: int, threshold: float = 0.35
) -> MotionMasks:
    """MonST3R-style masks (T,H,W) from optical flows and ego-flows, both (P,H,W,2), of pairs.

    Per pair the end-point error |ego - flow| is min-max normalised to [0, 1] (pixels whose
    ego-flow is undefined get the maximum); frame t averages the pairs (t, t') and is dynamic
    above `threshold`. The ego-flows are the caller's geometry: `ego_flow` from per-frame depth,
    K and poses, or `pairwise_ego_flow` from a pair's pointmaps.
    """
    _check_flows(flows, pairs, num_frames)
    if ego_flows.shape != flows.shape:
        raise UserError(f"got ego-flows of shape {ego_flows.shape} for flows of shape {flows.shape}; give one per pair")
    total = np.zeros((num_frames, *flows.shape[1:3]))  # (T,H,W) summed normalised errors
    count = np.zeros(num_frames, int)
    for flow, ego, (i, _) in zip(flows, ego_flows, pairs):
        error = np.linalg.norm(ego - flow, axis=-1)  # (H,W) end-point error, pixels
        finite = np.isfinite(error)
        if not finite.any():
            continue
        low, high = error[finite].min(), error[finite].max()
        total[i] += np.where(finite, (error - low) / max(high - low, 1e-12), 1.0)
        count[i] += 1
    _warn_frames_without_pairs(pairs, num_frames)
    masks = (total / np.maximum(count, 1)[:, None, None] > threshold) & (count > 0)[:, None, None]
    return MotionMasks(masks, [{"pair": [int(i), int(j)], "method": "ego-flow"} for i, j in pairs])
