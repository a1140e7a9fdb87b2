"""`c4d eval-recon`: score a reconstruction directory against ground truth.

Reads OUT (as `c4d run` writes it) and either one scene of a generated shard source (`--gt`,
`--scene-index`) or one sequence of a public benchmark on disk (`--dataset NAME --root DIR
[--sequence SEQ]`, the readers and layouts of `c4d_pipeline.eval_datasets`), and writes a JSON of
the pose, depth and motion-mask metrics (`c4d_pipeline.eval_recon`; a benchmark sequence has no
motion masks, and poses or depth only where the dataset has them). The JSON records which frames
were compared.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from c4d_core.errors import UserError
from c4d_core.files import write_json
from c4d_core.ownership import JSON_KEY, check_file
from c4d_pipeline.eval_datasets import LOADERS
from c4d_pipeline.eval_recon import evaluate, evaluate_sequence, pick_scene, pick_sequence
from c4d_pipeline.outputs import read_reconstruction


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--pred", required=True, help="reconstruction directory written by `c4d run`")
    truth = parser.add_mutually_exclusive_group(required=True)
    truth.add_argument("--gt", help="shard directory, shard, or glob of generated scenes")
    truth.add_argument("--dataset", choices=tuple(LOADERS),
                       help="a public benchmark in its download layout under --root (the layouts: "
                       "c4d_pipeline/eval_datasets.py)")
    parser.add_argument("--scene-index", type=int, default=0, help="which scene of --gt, 0-based in reading order")
    parser.add_argument("--root", help="the --dataset's folder")
    parser.add_argument("--sequence", help="which sequence of --dataset (default: its only one)")
    parser.add_argument("--out", default=None, help="JSON file to write (default: PRED/eval_recon.json)")
    parser.add_argument("--max-depth", type=float, default=None, help="ignore ground-truth depth at or beyond this")


def run(args: argparse.Namespace) -> int:
    if args.max_depth is not None and not args.max_depth > 0:  # NaN too
        raise UserError(f"--max-depth must be a positive depth (ground truth at or beyond it is "
                        f"ignored), got {args.max_depth:g}; leave it out to use every depth")
    out = check_file(Path(args.out) if args.out else Path(args.pred) / "eval_recon.json",
                     "eval-recon", args.overwrite)
    recon = read_reconstruction(args.pred)
    if args.dataset is not None:
        sequence = pick_sequence(args.dataset, args.root, args.sequence)
        result = {"pred": str(args.pred), "dataset": args.dataset, "root": str(args.root),
                  "sequence": sequence.name, **evaluate_sequence(recon, sequence, args.max_depth)}
    else:
        scene = pick_scene(args.gt, args.scene_index)
        result = {"pred": str(args.pred), "gt": str(args.gt), "scene_index": args.scene_index,
                  "scene_meta": scene.meta, **evaluate(recon, scene, args.max_depth)}
    write_json(out, {JSON_KEY: "eval-recon", **result})
    print(f"frames {len(result['frame_indices'])} ({result['frame_indices_from']})")
    if "pose" in result:
        pose = result["pose"]
        print(f"pose   ATE {pose['ate']:.4f}  RPE trans {pose['rpe_trans']:.4f}  RPE rot {pose['rpe_rot']:.3f} deg")
    for mode, d in result.get("depth", {}).items():
        print(f"depth  {mode:<11} Abs Rel {d['abs_rel']:.4f}  RMSE {d['rmse']:.4f}  delta<1.25 {d['delta_1_25']:.4f}")
    if "mask" in result:
        print(f"mask   IoU {result['mask']['iou']:.4f}  (per-frame mean {result['mask']['iou_frame_mean']:.4f})")
    print(f"wrote {out}")
    return 0

