"""Where a DynPT checkpoint's mobility calls go right and wrong, on generated held-out scenes.

Usage:
    python benchmarks/eval_mobility.py --ckpt CKPT [--ckpt CKPT2 ...] \
        --data VAL/movi-e,EXTRA/movi-e [--data VAL/movi-e-panning,EXTRA/movi-e-panning ...] \
        [--calibrate CAL/movi-e --calibrate CAL/movi-e-panning] [--resolution 64] [--out FILE.md]

Each --data is one set (comma-separated shard sources pooled); the scenes are read as `c4d eval`
reads them (`eval.num_tracks` tracks per scene, queried at their first visible frame, the query
frame not counted). Per checkpoint and set, over every counted (frame, query) pair:
- D-ACC at p > 0.5 next to answering "static" everywhere, and the 95 % interval of their
  difference when the scenes are resampled (paired bootstrap); the best D-ACC over the thresholds
  0.05..0.95 (optimistic: the threshold is picked on the scenes it is scored on); average
  precision and ROC AUC of the mobility probability;
- with --calibrate (one source per --data): the threshold with the best D-ACC on those scenes
  instead, and the D-ACC it gives on the set;
- per kind of tracked point (background, resting object, tossed object, from the scenes'
  `track_object` and `objects[k].tossed`): its share of the pairs and of the moving pairs, the
  median / 90th-percentile track error on ground-truth-visible pairs, the share called moving,
  and the false alarms with the median track error of the visible ones.
docs/results/demo_mobility.md shows what these tables say about the demo's tracker.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from c4d_core.files import write_text
from dynpt.evaluate import TRACK_KINDS, load_eval_scenes, mobility_counted, track_item
from dynpt.inference import load_tracker
from dynpt.metrics import average_precision, dynamic_accuracy, paired_bootstrap_interval, roc_auc

THRESHOLDS = np.round(np.arange(0.05, 0.96, 0.05), 2)


def score(tracker, items: list[dict]) -> dict[str, np.ndarray]:
    """Per counted (frame, query) pair of every item, flat arrays: `p` mobility probability,
    `moving` label, `kind` (index into TRACK_KINDS), `visible` (ground truth), `error` px,
    `scene` (index of the item)."""
    parts = []
    for scene, item in enumerate(items):
        tracked = track_item(tracker, item, "first")
        if tracked is None:
            continue
        query_points, index, result = tracked
        counted = mobility_counted(query_points, result.moving)  # (T,M)
        error = np.linalg.norm(result.tracks - item["tracks"][:, index], axis=-1)  # (T,M) px
        pairs = {"p": result.moving, "moving": item["moving"][:, index],
                 "kind": np.broadcast_to(item["track_kind"][index], counted.shape),
                 "visible": ~item["occluded"][:, index], "error": error,
                 "scene": np.full(counted.shape, scene)}
        parts.append({k: v[counted] for k, v in pairs.items()})
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def d_acc(p: np.ndarray, moving: np.ndarray, threshold: float = 0.5) -> float:
    return dynamic_accuracy(p > threshold, moving)


def best_threshold(p: np.ndarray, moving: np.ndarray) -> tuple[float, float]:
    """(threshold, D-ACC) with the highest D-ACC over THRESHOLDS."""
    accs = [d_acc(p, moving, t) for t in THRESHOLDS]
    i = int(np.argmax(accs))
    return float(THRESHOLDS[i]), accs[i]


def difference_interval(s: dict) -> tuple[float, float]:
    """95 % interval of D-ACC (p > 0.5) minus all-static, scenes resampled (fractions)."""
    scenes = np.unique(s["scene"], return_inverse=True)[1]
    count = lambda weights: np.bincount(scenes, weights=weights.astype(np.float64))
    total = count(np.ones_like(s["moving"]))
    return paired_bootstrap_interval(count((s["p"] > 0.5) == s["moving"]), total,
                                     count(~s["moving"]), total)


def overall_line(s: dict, calibrated: float | None) -> str:
    threshold, best = best_threshold(s["p"], s["moving"])
    low, high = difference_interval(s)
    cells = [f"{len(s['p'])}", f"{100 * s['moving'].mean():.1f}", f"{100 * d_acc(s['p'], s['moving']):.2f}",
             f"{100 * (1 - s['moving'].mean()):.2f}", f"{100 * low:+.2f} to {100 * high:+.2f}",
             f"{100 * best:.2f} at {threshold}",
             f"{average_precision(s['p'], s['moving']):.3f}", f"{roc_auc(s['p'], s['moving']):.3f}"]
    if calibrated is not None:
        cells.append(f"{100 * d_acc(s['p'], s['moving'], calibrated):.2f} at {calibrated}")
    return " | ".join(cells)


def kind_lines(s: dict) -> list[str]:
    lines = []
    called = s["p"] > 0.5
    for k, name in enumerate(TRACK_KINDS):
        of_kind = s["kind"] == k
        if not of_kind.any():
            continue
        errors = s["error"][of_kind & s["visible"]]
        false = of_kind & called & ~s["moving"]
        false_err = s["error"][false & s["visible"]]
        lines.append(" | ".join([
            name, f"{100 * of_kind.mean():.1f}", f"{100 * s['moving'][of_kind].sum() / s['moving'].sum():.1f}",
            f"{np.median(errors):.2f} / {np.percentile(errors, 90):.2f}" if errors.size else "-",
            f"{100 * called[of_kind].mean():.1f}",
            f"{false.sum()} ({np.median(false_err):.1f} px)" if false_err.size else f"{false.sum()}"]))
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--ckpt", action="append", required=True, help="DynPT checkpoint (repeatable)")
    parser.add_argument("--data", action="append", required=True,
                        help="one set: shard sources, comma-separated (repeatable)")
    parser.add_argument("--calibrate", action="append", default=[],
                        help="per --data: sources on which the threshold is chosen")
    parser.add_argument("--resolution", type=int, default=64, help="eval resolution (square)")
    parser.add_argument("--num-tracks", type=int, default=256)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, help="also write the tables to this markdown file")
    args = parser.parse_args()
    if args.calibrate and len(args.calibrate) != len(args.data):
        parser.error("give one --calibrate per --data, or none")
    torch.set_num_threads(args.threads)
    eval_cfg = OmegaConf.create({"resolution": [args.resolution] * 2, "num_tracks": args.num_tracks,
                                 "seed": 0, "num_scenes": 0})
    load = lambda sources: [it for src in sources.split(",") for it in load_eval_scenes(src, eval_cfg)]
    sets = [load(d) for d in args.data]
    calibration = [load(c) for c in args.calibrate]
    head = ("| checkpoint | set | pairs | moving % | D-ACC (p>0.5) | all static | difference, 95 % interval "
            "| best D-ACC (threshold) "
            "| AP | AUC |" + (" D-ACC at the calibrated threshold |" if calibration else ""))
    overall = [head, "|" + "---|" * (head.count("|") - 1)]
    kinds = ["| checkpoint | set | point on | pairs % | of the moving % | track error median / p90 px "
             "| called moving % | false alarms (median error) |", "|" + "---|" * 8]
    for ckpt in args.ckpt:
        tracker = load_tracker(ckpt, "cpu")
        for i, (name, items) in enumerate(zip(args.data, sets)):
            s = score(tracker, items)
            calibrated = None
            if calibration:
                c = score(tracker, calibration[i])
                calibrated = best_threshold(c["p"], c["moving"])[0]
            overall.append(f"| {ckpt} | {name} | {overall_line(s, calibrated)} |")
            kinds += [f"| {ckpt} | {name} | {line} |" for line in kind_lines(s)]
            print(overall[-1], flush=True)
    text = "\n".join(overall) + "\n\n" + "\n".join(kinds) + "\n"
    print("\n" + text)
    if args.out:
        write_text(args.out, text)


if __name__ == "__main__":
    main()
