"""How much tracking accuracy the paper's D-ACC labels ask for: the epipolar cue on true tracks
with noise, on a tracker's tracks, and the tracker's own mobility head.

Usage:
    python benchmarks/mobility_cue.py --data PAPER/movi-e [--data PAPER/movi-e-panning ...] \
        [--ckpt CKPT] [--noise 0,0.25,0.5,1,2] [--out FILE.md]

Each --data is a shard source scored as `c4d eval --protocol c4d-paper` scores it (24 frames,
256 TAP-Vid-Kubric tracks a video at 256x256, the query frame not counted). A point-frame is
"moving" when its world point moved since the frame before (`datagen.annotate.world_motion`), so
the labels follow from geometry: a point that moves in the world leaves the epipolar geometry
the static scene gives the camera. The cue of point-frame (t, n) is the Sampson distance (px) of
the track's positions at frames t-1 and t+1 (clipped to the video) to the fundamental matrix
fitted by LMedS to all tracks visible in both (`c4d_pipeline.motion_mask`, as C4D's masks fit
it). Per set, over the counted point-frames, the ROC AUC and average precision of the cue, and
the best balanced D-ACC any threshold gives (optimistic: picked on the scored points):
- on the true tracks, with i.i.d. Gaussian noise of each --noise sigma (px, per coordinate,
  seeded) added: the tracking accuracy the labels need;
- with --ckpt: on that tracker's tracks, and the tracker's own mobility probability, with the
  median track error of moving and static visible point-frames; and the cue pooled over each
  track's frames as `dynpt/track_mobility.py` pools it (its default settings), alone (head
  weight 0) and fused with the head, as `c4d eval ... eval.mobility=epipolar` scores it; and the
  tracks refined by Lucas-Kanade (`dynpt/refine.py`), fused on the positions it confirmed, as the
  demo's paper-eval step scores them (configs/demo/default.yaml `eval.paper_overrides`), with the
  refined tracks' median errors.
It also gives how far moving point-frames move in the image (px a frame, true tracks).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from c4d.demo import paper_eval_config
from c4d_core.config import load_config
from c4d_core.epipolar import fundamental_lmeds, sampson_distance
from c4d_core.files import write_text
from dynpt.evaluate import load_source, mobility_counted, track_item
from dynpt.inference import load_tracker
from dynpt.metrics import average_precision, roc_auc
from dynpt.postprocess import Postprocess
from dynpt.track_mobility import EpipolarMobility, fuse_mobility

THRESHOLD_QUANTILES = np.linspace(0.01, 0.99, 99)
# the cue pooled over time by dynpt/track_mobility.py (its default settings), alone and fused
POOLED = {"tracker pooled": EpipolarMobility(head_weight=0.0), "tracker fused": EpipolarMobility()}
POOLED_LABELS = {"tracker pooled": "epipolar cue pooled over time, tracker's tracks",
                 "tracker fused": "the same plus the head (eval.mobility=epipolar)",
                 "refined fused": "refined by Lucas-Kanade, fused as the demo's paper-eval step"}


def epipolar_cue(tracks: np.ndarray, visible: np.ndarray, seed: int = 0) -> np.ndarray:
    """float (T,N) Sampson distance (px) of each track between frames t-1 and t+1 to the
    fundamental matrix of all tracks visible in both; NaN where no matrix is found.
    tracks (T,N,2) px, visible bool (T,N)."""
    T = len(tracks)
    cue = np.full(visible.shape, np.nan)
    for t in range(T):
        a, b = max(t - 1, 0), min(t + 1, T - 1)
        both = visible[a] & visible[b]
        fitted = fundamental_lmeds(tracks[a, both], tracks[b, both], seed + t)
        if fitted is not None:
            cue[t] = sampson_distance(fitted[0], tracks[a].astype(np.float64), tracks[b].astype(np.float64))
    return cue


def best_balanced(scores: np.ndarray, labels: np.ndarray) -> float:
    """The best mean of the per-class accuracies of `scores > q` over the scores' percentiles."""
    best = 0.0
    for q in np.quantile(scores, THRESHOLD_QUANTILES):
        called = scores > q
        best = max(best, (called[labels].mean() + (~called[~labels]).mean()) / 2)
    return float(best)


def ranking(scores: np.ndarray, labels: np.ndarray) -> dict[str, float]:
    return {"auc": roc_auc(scores, labels), "ap": average_precision(scores, labels),
            "best_balanced": best_balanced(scores, labels)}


def image_motion(tracks: np.ndarray) -> np.ndarray:
    """float (T,N) px a frame of true tracks (T,N,2), over frames t-1..t+1 (clipped)."""
    T = len(tracks)
    after, before = np.minimum(np.arange(T) + 1, T - 1), np.maximum(np.arange(T) - 1, 0)
    return np.linalg.norm(tracks[after] - tracks[before], axis=-1) / np.maximum(after - before, 1)[:, None]


def measure(items: list[dict], noises: list[float], tracker, paper_post: Postprocess,
            seed: int) -> dict:
    rng = np.random.default_rng(seed)
    pooled: dict[str, list[np.ndarray]] = {}

    def add(key: str, values: np.ndarray) -> None:
        pooled.setdefault(key, []).append(values)

    for item in items:
        truth = item["tracks"].astype(np.float64)  # (T,N,2)
        visible = ~item["occluded"]  # (T,N)
        query = np.stack([item["query_frame"], np.zeros(len(item["query_frame"]))], 1)
        counted = mobility_counted(query, np.zeros(visible.shape)) & visible  # (T,N)
        add("moving", item["moving"][counted])
        add("motion", image_motion(truth)[counted])
        for sigma in noises:
            noisy = truth + rng.normal(0.0, sigma, truth.shape)
            add(f"noise {sigma}", epipolar_cue(noisy, visible, seed)[counted])
        if tracker is not None:
            _, _, result = track_item(tracker, item, "sampled")  # every drawn point, (T,N)
            add("tracker cue", epipolar_cue(result.tracks.astype(np.float64), result.visible, seed)[counted])
            add("tracker head", result.moving[counted])
            for key, settings in POOLED.items():
                add(key, fuse_mobility(result.tracks, result.visible, result.moving, settings, seed)[counted])
            add("tracker error", np.linalg.norm(result.tracks - truth, axis=-1)[counted])
            refined = paper_post(result, item["video"])  # refined tracks, fused mobility
            add("refined fused", refined.moving[counted])
            add("refined error", np.linalg.norm(refined.tracks - truth, axis=-1)[counted])
    flat = {k: np.concatenate(v) for k, v in pooled.items()}
    labels = flat["moving"].astype(bool)
    rows = {}
    for key in [f"noise {s}" for s in noises] + (["tracker cue", "tracker head", *POOLED, "refined fused"]
                                                  if tracker else []):
        scores, ok = flat[key], np.isfinite(flat[key])
        rows[key] = ranking(scores[ok], labels[ok])
    motion = flat["motion"][labels]
    extra = {"moving_share": float(labels.mean()),
             "moving_motion_below": {px: float((motion < px).mean()) for px in (0.5, 1.0, 2.0)}}
    if tracker is not None:
        extra["median_error"], extra["refined_median_error"] = (
            {"moving": float(np.median(flat[key][labels])), "static": float(np.median(flat[key][~labels]))}
            for key in ("tracker error", "refined error"))
    return {"rows": rows, **extra}


def markdown(name: str, result: dict) -> str:
    lines = [f"### {name}", "",
             f"{100 * result['moving_share']:.1f} % of the counted visible point-frames move; of "
             "those, " + ", ".join(f"{100 * v:.0f} % move less than {px:g} px a frame" for px, v in
                                   result["moving_motion_below"].items()) + " in the image.", ""]
    if "median_error" in result:
        e = result["median_error"]
        r = result["refined_median_error"]
        lines += [f"The tracker's median error: {e['moving']:.1f} px on moving, {e['static']:.1f} px "
                  f"on static visible point-frames; refined by Lucas-Kanade {r['moving']:.1f} px and "
                  f"{r['static']:.2f} px.", ""]
    lines += ["| scores | ROC AUC | AP moving | best balanced D-ACC |", "|---|---|---|---|"]
    for key, r in result["rows"].items():
        label = {"tracker cue": "epipolar cue, tracker's tracks",
                 "tracker head": "tracker's mobility head", **POOLED_LABELS}.get(key, f"epipolar cue, true tracks + "
                                                                   f"{key.split()[1]} px noise")
        lines.append(f"| {label} | {r['auc']:.3f} | {r['ap']:.3f} | {100 * r['best_balanced']:.1f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", action="append", required=True, help="a shard source (repeatable)")
    parser.add_argument("--ckpt", help="a DynPT checkpoint: also its tracks and mobility head")
    parser.add_argument("--noise", default="0,0.25,0.5,1,2", help="comma-separated sigmas, px")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, help="write the tables here (markdown)")
    args = parser.parse_args()
    torch.manual_seed(args.seed)
    eval_cfg = load_config("dynpt", "tiny-cpu", overrides=["eval.protocol=c4d-paper",
                                                           "eval.num_scenes=0"]).eval
    tracker = load_tracker(args.ckpt, "cpu") if args.ckpt else None
    # refined, then fused on the positions Lucas-Kanade confirmed, as the demo's paper-eval step
    # scores it (configs/demo/default.yaml eval.paper_overrides)
    paper_post = Postprocess.from_config(paper_eval_config(load_config("demo", "default")))
    noises = [float(s) for s in args.noise.split(",")]
    text = ""
    for source in args.data:
        items, _ = load_source(source, eval_cfg)
        text += markdown(f"{source} ({len(items)} videos)", measure(items, noises, tracker, paper_post, args.seed)) + "\n"
        print(text, flush=True)
    if args.out:
        write_text(args.out, text)


if __name__ == "__main__":
    main()
