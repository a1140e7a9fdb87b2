"""Long videos in bounded memory: overlapping windows of frames, joined by Sim(3), then one pass
over the cameras (`window.frames` > 0 in the c4d config; 0 reconstructs the whole video at once).

1. Plan (`plan_windows`): as few windows of `window.frames` frames as overlap by at least
   `window.overlap`, spread evenly from the video's start to its end. The overlap
   must be at least the scene graph's longest pair, so that every pair of the whole-video graph
   lies inside some window; a window must be longer than that pair. Each window owns the frames
   from the middle of its overlap with the previous window to the middle of its overlap with the
   next one: it writes their outputs.
2. Anchor (`window.anchor`, on by default, when there is more than one window): first one
   reconstruction of `window.frames` keyframes spread evenly over the whole video
   (`anchor_frames`), with the same scene graph over the keyframes (so its pairs are further
   apart in time than a window's) and the same stages: a coarse reconstruction of the whole video
   in one window's memory, whose world is the reference. Its points, confidences and motion masks
   of the keyframes are kept (one window's shared frames' worth).
3. Per window, in turn: `pipeline.reconstruct` on the window's frames, unchanged (scene graph,
   pairwise pointmaps, flow, motion masks, both optimisation stages). The pointmap source and the
   flow estimator see the whole video's frames and only the window's pairs, in video indices
   (`_WindowView`); the tracker result is cut to the window's frames (`window_tracks`).
4. Join: the similarity (Umeyama, `procrustes.weighted_procrustes`) that best maps the window's
   points of some frames onto the reference's points of the same pixels of the same frames: static
   pixels, weighted by the smaller log-confidence of the two (`join_similarity`). The frames: the
   anchor's keyframes inside the window (none beyond about `window.frames`^2 frames, where the
   keyframes lie further apart than a window is long) together with the frames it shares with
   the previous, already joined window; without the anchor the shared frames alone (a chain).
5. The owned frames' outputs go to disk at once: frames, depth (in the joined world's units),
   masks, and the confidence in a scratch folder; the window's arrays are then dropped but for
   its points of the frames the next window shares.
6. Cameras (`pose_graph`, `window.joint_iters` L-BFGS iterations; 0: off): the anchor and every
   window measure the relative pose of each forward pair of their scene graph; all frames'
   camera-to-world poses are refined together to agree with every measurement, each weighted
   1 / the pair's offset in the reconstruction that measured it (the graph's steps: a pair of
   neighbouring keyframes weighs as a pair of neighbouring frames). Inside a window the poses
   agree already; the pass spreads the disagreement of two windows on their shared frames over
   the frames around each seam instead of leaving a jump where the owner changes, and the
   anchor's pairs, which span the video, hold the drift that the windows' pairs alone integrate.
7. Final pass, one frame at a time: world points from the depth, intrinsics and refined pose;
   pointmaps.npz (streamed, `outputs.write_npz_frames`), coloured depth, 3-D tracks and scene.ply.
Peak memory is one window's reconstruction plus the anchor's keyframe points and a few arrays of
(T,) poses and (T,N) tracks; the frames of the video (uint8) and the tracker result are held
whole, as the caller gives them.
"""

from __future__ import annotations

import logging
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from c4d_core.config import to_dict
from c4d_core.draw import colorize_depth
from c4d_core.errors import UserError
from c4d_core.files import write_json, write_text
from c4d_core.geometry import unproject_depth_map
from c4d_pipeline import outputs
from c4d_pipeline.optimize import check_intrinsics
from c4d_pipeline.pipeline import check_frames, lift_tracks, reconstruct, software_versions
from c4d_pipeline.procrustes import weighted_procrustes
from c4d_pipeline.scene_graph import graph_from_config, window_offsets
from c4d_pipeline.scene_params import quat_to_rotation

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Window:
    """Frames [start, stop) of the video are reconstructed together; [own_start, own_stop) are
    the frames whose outputs this window writes."""

    start: int
    stop: int
    own_start: int
    own_stop: int


def plan_windows(num_frames: int, frames: int, overlap: int, graph_cfg) -> list[Window]:
    """Windows of `frames` frames overlapping by at least `overlap` over a video of `num_frames`
    (module docstring, 1.); one window of the whole video when it is not longer than `frames`.
    `UserError` when the windows cannot hold the scene graph of `graph_cfg` (the c4d config's
    `graph` section): `frames` not longer than its longest pair, `overlap` shorter than it, or
    `overlap` >= `frames`."""
    longest = max(window_offsets(graph_cfg.window, graph_cfg.stride, graph_cfg.start))
    if frames <= longest:
        raise UserError(f"window.frames = {frames} cannot hold the scene graph, whose longest pair spans "
                        f"{longest} frames (graph.start + graph.stride x (graph.window - 1)); give "
                        f"window.frames > {longest} (several times more: each window is one "
                        "optimisation) or a shorter graph")
    if overlap < longest:
        raise UserError(f"window.overlap = {overlap} is shorter than the scene graph's longest pair "
                        f"({longest} frames): pairs across a seam would be in no window; give "
                        f"window.overlap >= {longest}")
    if overlap >= frames:
        raise UserError(f"window.overlap = {overlap} must be smaller than window.frames = {frames}")
    if num_frames <= frames:
        return [Window(0, num_frames, 0, num_frames)]
    count = -(-(num_frames - overlap) // (frames - overlap))  # ceil: windows at the longest step
    starts = [(k * (num_frames - frames) + (count - 1) // 2) // (count - 1) for k in range(count)]  # evenly spread
    stops = [s + frames for s in starts]
    seams = [(start + stop) // 2 for start, stop in zip(starts[1:], stops[:-1])]  # middles of the overlaps
    owns = [0, *seams, num_frames]
    return [Window(s, e, a, b) for s, e, a, b in zip(starts, stops, owns[:-1], owns[1:])]


def anchor_frames(num_frames: int, frames: int) -> np.ndarray:
    """The anchor's keyframes (module docstring, 2.): `frames` video frames (int (K,), increasing)
    spread evenly from the first frame to the last."""
    return np.unique(np.round(np.linspace(0, num_frames - 1, frames)).astype(np.int64))


class _WindowView:
    """A pointmap source and flow estimator seen from a window of video frames `index` (int (F,),
    increasing): asked for pairs of window frames, it asks `source` / `flow_estimator` for the same
    pairs in video indices, with the whole video's `frames` (what sources of generated scenes need)."""

    def __init__(self, source, flow_estimator, frames: np.ndarray, index: np.ndarray):
        self.source, self.flow_estimator, self.frames, self.index = source, flow_estimator, frames, index

    def pointmaps(self, frames, edges):
        pw = self.source.pointmaps(self.frames, self.index[np.asarray(edges)])
        return replace(pw, edges=np.searchsorted(self.index, pw.edges))

    def flow(self, frames, pairs):
        return self.flow_estimator.flow(self.frames, [(int(self.index[i]), int(self.index[j])) for i, j in pairs])


def window_tracks(tracker_result, index: np.ndarray):
    """The tracker result (T frames) cut to the video frames `index` (int (F,), increasing); each
    query's frame becomes the position of the first of them at or after it."""
    if tracker_result is None:
        return None
    queries = np.array(tracker_result.queries, np.float32)  # (N,3) t, x, y
    queries[:, 0] = np.searchsorted(index, queries[:, 0])
    return replace(tracker_result, **{name: np.asarray(getattr(tracker_result, name))[index]
                                      for name in ("tracks", "visible", "confidence", "moving")},
                   queries=queries)


def join_similarity(src: np.ndarray, dst: np.ndarray, src_conf: np.ndarray, dst_conf: np.ndarray,
                    static: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """The similarity (scale s, rotation R (3,3), translation t (3,)) with s R src + t ~ dst.

    src, dst: float (S,H,W,3) world points of the same pixels of S shared frames in two windows;
    src_conf, dst_conf: raw confidences (S,H,W) >= 1; static: bool (S,H,W), static in both.
    Weights: the smaller log-confidence of the two, on static pixels (all pixels where none is
    static with a confidence above 1).
    """
    weights = np.minimum(np.log(src_conf), np.log(dst_conf)) * static
    if not weights.sum() > 0:
        weights = np.ones(static.shape)
    scale, rot, trans = weighted_procrustes(torch.from_numpy(src.reshape(1, -1, 3).astype(np.float64)),
                                            torch.from_numpy(dst.reshape(1, -1, 3).astype(np.float64)),
                                            torch.from_numpy(weights.reshape(1, -1).astype(np.float64)))
    return float(scale[0]), rot[0].numpy(), trans[0].numpy()


def similarity_poses(cam_to_world: np.ndarray, scale: float, rot: np.ndarray, trans: np.ndarray) -> np.ndarray:
    """Camera-to-world poses (T,4,4) of a world mapped by x -> scale rot x + trans."""
    out = np.array(cam_to_world, np.float64)
    out[:, :3, :3] = rot @ out[:, :3, :3]
    out[:, :3, 3] = scale * out[:, :3, 3] @ rot.T + trans
    return out


def pose_graph(cam_to_world: np.ndarray, pairs: np.ndarray, relative: np.ndarray, weights: np.ndarray,
               depth: float, iters: int) -> np.ndarray:
    """Camera-to-world poses (T,4,4) refined to agree with measured relative poses.

    cam_to_world: float (T,4,4) initial poses; pairs: int (M,2) frames (i, j); relative: (M,4,4)
    measured pose of camera j in camera i's frame (P_i^-1 P_j); weights: float (M,). Minimises,
    over a rotation increment (the quaternion (1, v), normalised; v ~ half the axis-angle) and a
    translation increment per frame (frame 0 held, fixing the gauge; the scale is the
    measurements'), sum w (||R_i^T R_j - R_ij||_F^2 + 2 ||R_i^T (t_j - t_i) - t_ij||^2 / depth^2):
    a camera moved by d at the typical `depth` of the scene (its median, in the poses' units)
    weighs as one turned by d / depth radians (||R(a) - I||_F^2 = 8 sin^2(a/2) ~ 2 a^2), so neither
    error is traded for the other by a choice of units. `iters` L-BFGS iterations (0: unchanged).
    float64.
    """
    if iters <= 0 or len(pairs) == 0:
        return np.array(cam_to_world, np.float64)
    init = torch.from_numpy(np.asarray(cam_to_world, np.float64))
    rel = torch.from_numpy(np.asarray(relative, np.float64))
    i, j = torch.from_numpy(pairs[:, 0]), torch.from_numpy(pairs[:, 1])
    weight = torch.from_numpy(np.asarray(weights, np.float64))  # (M,)
    free = torch.ones(len(init), 1, dtype=torch.float64)
    free[0] = 0.0
    turn = torch.zeros(len(init), 3, dtype=torch.float64, requires_grad=True)  # v of each quaternion (1, v)
    shift = torch.zeros(len(init), 3, dtype=torch.float64, requires_grad=True)

    def poses():
        quat = torch.cat([torch.ones(len(init), 1, dtype=torch.float64), free * turn], -1)
        return quat_to_rotation(quat) @ init[:, :3, :3], init[:, :3, 3] + free * shift

    def loss():
        opt.zero_grad()
        rot, pos = poses()
        r_i = rot[i].transpose(1, 2)
        value = (weight * (((r_i @ rot[j] - rel[:, :3, :3]) ** 2).sum((1, 2)) + (
            ((r_i @ (pos[j] - pos[i])[..., None])[..., 0] - rel[:, :3, 3]) ** 2).sum(-1) * 2 / depth ** 2)).sum()
        value.backward()
        return value

    opt = torch.optim.LBFGS([turn, shift], max_iter=iters, line_search_fn="strong_wolfe")
    opt.step(loss)
    with torch.no_grad():
        rot, pos = poses()
    out = np.tile(np.eye(4), (len(init), 1, 1))
    out[:, :3, :3], out[:, :3, 3] = rot.numpy(), pos.numpy()
    return out


def final_losses(report: dict) -> dict[str, dict[str, float]]:
    """Each loss curve's last value in a `reconstruct` report: stage -> loss -> value."""
    return {stage: {name: curve[-1] for name, curve in curves.items()} for stage, curves in report["losses"].items()}


def write_world(out: Path, scratch: Path, frames: np.ndarray, cam_to_world: np.ndarray, intrinsics: np.ndarray,
                tracks_2d: dict | None, depth_range, oc) -> tuple[np.ndarray, np.ndarray] | None:
    """The last pass (module docstring, 7.), one frame at a time: pointmaps.npz, depth/*.png, scene.ply.

    out: the output folder holding depth/*.npy and masks/*.png of every frame; scratch: the folder
    of each frame's confidence (H,W) as NNNNNN.npy and of scene.ply's rows while they are written;
    frames uint8 (T,H,W,3); cam_to_world float32 (T,4,4); intrinsics float32 (T,3,3); tracks_2d
    the tracker's arrays (tracks (T,N,2), visible (T,N), ...) or None; depth_range (vmin, vmax) of
    the coloured depth; oc the config's `outputs` section. Returns the 3-D tracks (T,N,3) float32
    and their validity (T,N) bool (None without tracks).
    """
    num_frames, h, w = frames.shape[:3]
    shape = (num_frames, len(tracks_2d["queries"])) if tracks_2d is not None else (0, 0)
    tracks_world, tracks_valid = np.zeros((*shape, 3), np.float32), np.zeros(shape, bool)
    confidence = lambda t: np.load(scratch / f"{t:06d}.npy")  # noqa: E731 -- (H,W) of frame t
    with outputs.PlyStream(out / "scene.ply", scratch / "scene.body") as ply:
        def world_points():  # (H,W,3) of each frame in turn, with its coloured depth, tracks and PLY rows
            for t in range(num_frames):
                depth = np.load(out / "depth" / f"{t:06d}.npy")
                points = unproject_depth_map(depth, intrinsics[t], cam_to_world[t]).astype(np.float32)
                outputs.save_png(out / "depth" / f"{t:06d}.png", colorize_depth(depth, *depth_range))
                if tracks_2d is not None:
                    world, valid = lift_tracks(points[None], tracks_2d["tracks"][t:t + 1],
                                               tracks_2d["visible"][t:t + 1])
                    tracks_world[t], tracks_valid[t] = world[0], valid[0]
                ply.add(*outputs.frame_ply_points(
                    points, confidence(t), outputs.read_mask(out, t), frames[t],
                    t % oc.ply_static_frame_stride == 0, oc.ply_pixel_stride, oc.ply_min_confidence))
                yield points

        outputs.write_npz_frames(out / "pointmaps.npz", num_frames, {
            "points": ((h, w, 3), world_points),
            "confidence": ((h, w), lambda: map(confidence, range(num_frames)))})
    return None if tracks_2d is None else (tracks_world, tracks_valid)


@dataclass
class LongReconstruction:
    """What `reconstruct_windowed` returns beside the files it wrote (T frames)."""

    cam_to_world: np.ndarray  # float32 (T,4,4) as in poses_tum.txt
    intrinsics: np.ndarray  # float32 (T,3,3)
    report: dict  # report.json


def reconstruct_windowed(frames: np.ndarray, pointmap_source, flow_estimator, tracker_result, cfg,
                         out_dir: str | Path, inputs: dict | None = None,
                         timestamps: np.ndarray | None = None,
                         intrinsics: np.ndarray | None = None) -> LongReconstruction:
    """Reconstruct a video window by window (module docstring) and write the output table of
    `pipeline.reconstruct` into `out_dir` (required: the outputs are streamed there).

    Arguments as `pipeline.reconstruct`'s: frames uint8 (T,H,W,3); pointmap_source, flow_estimator
    asked for pairs (i, j) of video frames with all T frames; tracker_result with (T,N) arrays or
    None; cfg a c4d config with `window.frames` > 0; timestamps float64 (T,) seconds; intrinsics
    known (T,4) fx, fy, cx, cy. `UserError` on a window setting that cannot hold the scene graph.
    report.json gains `windows` (each window's frames, owned frames, join scale and what it was
    joined to: "anchor", "previous" or "reference") and `anchor` (its keyframes, its losses).
    """
    check_frames(frames)
    num_frames, h, w = frames.shape[:3]
    check_intrinsics(intrinsics, num_frames)
    wc = cfg.window
    plan = plan_windows(num_frames, wc.frames, wc.overlap, cfg.graph)
    out = Path(out_dir)
    tracks_2d = None if tracker_result is None else {
        name: np.asarray(getattr(tracker_result, name)) for name in ("tracks", "visible", "moving", "queries")}
    cam_to_world = np.zeros((num_frames, 4, 4))  # joined poses of the owning windows
    intrinsics_out = np.zeros((num_frames, 3, 3), np.float32)
    pairs, relative, weights, windows_report = [], [], [], []
    losses: dict[str, dict[str, list[float]]] = {}  # stage -> loss -> its last value in each window
    seconds: dict[str, float] = {}
    depth_sample = []  # every 8th pixel of every frame's depth: the colour range of depth/*.png
    carry = None  # the previous window's frames shared with the next: (first frame, points, conf, static)
    anchor = None  # the keyframes' (index, points, conf, static) in the reference world

    def part(index: np.ndarray):
        """`reconstruct` on the video frames `index` (int (F,), increasing), its seconds counted."""
        view = _WindowView(pointmap_source, flow_estimator, frames, index)
        rec = reconstruct(frames[index], view, view, window_tracks(tracker_result, index), cfg,
                          intrinsics=None if intrinsics is None else intrinsics[index])
        for key, value in rec.report["seconds"].items():
            seconds[key] = seconds.get(key, 0.0) + value
        return rec

    def measure(index: np.ndarray, poses: np.ndarray) -> None:
        """The pose graph's measurements: relative poses (in the reference world's units) of the
        forward graph pairs of a part of frames `index` with joined poses (F,4,4), each weighted
        1 / its offset in the part (module docstring, 6.)."""
        local = graph_from_config(len(index), cfg.graph)
        local = local[local[:, 0] < local[:, 1]]
        pairs.append(index[local])
        relative.append(np.linalg.inv(poses[local[:, 0]]) @ poses[local[:, 1]])
        weights.append(1.0 / (local[:, 1] - local[:, 0]))

    with tempfile.TemporaryDirectory(dir=out, prefix=".windows-") as scratch:
        scratch = Path(scratch)
        if wc.anchor and len(plan) > 1:
            keys = anchor_frames(num_frames, wc.frames)
            log.info("anchor: %d keyframes, every %.1f frames", len(keys), (num_frames - 1) / (len(keys) - 1))
            rec = part(keys)
            measure(keys, np.asarray(rec.cam_to_world, np.float64))
            anchor = (keys, rec.points, rec.confidence, ~rec.masks)
            anchor_report = {"frames": keys.tolist(), "losses": final_losses(rec.report)}
            del rec
        for n, win in enumerate(plan):
            log.info("window %d/%d: frames %d-%d", n + 1, len(plan), win.start, win.stop - 1)
            rec = part(np.arange(win.start, win.stop))
            mask_method = rec.report["inputs"]["motion_masks"]  # the same in every window
            refs = {}  # what the window is joined through: name -> (its frames (S,), points, conf, static)
            inside = [] if anchor is None else np.flatnonzero((anchor[0] >= win.start) & (anchor[0] < win.stop))
            if len(inside):  # the anchor's keyframes in the window
                refs["anchor"] = (anchor[0][inside] - win.start, *(a[inside] for a in anchor[1:]))
            if carry is not None:  # the frames shared with the previous window, joined already
                first, *shared = carry
                refs["previous"] = (np.arange(first - win.start, first - win.start + len(shared[0])), *shared)
            scale, rot, trans = 1.0, np.eye(3), np.zeros(3)
            if refs:
                mine, dst, dst_conf, dst_static = (np.concatenate(parts) for parts in zip(*refs.values()))
                scale, rot, trans = join_similarity(rec.points[mine], dst, rec.confidence[mine], dst_conf,
                                                    dst_static & ~rec.masks[mine])
            poses = similarity_poses(rec.cam_to_world, scale, rot, trans)  # (F,4,4)
            measure(np.arange(win.start, win.stop), poses)
            windows_report.append({"frames": [win.start, win.stop], "owns": [win.own_start, win.own_stop],
                                   "scale": scale, "joined_to": list(refs) or ["reference"]})
            for stage, values in final_losses(rec.report).items():  # window by window
                for name, value in values.items():
                    losses.setdefault(stage, {}).setdefault(name, []).append(value)
            for t in range(win.own_start, win.own_stop):
                k = t - win.start
                outputs.write_frame(out, t, rec.frames[k], scale * rec.depth[k], rec.masks[k])
                outputs.save_npy(scratch / f"{t:06d}.npy", rec.confidence[k])
                depth_sample.append(scale * rec.depth[k, ::8, ::8].ravel())
            own = slice(win.own_start - win.start, win.own_stop - win.start)
            cam_to_world[win.own_start:win.own_stop] = poses[own]
            intrinsics_out[win.own_start:win.own_stop] = rec.intrinsics[own]
            if n + 1 < len(plan):
                keep = slice(plan[n + 1].start - win.start, None)
                points = scale * rec.points[keep].astype(np.float64) @ rot.T + trans
                carry = (plan[n + 1].start, points, rec.confidence[keep], ~rec.masks[keep])
            del rec

        start = time.perf_counter()
        depth_sample = np.concatenate(depth_sample)
        cam_to_world = pose_graph(cam_to_world, np.concatenate(pairs), np.concatenate(relative), np.concatenate(weights),
                                  float(np.median(depth_sample)), int(wc.joint_iters)).astype(np.float32)
        seconds["pose_graph"] = time.perf_counter() - start
        start = time.perf_counter()
        tracks_3d = write_world(out, scratch, frames, cam_to_world, intrinsics_out, tracks_2d,
                                np.percentile(depth_sample, [2.0, 98.0]), cfg.outputs)
    write_text(out / "poses_tum.txt", outputs.tum_lines(cam_to_world.astype(np.float64), timestamps))
    outputs.save_npy(out / "intrinsics.npy", intrinsics_out)
    if tracks_2d is not None:
        outputs.save_npz(out / "tracks_2d.npz", **tracks_2d)
        outputs.save_npz(out / "tracks_3d.npz", tracks_world=tracks_3d[0], valid=tracks_3d[1])
    seconds["write"] = time.perf_counter() - start
    report = {
        "inputs": {"frames": num_frames, "height": h, "width": w,
                   "pointmap_source": type(pointmap_source).__name__,
                   "flow": type(flow_estimator).__name__,
                   "motion_masks": mask_method,
                   **(inputs or {})},
        "config": to_dict(cfg), "seconds": seconds, "losses": losses,
        "windows": windows_report,
        **({"anchor": anchor_report} if anchor is not None else {}),
        "versions": software_versions(),
    }
    write_json(out / "report.json", report, indent=1)
    return LongReconstruction(cam_to_world, intrinsics_out, report)
