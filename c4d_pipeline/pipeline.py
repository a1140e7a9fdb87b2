"""The C4D reconstruction of one video, from frames to the files of the output table.

scene graph -> pairwise pointmaps -> optical flow per edge -> motion masks (DynPT + flow, or the
flow-only baseline without a tracker) -> two-stage optimisation -> 3-D tracks -> files.
"""

from __future__ import annotations

import copy
import logging
import platform
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch

from c4d_core.config import to_dict
from c4d_core.errors import UserError
from c4d_core.system import configure_threads
from c4d_pipeline import motion_mask as mm
from c4d_pipeline.alignment import initialise
from c4d_pipeline.objectives import sample_points
from c4d_pipeline.optimize import check_intrinsics, optimise
from c4d_pipeline.outputs import Reconstruction, write_reconstruction
from c4d_pipeline.pointmaps import PairwisePointmaps, PointmapSource, sanitize
from c4d_pipeline.scene_graph import graph_from_config

log = logging.getLogger(__name__)


def software_versions() -> dict[str, str]:
    """report.json's `versions`: Python's, torch's and numpy's."""
    return {"python": platform.python_version(), "torch": torch.__version__, "numpy": np.__version__}


def check_frames(frames: np.ndarray) -> None:
    """`UserError` unless frames are uint8 (T,H,W,3)."""
    if not isinstance(frames, np.ndarray) or frames.ndim != 4 or frames.shape[-1] != 3:
        raise UserError(f"frames must be a (T,H,W,3) array, got shape {getattr(frames, 'shape', None)}")
    if frames.dtype != np.uint8:
        raise UserError(f"frames must be uint8 RGB, got {frames.dtype}; convert the video first")


def lift_tracks(points: np.ndarray, tracks: np.ndarray, visible: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """3-D tracks from world pointmaps (T,H,W,3) sampled bilinearly at 2-D tracks (T,N,2).

    Returns tracks_world float32 (T,N,3) and valid bool (T,N) = visible, finite and inside the image.
    """
    h, w = points.shape[1:3]
    trk = np.nan_to_num(np.asarray(tracks, np.float32), nan=-1.0)
    inside = (trk[..., 0] >= 0) & (trk[..., 0] <= w - 1) & (trk[..., 1] >= 0) & (trk[..., 1] <= h - 1)
    valid = np.asarray(visible, bool) & inside & np.isfinite(tracks).all(-1)
    with torch.no_grad():
        world = sample_points(torch.from_numpy(points), torch.from_numpy(trk)).numpy()  # (T,N,3)
    return world.astype(np.float32), valid


def _tracker_arrays(tracker_result, num_frames: int, image_size) -> dict[str, np.ndarray] | None:
    if tracker_result is None:
        return None
    arrays = mm.track_arrays(tracker_result)
    queries = tracker_result.queries
    arrays["queries"] = np.asarray(queries.detach().cpu() if hasattr(queries, "detach") else queries)
    if arrays["tracks"].shape[0] != num_frames:
        raise UserError(
            f"the tracker result has {arrays['tracks'].shape[0]} frames but the video has "
            f"{num_frames}; track the same frames the reconstruction uses"
        )
    return arrays


def estimate_motion_masks(frames, edges, flows, tracker_result, pw, cfg,
                          intrinsics: np.ndarray | None = None) -> tuple[np.ndarray, str]:
    """Motion masks bool (T,H,W) (True = dynamic) and the method used.

    With a tracker result: C4D's DynPT + flow masks. Without: the flow-only baseline, with the
    ego-flow from the spanning-tree initialisation's depth, intrinsics (the known (T,4) fx, fy,
    cx, cy if given) and poses.
    """
    pairs = [tuple(map(int, e)) for e in edges]
    if tracker_result is not None:
        mcfg = mm.MotionMaskConfig(**to_dict(cfg.motion_mask.c4d))
        return mm.correspondence_motion_masks(tracker_result, flows, pairs, mcfg, frames).masks, "dynpt+flow"
    log.warning("no tracker result: motion masks from the flow-only baseline, stage 2 (PTS) skipped")
    init = initialise(pw, frames.shape[0], shared_focal=cfg.optim.shared_focal,
                      intrinsics=None if intrinsics is None else torch.from_numpy(intrinsics))
    depth, pose = init.depth.numpy(), init.cam_to_world.numpy().astype(np.float64)
    k = np.zeros((frames.shape[0], 3, 3))
    (k[:, 0, 0], k[:, 1, 1]), (k[:, 0, 2], k[:, 1, 2]) = init.focal_xy().numpy().T, init.principal.numpy().T
    k[:, 2, 2] = 1
    ego = np.stack([mm.ego_flow(depth[i], k[i], k[j], pose[i], pose[j]) for i, j in pairs])
    masks = mm.flow_only_motion_masks(flows, ego, pairs, frames.shape[0], cfg.motion_mask.flow_only_threshold)
    return masks.masks, "flow-only"


@contextmanager
def _pointmap_failures(pw: PairwisePointmaps):
    """Turn a numerical failure downstream of the pointmaps (a non-finite loss, an alignment that
    does not converge) into one `UserError` naming their statistics and what to try."""
    try:
        yield
    except (FloatingPointError, torch.linalg.LinAlgError) as exc:
        what = str(exc).splitlines()[0]
        raise UserError(
            f"the reconstruction diverged ({what}); the likely cause is the pointmap network's "
            f"output: {pw.statistics()}. Try a better-trained network (more `c4d pretrain-pointmaps` "
            "steps on scenes like this video, or DUSt3R's released weights) at the size it was "
            "trained at"
        ) from exc


class Reused:
    """A pointmap source or flow estimator `inner` that hands back a copy of its last result when
    asked again for the same frames and pairs: one video reconstructed with several configurations
    from the same inputs (C4D and GA only in `c4d demo`) computes them once."""

    def __init__(self, inner):
        self.inner = inner
        self._last: dict[str, tuple] = {}  # method -> (frames, pairs (P,2), result)

    def pointmaps(self, frames: np.ndarray, edges) -> PairwisePointmaps:
        return self._reuse("pointmaps", frames, edges)

    def flow(self, frames: np.ndarray, pairs) -> np.ndarray:
        return self._reuse("flow", frames, pairs)

    def _reuse(self, method: str, frames: np.ndarray, pairs):
        key = np.asarray(pairs, np.int64).reshape(-1, 2)
        last = self._last.get(method)
        if last is None or not (np.array_equal(last[0], frames) and np.array_equal(last[1], key)):
            last = self._last[method] = (frames.copy(), key, getattr(self.inner, method)(frames, pairs))
        return copy.deepcopy(last[2])


def _kind(source) -> str:
    """The class name of a pointmap source or flow estimator (of the one a `Reused` wraps)."""
    return type(source.inner if isinstance(source, Reused) else source).__name__


def reconstruct(frames: np.ndarray, pointmap_source: PointmapSource, flow_estimator,
                tracker_result, cfg, out_dir: str | Path | None = None,
                inputs: dict | None = None, timestamps: np.ndarray | None = None,
                intrinsics: np.ndarray | None = None) -> Reconstruction:
    """Reconstruct a video with C4D and (if `out_dir`) write the output table there.

    frames: uint8 (T,H,W,3) at the resolution of the reconstruction (the pointmap source must
    return pointmaps at this size); pointmap_source: a `PointmapSource`; flow_estimator: an object
    with `flow(frames, pairs) -> (P,H,W,2)` (`c4d_pipeline.flow.build_flow`); tracker_result:
    dynpt's TrackResult (tracks (T,N,2), visible, confidence, moving (T,N), queries (N,3)) or None
    (flow-only masks, no PTS); cfg: a c4d config (configs/c4d/default.yaml); inputs: free-form
    description of the inputs for report.json; timestamps: float64 (T,) source time of each frame
    in seconds, for poses_tum.txt (None: the frame index); intrinsics: known float (T,4) fx, fy,
    cx, cy in pixels of `frames` (`video_input.network_intrinsics` converts `intrinsics.known`
    from the source video's pixels), fixed or a starting point per `intrinsics.mode` (None: the
    focal estimated, the principal point at the image centre).
    Bad input: a source returning NaN/inf points gets those pixels ignored (warning); mismatched
    frame counts or sizes between frames, pointmaps, flow and tracks raise `UserError`; a video
    too short for the scene graph raises `UserError`; too few static points for a pair's
    fundamental matrix falls back as documented in `c4d_pipeline.motion_mask`.
    """
    check_frames(frames)
    num_frames, h, w = frames.shape[:3]
    check_intrinsics(intrinsics, num_frames)
    if cfg.threads > 0:  # a library caller's config (`c4d run` set them before loading the networks)
        configure_threads(threads=cfg.threads)
    seconds: dict[str, float] = {}
    start = time.perf_counter()
    edges = graph_from_config(num_frames, cfg.graph)
    pw = pointmap_source.pointmaps(frames, edges)
    for view in ("i", "j"):  # NaN/inf points: ignored pixels (confidence 1), with a warning
        pts, conf = getattr(pw, f"pts_{view}"), getattr(pw, f"conf_{view}")
        if not (np.isfinite(pts).all() and np.isfinite(conf).all()):
            fixed = sanitize(pts, conf)
            setattr(pw, f"pts_{view}", fixed[0])
            setattr(pw, f"conf_{view}", fixed[1])
    pw.validate(num_frames, (h, w))
    seconds["pointmaps"] = time.perf_counter() - start

    start = time.perf_counter()
    flows = np.asarray(flow_estimator.flow(frames, [tuple(map(int, e)) for e in edges]), np.float32)
    if flows.shape != (len(edges), h, w, 2):
        raise UserError(f"the flow estimator returned shape {flows.shape}, expected {(len(edges), h, w, 2)}")
    if not np.isfinite(flows).all():
        log.warning("optical flow: %d non-finite values; those pixels are left out of CMA and masks",
                    int((~np.isfinite(flows)).sum()))
    seconds["flow"] = time.perf_counter() - start

    start = time.perf_counter()
    tracks = _tracker_arrays(tracker_result, num_frames, (h, w))
    with _pointmap_failures(pw):
        masks, mask_method = estimate_motion_masks(frames, edges, np.nan_to_num(flows), tracker_result, pw, cfg,
                                                   intrinsics)
    seconds["motion_masks"] = time.perf_counter() - start

    with _pointmap_failures(pw):
        result = optimise(
            pw, num_frames, cfg, flows=flows, static_masks=~masks,
            tracks=None if tracks is None else tracks["tracks"],
            visible=None if tracks is None else tracks["visible"], device=cfg.device,
            intrinsics=intrinsics,
        )
    seconds.update({f"optimise_{k}": v for k, v in result.history["seconds"].items()})

    tracks_world = valid = None
    if tracks is not None:
        tracks_world, valid = lift_tracks(result.points, tracks["tracks"], tracks["visible"])
    report = {
        "inputs": {"frames": num_frames, "height": h, "width": w, "edges": len(edges),
                   "pointmap_source": _kind(pointmap_source), "flow": _kind(flow_estimator),
                   "motion_masks": mask_method,
                   **(inputs or {})},
        "config": to_dict(cfg),
        "seconds": seconds,
        "losses": result.history["losses"],
        "pts_frames": result.history.get("pts_frames", 0),
        "versions": software_versions(),
    }
    rec = Reconstruction(
        frames=frames, depth=result.depth, masks=masks, cam_to_world=result.cam_to_world,
        intrinsics=result.intrinsics, points=result.points, confidence=result.confidence,
        tracks_2d=None if tracks is None else {k: tracks[k] for k in ("tracks", "visible", "moving", "queries")},
        tracks_world=tracks_world, tracks_valid=valid, report=report, timestamps=timestamps,
    )
    if out_dir is not None:
        oc = cfg.outputs
        write_reconstruction(rec, out_dir, oc.ply_pixel_stride, oc.ply_static_frame_stride, oc.ply_min_confidence)
    return rec
