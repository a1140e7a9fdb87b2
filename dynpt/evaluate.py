"""Evaluating a DynPT tracker: D-ACC (mobility) and the TAP-Vid metrics.

Sources: datagen shards (a directory, shard or glob) or TAP-Vid DAVIS / Kinetics pickles
(dynpt.tapvid_data). Two protocols (`eval.protocol`) make a shard scene an evaluation item:
  - `scene`: the scene's own tracks; the video is resized to the eval resolution and
    `eval.num_tracks` tracks visible somewhere are chosen with a fixed seed; queries follow the
    TAP-Vid benchmark's 'first' or 'strided' mode;
  - `c4d-paper`, the paper's D-ACC protocol (its sec. 4: 24-frame 256x256 Kubric videos, 256
    tracks): the first 24 frames, 256 tracks drawn afresh from the scene's depth, segmentation and
    poses (object points from their object coordinates and 3-D boxes where the scene has them, as
    in Kubric's records) exactly as TAP-Vid-Kubric draws them
    (`datagen.annotate.tapvid_kubric_tracks`, seeded by `eval.seed` and the video's index), video
    and tracks resized to 256x256; each track is
    queried at its drawn point and scored on every other frame (the 'strided' rule).
TAP-Vid metrics are computed per video and averaged over videos. D-ACC pools every (query, frame)
pair of the source, except the query frame itself, and is also reported separately on
ground-truth moving and static pairs, with their mean (balanced) and the average precision of the
"moving" probability over the same pairs.
A corrupt or incomplete scene (or the unreadable rest of a truncated shard) is skipped with a
warning naming shard and scene; the report counts the skipped ones.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from pathlib import Path

import numpy as np

from c4d_core.draw import contact_sheet, draw_tracks_enlarged
from c4d_core.errors import UserError
from c4d_core.files import write_json, write_text
from c4d_core.geometry import swap_track_axes
from datagen.annotate import tapvid_kubric_tracks
from datagen.foreign import (SHARDS, mobility_labels, options_from, read_unit, source_kind,
                             source_units)
from datagen.shards import ForeignData, decode_scene, iter_samples, list_shards, lost_scenes
from dynpt.augment import resize_clip
from dynpt.metrics import (average_precision, dynamic_accuracy, paired_bootstrap_interval,
                           tapvid_metrics)
from dynpt.tapvid_data import read_tapvid, sample_queries

log = logging.getLogger(__name__)

EVAL_FIELDS = ("rgb", "tracks", "occluded", "moving", "meta", "track_object", "objects")
# The paper's D-ACC protocol: video length and size, tracks per video; the layers it draws from.
PAPER_FRAMES, PAPER_RESOLUTION, PAPER_TRACKS = 24, (256, 256), 256
PAPER_FIELDS = ("rgb", "meta", "objects", "depth", "segmentation", "intrinsics", "cam_to_world",
                "object_to_world", "object_coordinates", "instances")
TRACK_KINDS = ("background", "resting object", "tossed object")  # values of an item's `track_kind`
TABLE_KEYS = {  # summary key -> column title; values are shown in percent
    "d_acc": "D-ACC", "d_acc_moving": "D-ACC moving", "d_acc_static": "D-ACC static",
    "d_acc_balanced": "D-ACC balanced", "moving_ap": "AP moving",
    "average_jaccard": "AJ", "average_pts_within_thresh": "<δ avg", "occlusion_accuracy": "OA",
}


def track_kinds(scene, track_object: np.ndarray | None = None) -> np.ndarray | None:
    """int8 (N,) index into TRACK_KINDS of what each track lies on (the scene's own tracks, or
    `track_object` int (N,) of other tracks of the scene), or None without the labels."""
    track_object = scene.track_object if track_object is None else track_object
    if track_object is None or scene.objects is None:
        return None
    tossed = np.array([False] + [bool(o.get("tossed", False)) for o in scene.objects])
    kind = np.where(tossed[track_object], 2, 1)
    return np.where(track_object == 0, 0, kind).astype(np.int8)


def scene_item(scene, index: int, eval_cfg) -> dict:
    """A datagen Scene -> an evaluation item at the eval resolution with `num_tracks` tracks."""
    clip = {"rgb": scene.rgb, **scene.tracks_time_major()}
    size = tuple(eval_cfg.resolution)
    if scene.rgb.shape[1:3] != size:
        clip = resize_clip(clip, size)
    seen = np.flatnonzero((~clip["occluded"]).any(axis=0))
    rng = np.random.default_rng([eval_cfg.seed, index])
    chosen = np.sort(rng.choice(seen, min(eval_cfg.num_tracks, seen.size), replace=False))
    kinds = track_kinds(scene)
    return {"name": f"{scene.meta.get('preset', 'scene')}-{scene.meta.get('scene_index', index)}",
            "video": clip["rgb"], "tracks": clip["tracks"][:, chosen],
            "occluded": clip["occluded"][:, chosen],
            "moving": None if clip["moving"] is None else clip["moving"][:, chosen],
            "track_kind": None if kinds is None else kinds[chosen]}


class UnfitVideo(UserError):
    """A readable video that the evaluation protocol cannot score (e.g. too short): the whole
    evaluation stops, since skipping it would score another set than the protocol's."""


def paper_item(scene, index: int, eval_cfg) -> dict:
    """A datagen Scene -> an evaluation item of the paper's D-ACC protocol (module docstring):
    its first 24 frames, 256 TAP-Vid-Kubric tracks drawn at the video's own size with the seed
    [eval_cfg.seed, index] and labelled by `eval_cfg.mobility_rule` (a point's or its object's
    world motion), then resized to 256x256. The item adds `query_frame` int (N,)."""
    name = scene.name(index)
    if scene.num_frames < PAPER_FRAMES:
        raise UnfitVideo(f"{name} has {scene.num_frames} frames; the c4d-paper protocol scores "
                        f"{PAPER_FRAMES}-frame videos: generate them with `c4d datagen ... "
                        f"frames={PAPER_FRAMES}` (the movi presets' default)")
    t = PAPER_FRAMES
    scene = dataclasses.replace(
        scene, rgb=scene.rgb[:t], depth=scene.depth[:t], segmentation=scene.segmentation[:t],
        intrinsics=scene.intrinsics[:t], cam_to_world=scene.cam_to_world[:t],
        object_to_world=scene.object_to_world[:, :t],
        object_coordinates=None if scene.object_coordinates is None else scene.object_coordinates[:t],
        instances=None if scene.instances is None  # what the drawing reads of them
        else {"bbox_3d": scene.instances["bbox_3d"][:, :t]})
    drawn = tapvid_kubric_tracks(scene, [int(eval_cfg.seed), index], PAPER_TRACKS)
    moving = mobility_labels(drawn, scene.object_to_world, options_from(eval_cfg, eval_cfg.seed))
    clip = {"rgb": scene.rgb, "tracks": swap_track_axes(drawn.tracks),
            "occluded": swap_track_axes(drawn.occluded), "moving": swap_track_axes(moving)}
    if scene.image_size != PAPER_RESOLUTION:
        clip = resize_clip(clip, PAPER_RESOLUTION)
    return {"name": f"{scene.meta.get('preset', 'scene')}-{scene.meta.get('scene_index', index)}",
            "video": clip["rgb"], "tracks": clip["tracks"], "occluded": clip["occluded"],
            "moving": clip["moving"], "query_frame": drawn.query_frame.astype(np.int64),
            "track_kind": track_kinds(scene, drawn.track_object)}


def eval_fields(eval_cfg) -> tuple[str, ...]:
    """The scene layers an evaluation protocol reads."""
    return PAPER_FIELDS if eval_cfg.get("protocol") == "c4d-paper" else EVAL_FIELDS


def protocol_query_mode(eval_cfg) -> str:
    """How an evaluation under `eval_cfg` queries: 'sampled' (the drawn points) for c4d-paper,
    else `eval_cfg.query_mode`."""
    return "sampled" if eval_cfg.get("protocol") == "c4d-paper" else eval_cfg.query_mode


def make_item(scene, index: int, eval_cfg) -> dict:
    """A datagen Scene -> an evaluation item by `eval_cfg.protocol` (module docstring)."""
    if eval_cfg.get("protocol") == "c4d-paper":
        return paper_item(scene, index, eval_cfg)
    return scene_item(scene, index, eval_cfg)


def load_eval_scenes(source, eval_cfg, skipped: list[str] | None = None) -> list[dict]:
    """The first `eval_cfg.num_scenes` (0: all) readable scenes of a shard source as evaluation
    items. Unreadable ones are skipped with a warning; their errors are appended to `skipped`.
    Other projects' Kubric data is read by `load_foreign_scenes`."""
    if source_kind(source) != SHARDS:
        return load_foreign_scenes(source, eval_cfg, skipped)
    items: list[dict] = []
    skipped = [] if skipped is None else skipped

    def skip(exc: UserError) -> None:
        log.warning("skipping a bad evaluation scene: %s", exc)
        skipped.append(str(exc))

    for shard in list_shards(source):
        read = 0
        try:
            for read, raw in enumerate(iter_samples(shard, eval_fields(eval_cfg)), 1):
                if eval_cfg.num_scenes and len(items) >= eval_cfg.num_scenes:
                    return items
                try:
                    scene = decode_scene(raw, eval_fields(eval_cfg))
                except UserError as exc:
                    skip(exc)
                    continue
                items.append(make_item(scene, len(items) + len(skipped), eval_cfg))
        except UnfitVideo:
            raise
        except ForeignData as exc:  # not part of the dataset: refused, or skipped on request
            if eval_cfg.foreign != "skip":
                raise UserError(f"{exc} (or set eval.foreign=skip to skip such shards with a "
                                "warning)") from None
            log.warning("skipping the rest of a shard of another dataset: %s", exc)
        except UserError as exc:  # a truncated or damaged tar: its rest is lost
            skip(exc)
            skipped.extend([str(exc)] * (lost_scenes(shard, read) - 1))  # one per scene lost
    return items


def load_source(source: str, eval_cfg, skipped: list[str] | None = None) -> tuple[list[dict], str]:
    """Evaluation items of a shard source (its first `eval_cfg.num_scenes`, 0: all; the errors of
    skipped scenes are appended to `skipped`) or of a TAP-Vid pickle source (all its videos: a
    benchmark's figures are over all of them, so a `num_scenes` is refused), and its kind."""
    text = os.fspath(source)
    if text.endswith(".pkl") or (Path(text).is_dir() and any(Path(text).glob("*.pkl"))):
        if eval_cfg.get("protocol") == "c4d-paper":
            raise UserError(f"the c4d-paper protocol draws its tracks from a scene's depth, "
                            f"segmentation and poses, which a TAP-Vid benchmark ({text}) lacks: "
                            "score it without --protocol")
        if eval_cfg.get("num_scenes"):
            raise UserError(f"eval.num_scenes={eval_cfg.num_scenes} is for datagen shards; a TAP-Vid "
                            f"benchmark ({text}) is scored on all its videos, as its published "
                            "figures are: leave eval.num_scenes out")
        return list(read_tapvid(text, tuple(eval_cfg.resolution))), "tapvid"
    kind = source_kind(text)  # a UserError naming every kind expected for a folder of none
    if kind == SHARDS:
        list_shards(text)  # a clear UserError if there are no shards
    return load_eval_scenes(text, eval_cfg, skipped), kind


def load_foreign_scenes(source, eval_cfg, skipped: list[str] | None = None) -> list[dict]:
    """The first `eval_cfg.num_scenes` (0: all) scenes of other projects' Kubric data
    (`datagen.foreign`: TFDS MOVi records, CoTracker or Kubric worker folders) as evaluation items,
    made by the protocol as shard scenes are; tracks the data lacks are drawn with `eval.seed`
    (mobility by `eval.mobility_rule`, "point" unless set). A damaged scene stops the evaluation
    with one line naming it, or with `eval.foreign=skip` is skipped with a warning and its error
    appended to `skipped`."""
    items: list[dict] = []
    skipped = [] if skipped is None else skipped
    options = options_from(eval_cfg, eval_cfg.seed, eval_fields(eval_cfg))
    for unit in source_units(source):
        if eval_cfg.num_scenes and len(items) >= eval_cfg.num_scenes:
            break
        try:
            scene = read_unit(unit, options)
        except UserError as exc:
            if eval_cfg.foreign != "skip":
                raise UserError(f"{exc} (or set eval.foreign=skip to skip such scenes with a "
                                "warning)") from None
            log.warning("skipping a damaged evaluation scene: %s", exc)
            skipped.append(str(exc))
            continue
        items.append(make_item(scene, unit.index, eval_cfg))
    return items


def track_item(tracker, item: dict, query_mode: str):
    """Query `item`'s tracks by the benchmark's mode ('first', 'strided'), or at the points the
    c4d-paper protocol drew ('sampled', the item's `query_frame`), and track them.

    Returns (query_points (M,3) as (t, y, x), index (M,) of the queried tracks, TrackResult), or
    None when no track is visible.
    """
    if query_mode == "sampled":  # the protocol's drawn points, each visible at its query frame
        index = np.arange(item["tracks"].shape[1])
        xy = item["tracks"][item["query_frame"], index]  # (N,2)
        query_points = np.stack([item["query_frame"], xy[:, 1], xy[:, 0]], 1).astype(np.float32)
    else:
        query_points, index = sample_queries(item["occluded"], item["tracks"], query_mode)
    if len(index) == 0:
        log.warning("%s: no visible track to query; skipped", item["name"])
        return None
    return query_points, index, tracker.track(item["video"], query_points[:, [0, 2, 1]])  # (t,x,y)


def mobility_counted(query_points: np.ndarray, moving: np.ndarray) -> np.ndarray:
    """bool (T,M): the (frame, query) pairs D-ACC counts, every predicted one but the query frame."""
    counted = np.arange(len(moving))[:, None] != query_points[None, :, 0]  # (T,M)
    return counted & np.isfinite(moving)


PER_VIDEO_ONLY = ("name", "num_queries", "d_acc", "d_acc_right", "d_acc_counted")  # not averaged


def evaluate_items(tracker, items: list[dict], query_mode: str) -> dict:
    """Run `tracker.track` on every item; per-video TAP-Vid metrics, pooled D-ACC, an example.

    Returns {'summary': {key: float}, 'per_video': [{name, metrics...}], 'example': {...}}.
    """
    return score_items(items, [track_item(tracker, item, query_mode) for item in items], query_mode)


def score_items(items: list[dict], tracked: list, query_mode: str) -> dict:
    """`evaluate_items`'s scores of `items` from their `track_item` results `tracked` (one per
    item, None where nothing was tracked), so one tracking pass can be scored more than once."""
    per_video, correct = [], {"moving": [0, 0], "static": [0, 0]}  # split -> [right, counted]
    scores, labels = [], []  # the counted pairs' "moving" probabilities and truths
    metrics_mode = "strided" if query_mode == "sampled" else query_mode  # every frame but the query's
    example = None
    for item, done in zip(items, tracked):
        if done is None:
            continue
        query_points, index, result = done
        gt_tracks = swap_track_axes(item["tracks"][:, index])[None]  # (1,M,T,2)
        gt_occ = swap_track_axes(item["occluded"][:, index])[None]  # (1,M,T)
        pred_occ = ~swap_track_axes(result.visible)[None]  # (1,M,T)
        with np.errstate(invalid="ignore", divide="ignore"):
            metrics = tapvid_metrics(query_points[None], gt_occ, gt_tracks, pred_occ,
                                     swap_track_axes(result.tracks)[None], metrics_mode)
        row = {"name": item["name"], "num_queries": int(len(index)),
               **{k: float(v[0]) for k, v in metrics.items()}}
        if item["moving"] is not None:
            gt_moving = item["moving"][:, index]  # (T,M)
            counted = mobility_counted(query_points, result.moving)  # (T,M)
            pred = result.moving > 0.5
            scores.append(result.moving[counted])
            labels.append(gt_moving[counted])
            for split, mask in (("moving", counted & gt_moving), ("static", counted & ~gt_moving)):
                correct[split][0] += int(((pred == gt_moving) & mask).sum())
                correct[split][1] += int(mask.sum())
            row["d_acc"] = dynamic_accuracy(pred, gt_moving, counted)
            row["d_acc_right"] = int(((pred == gt_moving) & counted).sum())  # pooled, and intervals
            row["d_acc_counted"] = int(counted.sum())
        per_video.append(row)
        if example is None:
            example = {"video": item["video"], "tracks": result.tracks, "visible": result.visible,
                       "moving": result.moving}
    if not per_video:
        raise UserError("no evaluable video: every video lacks visible tracks")
    summary = {k: float(np.mean([r[k] for r in per_video]))
               for k in per_video[0] if k not in PER_VIDEO_ONLY}
    if items and items[0]["moving"] is not None:
        correct["all"] = [sum(r["d_acc_right"] for r in per_video),
                          sum(r["d_acc_counted"] for r in per_video)]
        for split, key in (("all", "d_acc"), ("moving", "d_acc_moving"), ("static", "d_acc_static")):
            right, total = correct[split]
            summary[key] = right / total if total else float("nan")
        # D-ACC pools pairs, so it is dominated by the (usually ~90%) static ones; the mean of the
        # per-class accuracies is 50% for any constant answer.
        summary["d_acc_balanced"] = (summary["d_acc_moving"] + summary["d_acc_static"]) / 2
        scores, labels = np.concatenate(scores), np.concatenate(labels)
        # A constant score (all static) ranks nothing: its AP is the share of moving pairs.
        summary["moving_ap"] = (average_precision(scores, labels) if 0 < labels.sum() < labels.size
                                else float("nan"))
    summary["num_videos"] = len(per_video)
    return {"summary": summary, "per_video": per_video, "example": example}


def d_acc_difference_interval(result: dict, baseline: dict, level: float = 0.95) -> list[float] | None:
    """[low, high] (fractions) of pooled D-ACC of `result` minus `baseline`, both from
    `evaluate_items` on the same videos, when the videos are resampled (paired bootstrap,
    `dynpt.metrics.paired_bootstrap_interval`); None without mobility labels."""
    theirs = {r["name"]: r for r in baseline["per_video"] if "d_acc_counted" in r}
    pairs = [(r, theirs[r["name"]]) for r in result["per_video"] if r["name"] in theirs
             and "d_acc_counted" in r]
    if not pairs:
        return None
    a, b = zip(*pairs)
    counts = [[r[k] for r in rows] for rows in (a, b) for k in ("d_acc_right", "d_acc_counted")]
    return list(paired_bootstrap_interval(*counts, level=level))


def evaluate_model(model, items: list[dict], eval_cfg, device) -> dict:
    """`evaluate_items` for an in-memory model (used by training's validation), queried as
    `eval_cfg`'s protocol says."""
    from dynpt.inference import Tracker

    return evaluate_items(Tracker(model, device), items, protocol_query_mode(eval_cfg))


def track_image(example: dict, num_frames: int = 4, min_height: int = 256) -> np.ndarray:
    """Predicted tracks on `num_frames` frames, coloured by predicted mobility: uint8 (H,W,3).

    Small videos are enlarged (nearest neighbour, integer factor) to at least `min_height` rows.
    """
    frames = np.linspace(0, len(example["video"]) - 1, num_frames).round().astype(int)
    drawn = draw_tracks_enlarged(example["video"][frames], example["tracks"][frames],
                                 example["visible"][frames], np.nan_to_num(example["moving"][frames]),
                                 min_height=min_height, legend=True)
    return contact_sheet(drawn, columns=num_frames, labels=[f"t={t}" for t in frames])


def signed(value: float, digits: int = 1) -> str:
    """`value` with its sign and `digits` decimals; one that rounds to zero is "+0.0", never "-0.0"."""
    text = f"{value:+.{digits}f}"
    return f"{0.0:+.{digits}f}" if float(text) == 0 else text


def interval_verdict(low: float, high: float) -> str:
    """What a 95 % interval [low, high] of a difference (method minus baseline) says of the method:
    "above" the baseline only when the whole interval is above 0, "below" when it is all below,
    "within the variation" when it holds 0."""
    return "above" if low > 0 else "below" if high < 0 else "within the variation"


def markdown_table(rows: dict[str, dict], title: str) -> str:
    """Markdown table (percent), one row per {name: summary}, e.g. the tracker and a baseline."""
    first = next(iter(rows.values()))
    keys = [k for k in TABLE_KEYS if k in first]
    head = ("| source | tracker | videos | skipped | " + " | ".join(TABLE_KEYS[k] for k in keys)
            + " |")
    rule = "|---|---|---|---|" + "---|" * len(keys)
    lines = [head, rule]
    for name, summary in rows.items():
        cells = " | ".join(f"{100 * summary[k]:.1f}" for k in keys)
        lines.append(f"| {title} | {name} | {summary['num_videos']} | "
                     f"{summary.get('num_skipped', 0)} | {cells} |")
    return "\n".join(lines) + "\n"


def write_report(result: dict, baseline: dict, out_dir: str | Path, title: str,
                 info: dict) -> tuple[Path, Path]:
    """`eval.json` (summary, per video, the zero-motion baseline's summary and per video, the
    interval of the D-ACC difference, `info`) and `eval.md` (both summaries, the interval) in
    `out_dir`, both atomically. `result` and `baseline` come from `evaluate_items`."""
    out = Path(out_dir)
    interval = d_acc_difference_interval(result, baseline)
    payload = {"info": info, "summary": result["summary"], "per_video": result["per_video"],
               "zero_motion": baseline["summary"], "zero_motion_per_video": baseline["per_video"],
               "d_acc_difference_interval": interval}
    text = markdown_table({"checkpoint": result["summary"],
                           "zero motion, all static": baseline["summary"]}, title)
    if interval is not None:
        diff = 100 * (result["summary"]["d_acc"] - baseline["summary"]["d_acc"])
        verdict = {"above": "so it beats all-static", "below": "so it is below all-static",
                   "within the variation": "so the difference is within the variation over the "
                                           "videos"}[interval_verdict(*interval)]
        text += (f"\nD-ACC minus all-static: {signed(diff)} points; 95 % interval over the videos "
                 f"(paired bootstrap): {signed(100 * interval[0])} to {signed(100 * interval[1])}, "
                 f"{verdict}.\n")
    return write_json(out / "eval.json", payload), write_text(out / "eval.md", text)
