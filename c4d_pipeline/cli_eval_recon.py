"""`c4d eval-recon`: score a reconstruction directory against a generated scene's ground truth.

Reads OUT (as `c4d run` writes it, read by `c4d_pipeline.outputs`) and one scene of
SCENE_SOURCE, and writes a JSON of the pose, depth and motion-mask metrics of
`c4d_pipeline.eval_metrics`. The reconstruction may use a subset of the scene's frames (their scene
indices come from report.json's `inputs.frame_indices`; without it, all frames in order) at another
resolution (its depth is resized to the scene's bicubically, as MonST3R's evaluation does, its
masks by nearest neighbour). The JSON records which scene frames were compared.
"""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path

import cv2
import numpy as np

from c4d_core.errors import UserError
from c4d_core.files import write_json
from c4d_pipeline.eval_metrics import DEPTH_ALIGNMENTS, depth_metrics, mask_iou, pose_metrics
from c4d_pipeline.motion_mask import ground_truth_motion_masks
from c4d_pipeline.outputs import Reconstruction, read_reconstruction
from datagen import read_scenes
from datagen.scene import Scene


def check_reconstruction(recon: Reconstruction) -> None:
    """Raise `UserError` unless poses, depth maps and masks agree on the number of frames."""
    counts = {"poses": len(recon.cam_to_world), "depth maps": len(recon.depth), "masks": len(recon.masks)}
    if len(set(counts.values())) != 1:
        found = ", ".join(f"{n} {name}" for name, n in counts.items())
        raise UserError(f"the reconstruction has {found}; they must match, rerun `c4d run`")


def scene_frame_indices(recon: Reconstruction, num_scene_frames: int) -> tuple[list[int], str]:
    """The scene frame index of every reconstructed frame, and where it came from."""
    count = recon.num_frames
    recorded = recon.report.get("inputs", {}).get("frame_indices")
    if recorded is not None:
        indices, origin = [int(i) for i in recorded], "report.json"
    elif count == num_scene_frames:
        indices, origin = list(range(count)), "all frames"
    else:
        raise UserError(
            f"the reconstruction has {count} frames, the scene {num_scene_frames}, and its report.json "
            "does not say which were used (inputs.frame_indices); reconstruct the whole scene"
        )
    if len(indices) != count or not all(0 <= i < num_scene_frames for i in indices):
        raise UserError(
            f"report.json's frame indices {indices[:5]}... do not fit {count} reconstructed frames of a "
            f"{num_scene_frames}-frame scene; is --scene-index the scene that was reconstructed?"
        )
    return indices, origin


MAX_FRAME_DIFFERENCE = 8.0  # mean |recon - scene frame| (0..255): same scene ~2 after another
# resampler; other movi-e scenes 40-70 apart, the test box scenes of another seed 12
MAX_ASPECT_DIFFERENCE = 0.05  # relative difference of height/width between reconstruction and scene


def check_same_scene(recon: Reconstruction, scene: Scene, indices: list[int]) -> None:
    """`UserError` unless `recon` is a reconstruction of `scene`: the input size its report.json
    records, the aspect ratio and the frames it used must match the scene's."""
    inputs = recon.report.get("inputs", {})
    hw, (h, w) = scene.image_size, recon.depth.shape[1:3]
    source_hw = inputs.get("source_hw")
    if source_hw is not None and tuple(source_hw) != tuple(hw):
        raise UserError(f"the reconstruction was made from a {source_hw[1]}x{source_hw[0]} video "
                        f"(report.json), the scene is {hw[1]}x{hw[0]}; pick the scene that was "
                        "reconstructed (--gt, --scene-index)")
    crop = inputs.get("crop_xy"), inputs.get("resized_hw")
    if None in crop and abs((h / w) / (hw[0] / hw[1]) - 1) > MAX_ASPECT_DIFFERENCE:
        raise UserError(f"the reconstruction is {w}x{h} pixels, the scene {hw[1]}x{hw[0]}: their "
                        "aspect ratios differ, so the pixels cannot be compared; reconstruct the "
                        "whole frame of this scene")
    if scene.rgb is None or not recon.frames.any():
        return
    frames = scene.rgb[indices]
    if None not in crop:  # the same resize and centre crop as the reconstruction's input
        (x, y), (rh, rw) = crop[0], crop[1]
        frames = _resize(frames, (rh, rw), cv2.INTER_AREA)[:, y:y + h, x:x + w]
    frames = _resize(frames, (h, w), cv2.INTER_AREA)
    difference = float(np.abs(frames.astype(np.float32) - recon.frames).mean())
    if difference > MAX_FRAME_DIFFERENCE:
        raise UserError(f"the reconstruction's frames differ from those of scene {scene.meta.get('scene_index', '?')} "
                        f"(mean difference {difference:.0f} of 255): it reconstructs another video; "
                        "pick the scene that was reconstructed (--gt, --scene-index)")


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
    check_reconstruction(recon)
    indices, origin = scene_frame_indices(recon, scene.num_frames)
    check_same_scene(recon, scene, indices)
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
    if scene.depth is not None and scene.segmentation is not None and scene.object_to_world is not None:
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
    write_json(out, result)
    pose = result["pose"]
    print(f"frames {len(result['frame_indices'])} ({result['frame_indices_from']})")
    print(f"pose   ATE {pose['ate']:.4f}  RPE trans {pose['rpe_trans']:.4f}  RPE rot {pose['rpe_rot']:.3f} deg")
    for mode, d in result.get("depth", {}).items():
        print(f"depth  {mode:<11} Abs Rel {d['abs_rel']:.4f}  RMSE {d['rmse']:.4f}  delta<1.25 {d['delta_1_25']:.4f}")
    if "mask" in result:
        print(f"mask   IoU {result['mask']['iou']:.4f}  (per-frame mean {result['mask']['iou_frame_mean']:.4f})")
    print(f"wrote {out}")
    return 0
