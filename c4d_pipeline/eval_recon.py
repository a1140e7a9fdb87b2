"""Scoring a reconstruction against ground truth (the library of `c4d eval-recon`): a generated
scene's (`evaluate`), or a public benchmark sequence's (`evaluate_sequence`).

A reconstruction (OUT as `c4d run` writes it, read by `c4d_pipeline.outputs`) may use a subset of
the scene's frames (their scene indices come from report.json's `inputs.frame_indices`; without it,
all frames in order) at another resolution (its depth is resized to the scene's bicubically, as
MonST3R's evaluation does, its masks by nearest neighbour). `evaluate` returns the pose, depth and
motion-mask metrics of `c4d_pipeline.eval_metrics` and which scene frames were compared; the
checks before it raise `UserError` when the reconstruction is not one of this scene
(`check_ground_truth`, which `c4d inspect --gt` and `c4d view --gt` run too).
"""

from __future__ import annotations

import itertools

import cv2
import numpy as np

from c4d_core.errors import UserError
from c4d_pipeline.eval_datasets import EvalSequence, load_eval_dataset
from c4d_pipeline.eval_metrics import DEPTH_ALIGNMENTS, depth_metrics, mask_iou, pose_metrics
from c4d_pipeline.ground_truth import ground_truth_motion_masks
from c4d_pipeline.outputs import Reconstruction
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


# Whether a reconstruction's frames are the scene's: their correlation on thumbnails (frames
# area-averaged to a long side of COMPARE_SIDE pixels, each frame and colour centred), which a
# lossy video codec hardly moves (its loss is blocks, ringing and colour shifts) but another scene
# does. Measured on 8 movi-e scenes at 64x64 and 256x256, each written as .mp4 (mp4v), .webm (VP8)
# and .avi (MJPEG) by OpenCV and read back as `c4d run` does at --size 32 and 512: the scene
# itself >= 0.986 (its plain mean difference reached 9 of 255, over the former limit of 8), as
# JPEG at quality 15 >= 0.88; every other scene <= 0.39; the test box scenes of seeds 0 and 1 0.90.
COMPARE_SIDE = 16
MIN_FRAME_CORRELATION = 0.95
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
    correlation = frame_correlation(frames, recon.frames)
    if correlation is not None and correlation < MIN_FRAME_CORRELATION:
        raise UserError(f"the reconstruction's frames differ from those of scene "
                        f"{scene.meta.get('scene_index', '?')} (correlation {correlation:.2f} on "
                        f"{COMPARE_SIDE}-pixel thumbnails; the scene through a lossy video codec keeps "
                        f"{MIN_FRAME_CORRELATION} or more): it reconstructs another video; pick the "
                        "scene that was reconstructed (--gt, --scene-index)")


def frame_correlation(scene: np.ndarray, video: np.ndarray) -> float | None:
    """The correlation of two videos of one size (T,h,w,3; 0..255) on thumbnails: each frame
    area-averaged to a long side of COMPARE_SIDE pixels, then centred per frame and colour.
    None where the scene's thumbnails are flat (under 1 grey level of spread): nothing to tell
    videos apart by."""
    h, w = scene.shape[1:3]
    scale = min(1.0, COMPARE_SIDE / max(h, w))
    size = (max(1, round(h * scale)), max(1, round(w * scale)))
    a, b = (_resize(np.asarray(v, np.float32), size, cv2.INTER_AREA) for v in (scene, video))
    a, b = (v - v.mean(axis=(1, 2), keepdims=True) for v in (a, b))
    if np.sqrt((a * a).mean()) < 1.0:
        return None
    return float((a * b).sum() / max(np.sqrt((a * a).sum() * (b * b).sum()), 1e-12))


def recorded_scene(report: dict) -> tuple[str, int] | None:
    """The generated scene a reconstruction was made from as its report.json records it: `c4d
    demo`'s `inputs.scene`, "SOURCE #I" (scene I of its `c4d datagen` folder SOURCE, in reading
    order), as (SOURCE, I). None where none is recorded: `c4d run` records the video it read
    (`inputs.video`), which does not say which scene that video shows."""
    text = report.get("inputs", {}).get("scene")
    source, sep, index = text.rpartition(" #") if isinstance(text, str) else ("", "", "")
    return (source, int(index)) if sep and index.isdigit() else None


def check_ground_truth(recon: Reconstruction, scene: Scene) -> None:
    """`UserError` unless `scene` is the generated scene `recon` was made from, the one check of
    every command that scores or draws a reconstruction against ground truth (`c4d eval-recon`,
    `c4d inspect --gt`, `c4d view --gt`): the scene that report.json records (`recorded_scene`)
    must be this one (its meta's `scene_index`, its place in a whole `c4d datagen` folder), then
    the input size and frames must match (`check_same_scene`; all there is to go by where no
    scene is recorded). A tolerant read (`c4d inspect`) without frames or depth is checked by its
    record alone."""
    recorded, index = recorded_scene(recon.report), scene.meta.get("scene_index")
    if recorded is not None and index is not None and recorded[1] != index:
        source, made_from = recorded
        raise UserError(f"the reconstruction was made from scene {made_from} of {source} "
                        f"(report.json, inputs.scene), not from scene {index}, the ground truth "
                        f"asked for (--gt, --scene-index); score it against its own: --gt {source} "
                        f"--scene-index {made_from}")
    if recon.frames is not None and recon.depth is not None:
        check_same_scene(recon, scene, scene_frame_indices(recon, scene.num_frames)[0])


def pick_scene(source: str, index: int) -> Scene:
    """The `index`-th scene (0-based, in reading order) of a shard source."""
    if index < 0:
        raise UserError(f"--scene-index must be >= 0, got {index}")
    scene = next(itertools.islice(read_scenes(source), index, None), None)
    if scene is None:
        raise UserError(f"{source} holds fewer than {index + 1} scenes; pick a smaller --scene-index")
    return scene


def pick_sequence(dataset: str, root: str | None, name: str | None) -> EvalSequence:
    """The sequence `name` of `dataset` under `root`, or its only sequence."""
    if root is None:
        raise UserError(f"--dataset {dataset} needs --root, the folder of the download")
    sequences = load_eval_dataset(dataset, root, None if name is None else [name])
    if len(sequences) != 1:
        raise UserError(f"{dataset} under {root} has {len(sequences)} sequences "
                        f"({', '.join(s.name for s in sequences)}); pick one with --sequence")
    return sequences[0]


def _resize(video: np.ndarray, hw: tuple[int, int], interpolation: int) -> np.ndarray:
    if video.shape[1:3] == tuple(hw):
        return video
    return np.stack([cv2.resize(frame, (hw[1], hw[0]), interpolation=interpolation) for frame in video])


def evaluate(recon: Reconstruction, scene: Scene, max_depth: float | None = None) -> dict:
    """All metrics of a reconstruction against its scene (see eval_metrics for conventions)."""
    check_reconstruction(recon)
    check_ground_truth(recon, scene)
    indices, origin = scene_frame_indices(recon, scene.num_frames)
    hw = scene.image_size
    result = _pose_and_depth(recon, indices, origin, hw, scene.cam_to_world[indices].astype(np.float64),
                             None if scene.depth is None else scene.depth[indices], max_depth)
    if scene.depth is not None and scene.segmentation is not None and scene.object_to_world is not None:
        gt_masks = ground_truth_motion_masks(scene)[indices]  # (T,H,W)
        pred_masks = _resize(recon.masks.astype(np.uint8), hw, cv2.INTER_NEAREST).astype(bool)
        result["mask"] = {**mask_iou(pred_masks, gt_masks), "gt_dynamic_fraction": float(gt_masks.mean())}
    return result


def evaluate_sequence(recon: Reconstruction, sequence: EvalSequence, max_depth: float | None = None) -> dict:
    """The pose and depth metrics of a reconstruction of a public benchmark sequence
    (`c4d_pipeline.eval_datasets`), where the sequence has them: no motion masks, and no check
    that the frames are the sequence's beyond their number. `max_depth` caps depth below the
    dataset's own cap."""
    check_reconstruction(recon)
    indices, origin = scene_frame_indices(recon, sequence.num_frames)
    depth = sequence.depths()[indices] if sequence.depth_paths is not None else None  # (T,H,W)
    hw = depth.shape[1:] if depth is not None else sequence.frames()[0].shape[:2]
    if tuple(hw) != tuple(recon.depth.shape[1:]) and abs(
            (recon.depth.shape[1] / recon.depth.shape[2]) / (hw[0] / hw[1]) - 1) > MAX_ASPECT_DIFFERENCE:
        raise UserError(f"the reconstruction is {recon.depth.shape[2]}x{recon.depth.shape[1]} pixels, "
                        f"{sequence.dataset} {sequence.name} {hw[1]}x{hw[0]}: their aspect ratios differ, so "
                        "the pixels cannot be compared; reconstruct the whole frames of this sequence")
    poses = None if sequence.cam_to_world is None else sequence.cam_to_world[indices].astype(np.float64)
    return _pose_and_depth(recon, indices, origin, hw, poses, depth, max_depth)


def _pose_and_depth(recon: Reconstruction, indices: list[int], origin: str, hw: tuple[int, int],
                    gt_cam_to_world: np.ndarray | None, gt_depth: np.ndarray | None,
                    max_depth: float | None) -> dict:
    """The compared frames, both resolutions, pose metrics against float64 (T,4,4) camera-to-world
    poses and depth metrics against (T,H,W) depth (0: unknown), each where given."""
    result = {
        "frame_indices": indices,
        "frame_indices_from": origin,
        "resolution": {"reconstruction": list(recon.depth.shape[1:]), "ground_truth": list(hw)},
    }
    if gt_cam_to_world is not None:
        result["pose"] = pose_metrics(recon.cam_to_world, gt_cam_to_world)
    if gt_depth is not None:
        pred_depth = _resize(recon.depth, hw, cv2.INTER_CUBIC)  # (T,H,W)
        result["depth"] = {mode: depth_metrics(pred_depth, gt_depth, mode, max_depth) for mode in DEPTH_ALIGNMENTS}
    return result
