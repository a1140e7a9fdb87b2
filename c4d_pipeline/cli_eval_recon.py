"""`c4d eval-recon`: score a reconstruction directory against a generated scene's ground truth.

Reads OUT (the layout `c4d run` writes: poses_tum.txt, depth/%06d.npy, masks/%06d.png,
intrinsics.npy, report.json) and one scene of SCENE_SOURCE, and writes a JSON of the pose, depth
and motion-mask metrics of `c4d_pipeline.eval_metrics`. The reconstruction may use a subset of
the scene's frames (their scene indices are taken from report.json's `inputs.frame_indices`, else
from the TUM timestamps, else all frames in order) at another resolution (its depth is resized to
the scene's with bicubic interpolation, its masks nearest).
"""

from __future__ import annotations

import argparse
import itertools
import json
import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from c4d.errors import UserError
from c4d_pipeline.eval_metrics import DEPTH_ALIGNMENTS, depth_metrics, mask_iou, pose_metrics
from c4d_pipeline.motion_mask import ground_truth_motion_masks
from datagen import read_scenes
from datagen.geometry import make_pose, quat_to_matrix
from datagen.scene import Scene
from datagen.shards import write_json_atomic

log = logging.getLogger(__name__)


@dataclass
class Reconstruction:
    """What eval-recon reads of a reconstruction directory (T frames at h x w)."""

    cam_to_world: np.ndarray  # float64 (T,4,4)
    timestamps: np.ndarray  # float64 (T,)
    depth: np.ndarray  # float32 (T,h,w)
    masks: np.ndarray | None  # bool (T,h,w), True = dynamic
    report: dict


def read_tum_poses(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Timestamps (T,) and camera-to-world poses (T,4,4) of a TUM file `t tx ty tz qx qy qz qw`."""
    try:
        rows = [line.split() for line in path.read_text().splitlines() if line.strip() and not line.startswith("#")]
        values = np.array(rows, dtype=np.float64)
    except (OSError, ValueError) as exc:
        raise UserError(f"cannot read poses {path}: {exc}; it must hold lines 't tx ty tz qx qy qz qw'") from exc
    if values.ndim != 2 or values.shape[1] != 8 or len(values) == 0:
        raise UserError(f"poses {path} must hold one line of 8 numbers per frame (t tx ty tz qx qy qz qw)")
    quat_wxyz = values[:, [7, 4, 5, 6]]
    return values[:, 0], make_pose(quat_to_matrix(quat_wxyz), values[:, 1:4])


def read_reconstruction(out: str | Path) -> Reconstruction:
    """Read the files eval-recon needs from a reconstruction directory; clear errors if absent."""
    out = Path(out)
    if not (out / "poses_tum.txt").is_file():
        raise UserError(f"{out} is not a reconstruction directory (no poses_tum.txt); give the OUT of `c4d run`")
    timestamps, cam_to_world = read_tum_poses(out / "poses_tum.txt")
    depth_files = sorted((out / "depth").glob("*.npy"))
    if len(depth_files) != len(timestamps):
        raise UserError(f"{out} has {len(timestamps)} poses but {len(depth_files)} depth/*.npy files; rerun `c4d run`")
    depth = np.stack([np.load(f).astype(np.float32) for f in depth_files])  # (T,h,w)
    mask_files = sorted((out / "masks").glob("*.png"))
    masks = None
    if mask_files:
        if len(mask_files) != len(timestamps):
            raise UserError(f"{out} has {len(timestamps)} poses but {len(mask_files)} masks/*.png files; rerun `c4d run`")
        masks = np.stack([cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) > 127 for f in mask_files])  # (T,h,w)
    report = {}
    if (out / "report.json").is_file():
        try:
            report = json.loads((out / "report.json").read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise UserError(f"cannot read {out / 'report.json'}: {exc}; rerun `c4d run`") from exc
    return Reconstruction(cam_to_world, timestamps, depth, masks, report)


def scene_frame_indices(recon: Reconstruction, num_scene_frames: int) -> tuple[list[int], str]:
    """The scene frame index of every reconstructed frame, and where it came from."""
    count = len(recon.timestamps)
    recorded = recon.report.get("inputs", {}).get("frame_indices", recon.report.get("frame_indices"))
    if recorded is not None:
        indices, origin = [int(i) for i in recorded], "report.json"
    elif count == num_scene_frames:
        indices, origin = list(range(count)), "all frames"
    elif np.allclose(recon.timestamps, np.round(recon.timestamps)):
        indices, origin = [int(round(t)) for t in recon.timestamps], "poses_tum.txt timestamps"
    else:
        raise UserError(
            f"the reconstruction has {count} frames, the scene {num_scene_frames}, and nothing says which "
            "were used; add inputs.frame_indices to report.json or integer frame timestamps to poses_tum.txt"
        )
    if len(indices) != count or not all(0 <= i < num_scene_frames for i in indices):
        raise UserError(
            f"frame indices from {origin} ({indices[:5]}...) do not fit {count} reconstructed frames of a "
            f"{num_scene_frames}-frame scene; is --scene-index the scene that was reconstructed?"
        )
    return indices, origin


def pick_scene(source: str, index: int) -> Scene:
    """The `index`-th scene (0-based, in reading order) of a shard source."""
    if index < 0:
        raise UserError(f"--scene-index must be >= 0, got {index}")
    scene = next(itertools.islice(read_scenes(source), index, None), None)
    if scene is None:
        raise UserError(f"{source} holds fewer than {index + 1} scenes; pick a smaller --scene-index")
    return scene


def _resize(video: np.ndarray, hw: tuple[int, int], interpolation: int) -> np.ndarray:
    if video.shape[1:3] == tuple(hw):
        return video
    return np.stack([cv2.resize(frame, (hw[1], hw[0]), interpolation=interpolation) for frame in video])


def evaluate(recon: Reconstruction, scene: Scene, max_depth: float | None = None) -> dict:
    """All metrics of a reconstruction against its scene (see eval_metrics for conventions)."""
    indices, origin = scene_frame_indices(recon, scene.num_frames)
    hw = scene.image_size
    result = {
        "frame_indices": indices,
        "frame_indices_from": origin,
        "resolution": {"reconstruction": list(recon.depth.shape[1:]), "ground_truth": list(hw)},
        "pose": pose_metrics(recon.cam_to_world, scene.cam_to_world[indices].astype(np.float64)),
    }
    if scene.depth is not None:
        pred_depth = _resize(recon.depth, hw, cv2.INTER_CUBIC)  # (T,H,W)
        result["depth"] = {
            mode: depth_metrics(pred_depth, scene.depth[indices], mode, max_depth) for mode in DEPTH_ALIGNMENTS
        }
    if recon.masks is not None and scene.depth is not None and scene.object_to_world is not None:
        gt_masks = ground_truth_motion_masks(scene)[indices]  # (T,H,W)
        pred_masks = _resize(recon.masks.astype(np.uint8), hw, cv2.INTER_NEAREST).astype(bool)
        result["mask"] = {**mask_iou(pred_masks, gt_masks), "gt_dynamic_fraction": float(gt_masks.mean())}
    return result


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--pred", required=True, help="reconstruction directory written by `c4d run`")
    parser.add_argument("--gt", required=True, help="shard directory, shard, or glob of generated scenes")
    parser.add_argument("--scene-index", type=int, default=0, help="which scene of --gt, 0-based in reading order")
    parser.add_argument("--out", default=None, help="JSON file to write (default: PRED/eval_recon.json)")
    parser.add_argument("--max-depth", type=float, default=None, help="ignore ground-truth depth at or beyond this")


def run(args: argparse.Namespace) -> int:
    recon = read_reconstruction(args.pred)
    scene = pick_scene(args.gt, args.scene_index)
    result = {"pred": str(args.pred), "gt": str(args.gt), "scene_index": args.scene_index,
              "scene_meta": scene.meta, **evaluate(recon, scene, args.max_depth)}
    out = Path(args.out) if args.out else Path(args.pred) / "eval_recon.json"
    write_json_atomic(out, result)
    pose = result["pose"]
    print(f"frames {len(result['frame_indices'])} ({result['frame_indices_from']})")
    print(f"pose   ATE {pose['ate']:.4f}  RPE trans {pose['rpe_trans']:.4f}  RPE rot {pose['rpe_rot']:.3f} deg")
    for mode, d in result.get("depth", {}).items():
        print(f"depth  {mode:<11} Abs Rel {d['abs_rel']:.4f}  RMSE {d['rmse']:.4f}  delta<1.25 {d['delta_1_25']:.4f}")
    if "mask" in result:
        print(f"mask   IoU {result['mask']['iou']:.4f}  (per-frame mean {result['mask']['iou_frame_mean']:.4f})")
    print(f"wrote {out}")
    return 0
