"""Motion-mask quality on generated scenes: C4D's DynPT + flow masks vs the flow-only baseline.

    .venv/bin/python benchmarks/eval_c4d_masks.py --scenes SHARDS [--max-scenes 8]
        [--tracker CKPT] [--thresholds 0.5,1,2] [--flow-only-thresholds 0.25,0.35,0.5]

For every scene (the scene graph of configs/c4d/default.yaml) and every flow (exact 'gt' and
'dis'), the masks of
  - C4D (sec. 3.2.2) with an ORACLE tracker: the scene's own tracks and mobility labels;
  - C4D with the oracle's tracks but every mobility set to static (what DynPT's mobility adds
    beyond LMedS's own robustness to moving points);
  - C4D with a REAL tracker (`--tracker`, a DynPT checkpoint), if given;
  - the flow-only baseline (MonST3R), its ego-flow from the pairwise pointmaps of the
    ground-truth pointmap source with its realistic noise and static-world bias (PnP per pair);
  - the flow-only baseline with ORACLE geometry (true depth, intrinsics and poses);
each from all pairs of the graph and from the pairs of neighbouring frames only, are scored
against the ground-truth masks (pixels that moved > the mobility threshold since the
previous frame) by IoU pooled over each scene's frames; the table gives the mean over scenes
for every threshold. Prints markdown.
"""

from __future__ import annotations

import argparse
import itertools
import time
from dataclasses import replace

import numpy as np

from c4d_core.config import load_config
from c4d_pipeline.eval_metrics import mask_iou
from c4d_pipeline.flow import build_flow
from c4d_pipeline.ground_truth import GroundTruthPointmaps, ground_truth_motion_masks, oracle_tracks
from c4d_pipeline.motion_mask import (
    MotionMaskConfig,
    correspondence_motion_masks,
    ego_flow,
    flow_only_motion_masks,
    pairwise_ego_flow,
)
from c4d_pipeline.scene_graph import graph_from_config
from datagen import read_scenes


def floats(text: str) -> list[float]:
    return [float(x) for x in text.split(",")]


def scene_scores(scene, cfg, args, tracker) -> dict[tuple[str, str, float], float]:
    """IoU of every (method, flow, threshold) on one scene."""
    pairs = [tuple(int(v) for v in p) for p in graph_from_config(scene.num_frames, cfg.graph)]
    truth = ground_truth_motion_masks(scene)
    sc = scene
    pointmaps = GroundTruthPointmaps.from_config(sc, cfg.gt_pointmaps).pointmaps(sc.rgb, np.array(pairs))
    egos = {
        "flow-only (pointmap geometry)": np.stack([
            pairwise_ego_flow(pointmaps.pts_i[e], pointmaps.pts_j[e], pointmaps.conf_j[e], sc.intrinsics[j])
            for e, (_, j) in enumerate(pairs)
        ]),
        "flow-only (oracle geometry)": np.stack([
            ego_flow(sc.depth[i], sc.intrinsics[i], sc.intrinsics[j], sc.cam_to_world[i], sc.cam_to_world[j])
            for i, j in pairs
        ]),
    }
    oracle = oracle_tracks(scene)
    trackers = {
        "C4D, oracle tracker": oracle,
        "C4D, mobility ignored": replace(oracle, moving=np.zeros_like(oracle.moving)),  # every track static
    }
    if tracker is not None:
        trackers["C4D, DynPT tracker"] = tracker.track(scene.rgb)
    scores = {}
    for flow_name in ("gt", "dis"):
        flows = build_flow(flow_name, scene=scene).flow(scene.rgb, pairs)
        for max_offset in (0, 1):  # all pairs of the graph, or only those of neighbouring frames
            used = [p for p, (i, j) in enumerate(pairs) if not max_offset or abs(i - j) <= max_offset]
            pair_set = "all" if not max_offset else f"|i-j|<={max_offset}"
            for (name, tracks), threshold in itertools.product(trackers.items(), args.thresholds):
                mask_cfg = MotionMaskConfig(sampson_threshold_px=threshold, max_pair_offset=max_offset)
                masks = correspondence_motion_masks(tracks, flows, pairs, mask_cfg).masks
                scores[(name, flow_name, pair_set, threshold)] = mask_iou(masks, truth)["iou"]
            for (name, ego), threshold in itertools.product(egos.items(), args.flow_only_thresholds):
                masks = flow_only_motion_masks(flows[used], ego[used], [pairs[p] for p in used], scene.num_frames, threshold).masks
                scores[(name, flow_name, pair_set, threshold)] = mask_iou(masks, truth)["iou"]
    return scores


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", required=True, help="shards of generated scenes")
    parser.add_argument("--max-scenes", type=int, default=8)
    parser.add_argument("--tracker", default=None, help="DynPT checkpoint for the real-tracker rows")
    parser.add_argument("--thresholds", type=floats, default=floats("0.5,1,2"), help="Sampson thresholds, pixels")
    parser.add_argument("--flow-only-thresholds", type=floats, default=floats("0.25,0.35,0.5"))
    args = parser.parse_args()
    cfg = load_config("c4d", "default")
    tracker = None
    if args.tracker:
        from dynpt import load_tracker

        tracker = load_tracker(args.tracker)
    per_scene, fractions, start = [], [], time.perf_counter()
    for scene in itertools.islice(read_scenes(args.scenes), args.max_scenes):
        per_scene.append(scene_scores(scene, cfg, args, tracker))
        fractions.append(float(ground_truth_motion_masks(scene).mean()))
        print(f"scene {scene.meta.get('scene_index')}: {scene.num_frames} frames {scene.image_size}, "
              f"{100 * fractions[-1]:.1f}% dynamic pixels, {time.perf_counter() - start:.0f} s", flush=True)
    print(f"\n{len(per_scene)} scenes; mean IoU (pooled over each scene's frames), std over scenes\n")
    print("| method | flow | pairs | threshold | IoU mean | IoU std |")
    print("|---|---|---|---|---|---|")
    for key in sorted(per_scene[0], key=lambda k: (k[1], k[2], k[0], k[3])):
        values = np.array([s[key] for s in per_scene])
        print(f"| {key[0]} | {key[1]} | {key[2]} | {key[3]:g} | {values.mean():.3f} | {values.std():.3f} |")


if __name__ == "__main__":
    main()
