"""Motion-mask quality on generated scenes: C4D's DynPT + flow masks vs the flow-only baseline.

    .venv/bin/python benchmarks/eval_c4d_masks.py --scenes SHARDS [--skip 0] [--max-scenes 8]
        [--tracker CKPT] [--thresholds 0.5,1,2] [--flow-only-thresholds 0.25,0.35,0.5]
        [--flows gt,dis] [--pair-sets all,1] [--no-flow-only] [--noise-sigmas 4]
        [--judge-out-of-view both] [--per-scene] [--config default] [key=value ...]

For every scene (the scene graph of configs/c4d/<--config>.yaml with its key=value overrides,
whose motion_mask.c4d settings the masks keep but for the swept ones) and every flow (exact 'gt'
and 'dis', or any `build_flow` spec such as 'dis:fast'), the masks of
  - C4D (sec. 3.2.2) with an ORACLE tracker: the scene's own tracks and mobility labels;
  - C4D with the oracle's tracks but every mobility set to static (what DynPT's mobility adds
    beyond LMedS's own robustness to moving points);
  - C4D with a REAL tracker (`--tracker`, a DynPT checkpoint), if given;
  - the flow-only baseline (MonST3R), its ego-flow from the pairwise pointmaps of the
    ground-truth pointmap source with its realistic noise and static-world bias (PnP per pair);
  - the flow-only baseline with ORACLE geometry (true depth, intrinsics and poses);
  - "every pixel dynamic" (the IoU is the share of dynamic pixels: the chance level);
each from all pairs of the graph and/or from the pairs of frames at most N apart (`--pair-sets
all,1,3`), are scored against the ground-truth masks (pixels that moved > the mobility threshold
since the previous frame) by IoU pooled over each scene's frames; the table gives the mean over
scenes for every threshold. With `--tracker`, the tracker's static points (mobility < 0.5,
visible) are also checked against the true masks: the share of them that lie on moving pixels
(what LMedS has to reject) and how many there are per frame, beside the oracle's. Prints
markdown, and the CPU seconds of each scene.
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
    static_points,
)
from c4d_pipeline.scene_graph import graph_from_config
from datagen import read_scenes


def floats(text: str) -> list[float]:
    return [float(x) for x in text.split(",")]


def static_point_check(tracks, truth: np.ndarray, cfg: MotionMaskConfig) -> dict[str, float]:
    """Of the static points a mask would use (all frames): how many per frame, and the share on
    truly moving pixels (nearest pixel of the true mask (T,H,W))."""
    on_moving, count = 0, 0
    height, width = truth.shape[1:]
    for t in range(len(truth)):
        xy = static_points(tracks, t, cfg)
        col = np.clip(np.rint(xy[:, 0]).astype(int), 0, width - 1)
        row = np.clip(np.rint(xy[:, 1]).astype(int), 0, height - 1)
        on_moving += int(truth[t, row, col].sum())
        count += len(xy)
    return {"static_per_frame": count / len(truth), "static_on_moving": on_moving / max(count, 1)}


def scene_scores(scene, cfg, args, tracker) -> tuple[dict, dict]:
    """IoU of every (method, flow, pair set, threshold) on one scene, and the static-point checks."""
    pairs = [tuple(int(v) for v in p) for p in graph_from_config(scene.num_frames, cfg.graph)]
    truth = ground_truth_motion_masks(scene)
    sc = scene
    egos = {}
    if not args.no_flow_only:
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
    base = MotionMaskConfig(**dict(cfg.motion_mask.c4d))
    checks = {name: static_point_check(tracks, truth, base) for name, tracks in trackers.items()
              if name != "C4D, mobility ignored"}
    scores = {("every pixel dynamic", "-", "-", 0.0): mask_iou(np.ones_like(truth), truth)["iou"]}
    for flow_name in args.flows:
        flows = build_flow(flow_name, scene=scene).flow(scene.rgb, pairs)
        for pair_set in args.pair_sets:  # all pairs of the graph, or those of frames <= N apart
            max_offset = 0 if pair_set == "all" else int(pair_set)
            used = [p for p, (i, j) in enumerate(pairs) if not max_offset or abs(i - j) <= max_offset]
            label = "all" if not max_offset else f"|i-j|<={max_offset}"
            for (name, tracks), threshold, sigmas, out_of_view in itertools.product(
                    trackers.items(), args.thresholds, args.noise_sigmas, args.judge_out_of_view):
                mask_cfg = replace(base, sampson_threshold_px=threshold, max_pair_offset=max_offset,
                                   noise_sigmas=sigmas, judge_out_of_view=out_of_view)
                masks = correspondence_motion_masks(tracks, flows, pairs, mask_cfg, scene.rgb).masks
                variant = name + (f", {sigmas:g} sigmas" if len(args.noise_sigmas) > 1 else "") + (
                    ", out of view judged" if out_of_view else "")
                scores[(variant, flow_name, label, threshold)] = mask_iou(masks, truth)["iou"]
            for (name, ego), threshold in itertools.product(egos.items(), args.flow_only_thresholds):
                masks = flow_only_motion_masks(flows[used], ego[used], [pairs[p] for p in used], scene.num_frames, threshold).masks
                scores[(name, flow_name, label, threshold)] = mask_iou(masks, truth)["iou"]
    return scores, checks


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", required=True, help="shards of generated scenes")
    parser.add_argument("--skip", type=int, default=0, help="start after this many scenes of the shards")
    parser.add_argument("--max-scenes", type=int, default=8)
    parser.add_argument("--tracker", default=None, help="DynPT checkpoint for the real-tracker rows")
    parser.add_argument("--thresholds", type=floats, default=floats("0.5,1,2"), help="Sampson thresholds, pixels")
    parser.add_argument("--flow-only-thresholds", type=floats, default=floats("0.25,0.35,0.5"))
    parser.add_argument("--flows", default="gt,dis", type=lambda s: s.split(","),
                        help="flow specs of c4d_pipeline.flow.build_flow, comma-separated")
    parser.add_argument("--pair-sets", default="all,1", type=lambda s: s.split(","),
                        help="'all' graph pairs and/or N: the pairs of frames at most N apart")
    parser.add_argument("--no-flow-only", action="store_true", help="skip the flow-only baseline rows")
    parser.add_argument("--noise-sigmas", type=floats, default=None,
                        help="values of motion_mask noise_sigmas to sweep (default: the config's)")
    parser.add_argument("--judge-out-of-view", choices=("no", "yes", "both"), default="no")
    parser.add_argument("--per-scene", action="store_true", help="also print every scene's IoUs")
    parser.add_argument("--config", default="default", help="configs/c4d/<name>.yaml: graph and mask settings")
    parser.add_argument("overrides", nargs="*", metavar="key=value", help="overrides of that config")
    args = parser.parse_args()
    cfg = load_config("c4d", args.config, overrides=args.overrides)
    args.noise_sigmas = args.noise_sigmas or [cfg.motion_mask.c4d.noise_sigmas]
    args.judge_out_of_view = {"no": [False], "yes": [True], "both": [False, True]}[args.judge_out_of_view]
    tracker = None
    if args.tracker:
        from dynpt import load_tracker

        tracker = load_tracker(args.tracker)
    per_scene, all_checks, fractions = [], [], []
    for scene in itertools.islice(read_scenes(args.scenes), args.skip, args.skip + args.max_scenes):
        start = time.process_time()
        scores, checks = scene_scores(scene, cfg, args, tracker)
        per_scene.append(scores)
        all_checks.append(checks)
        fractions.append(float(ground_truth_motion_masks(scene).mean()))
        print(f"scene {scene.meta.get('scene_index')}: {scene.num_frames} frames {scene.image_size}, "
              f"{100 * fractions[-1]:.1f}% dynamic pixels, {time.process_time() - start:.0f} CPU-s; static "
              "points per frame, share on moving pixels: " + "; ".join(
                  f"{k.removeprefix('C4D, ')} {v['static_per_frame']:.0f}, {100 * v['static_on_moving']:.1f}%"
                  for k, v in checks.items()), flush=True)
    print(f"\n{len(per_scene)} scenes; mean IoU (pooled over each scene's frames), std over scenes\n")
    keys = sorted(per_scene[0], key=lambda k: (k[1], k[2], k[0], k[3]))
    header = "| method | flow | pairs | threshold | IoU mean | IoU std |"
    if args.per_scene:
        header += "".join(f" scene {i} |" for i in range(len(per_scene)))
    print(header)
    print("|" + "---|" * (header.count("|") - 1))
    for key in keys:
        values = np.array([s[key] for s in per_scene])
        line = f"| {key[0]} | {key[1]} | {key[2]} | {key[3]:g} | {values.mean():.3f} | {values.std():.3f} |"
        if args.per_scene:
            line += "".join(f" {v:.3f} |" for v in values)
        print(line)


if __name__ == "__main__":
    main()
