"""Ablation of the C4D objectives on generated scenes (the paper's Table 6 on our data).

For every scene and static-world-bias setting, the same inputs (ground-truth pointmaps with noise,
optical flow, C4D motion masks from the oracle tracker's mobility + flow, the scene's 2-D tracks
for PTS; with `--tracker CKPT` a trained DynPT's tracks and mobility instead of the oracle's, as
`c4d run` and `c4d demo` use them) go through the variants of configs/c4d/ablation/objectives.yaml (the table's rows and
their c4d config overrides):
  GA only   stage 1 with GA alone, no stage 2 (DUSt3R-style global alignment)
  w/o CMA   GA + CTS, then PTS
  w/o CTS   GA + CMA, then PTS
  w/o PTS   GA + CMA + CTS, no stage 2 (the full run's stage-1 depth)
  C4D       GA + CMA + CTS, then PTS
and is scored with ATE / RPE trans / RPE rot (Sim(3)-aligned) and video depth Abs Rel / RMSE /
delta < 1.25 (per-sequence scale-and-shift alignment). Results are cached per (scene, bias) in
OUT/runs/ so an interrupted run resumes; OUT/ablation.json and OUT/ablation.md hold the tables.

    python -m c4d_pipeline.ablation [--dynamic DIR] [--static DIR] --out OUT [--size 64]
        [--stride S] [--frames N] [--preset default] [--flow gt] [--masks c4d|gt] [--tracker CKPT]
        [--bias on,off] [--variants "GA only,w/o CMA,w/o CTS,C4D"] [key=value ...]
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from c4d_core.config import load_config, to_dict
from c4d_core.errors import UserError
from c4d_core.files import write_json, write_text
from c4d_core.geometry import rescale_pixels
from c4d_pipeline.eval_metrics import depth_metrics, mask_iou, pose_metrics
from c4d_pipeline.flow import build_flow
from c4d_pipeline.ground_truth import (ground_truth_motion_masks, oracle_tracks, resize_intrinsics,
                                       resize_nearest)
from c4d_pipeline.motion_mask import MotionMaskConfig, correspondence_motion_masks, track_arrays
from c4d_pipeline.optimize import optimise
from c4d_pipeline.pointmap_sources import build_pointmaps
from c4d_pipeline.scene_graph import graph_from_config
from datagen.scene import Scene

log = logging.getLogger("c4d.ablation")


def read_variants(table: str | Path = "objectives") -> tuple[tuple[str, ...], dict[str, list[str]],
                                                            dict[str, str]]:
    """The ablation's rows from a YAML of configs/c4d/ablation/ (a name) or a path, checked:
    (every row in the table's order, {run row: its c4d overrides}, {row: the run whose stage-1
    depth it reports}). Every run's overrides must load over the default c4d config."""
    rows = to_dict(load_config("c4d/ablation", table))
    runs, stage1_of = {}, {}
    for name, row in rows.items():
        if not isinstance(row, dict) or len(row) != 1 or not set(row) <= {"overrides", "stage1_of"}:
            raise UserError(f"ablation table {table}: row {name!r} must hold exactly one of "
                            f"`overrides: [key=value, ...]` or `stage1_of: ROW`, got {row!r}")
        if "overrides" in row:
            runs[name] = [str(item) for item in row["overrides"]]
            load_config("c4d", "default", overrides=runs[name])
        else:
            stage1_of[name] = row["stage1_of"]
    unknown = {name: run for name, run in stage1_of.items() if run not in runs}
    if unknown:
        raise UserError(f"ablation table {table}: `stage1_of` must name a row with overrides, got {unknown}")
    return tuple(rows), runs, stage1_of


# the table's rows; the runs (row -> weight overrides); rows read from a run's stage-1 depth
VARIANTS, RUNS, STAGE1_OF = read_variants()
METRICS = ("ate", "rpe_trans", "rpe_rot", "abs_rel", "rmse", "delta_1_25")


def resize_scene(scene: Scene, size: int, frames: int | None = None, stride: int = 1) -> Scene:
    """The first `frames` (all if None) of every `stride`-th frame of the scene, at `size` pixels on
    its longer side (area-averaged RGB, nearest-neighbour labels and depth). A track queried on a
    frame left out is queried again on its first visible kept frame."""
    keep = slice(0, None if frames is None else frames * stride, stride)
    kept = np.arange(scene.num_frames)[keep]  # (T',) the kept frames' indices in the scene
    h, w = scene.image_size
    hw = (round(h * size / max(h, w)), round(w * size / max(h, w)))
    sx, sy = hw[1] / w, hw[0] / h
    rgb = np.stack([cv2.resize(f, hw[::-1], interpolation=cv2.INTER_AREA) for f in scene.rgb[keep]])
    tracks = scene.tracks[:, keep].copy()
    tracks[..., 0] = rescale_pixels(tracks[..., 0], sx)
    tracks[..., 1] = rescale_pixels(tracks[..., 1], sy)
    occluded = scene.occluded[:, keep].copy()
    query_frame = np.minimum(np.searchsorted(kept, scene.query_frame), len(kept) - 1)  # (N,) kept index
    outside = kept[query_frame] != scene.query_frame  # queried on a frame left out: re-anchor
    query_frame[outside] = np.argmax(~occluded[outside], axis=1)
    usable = (~occluded).any(axis=1)
    return Scene(
        rgb=rgb, depth=np.stack([resize_nearest(d, hw) for d in scene.depth[keep]]),
        segmentation=np.stack([resize_nearest(s, hw) for s in scene.segmentation[keep]]),
        flow_fwd=None, flow_bwd=None, intrinsics=resize_intrinsics(scene.intrinsics[keep], (h, w), hw),
        cam_to_world=scene.cam_to_world[keep], object_to_world=scene.object_to_world[:, keep],
        objects=scene.objects, tracks=tracks[usable], occluded=occluded[usable],
        query_frame=query_frame[usable], track_object=scene.track_object[usable],
        tracks_world=scene.tracks_world[usable][:, keep], displacement=scene.displacement[usable][:, keep],
        moving=scene.moving[usable][:, keep], meta=scene.meta,
    )


def scores(result_depth, cam_to_world, scene: Scene) -> dict[str, float]:
    pose = pose_metrics(cam_to_world, scene.cam_to_world)
    depth = depth_metrics(result_depth, scene.depth, mode="scale_shift")
    return {"ate": pose["ate"], "rpe_trans": pose["rpe_trans"], "rpe_rot": pose["rpe_rot"],
            "abs_rel": depth["abs_rel"], "rmse": depth["rmse"], "delta_1_25": depth["delta_1_25"]}


def ablate_scene(scene: Scene, preset: str, overrides: list[str], bias: bool, flow_spec: str,
                 masks_from: str, variants=tuple(RUNS), tracker=None) -> dict:
    """Scores of the variants on one scene: {variant: {metric: value}, 'mask_iou': ...}.

    preset/overrides: the c4d config every variant starts from (each adds its weight overrides);
    variants: the stage-1 runs (keys of RUNS) to make; tracker: a `dynpt.inference.Tracker` whose
    tracks and mobility make the C4D masks and feed PTS (None: the oracle, the scene's truth).
    """
    cfg = load_config("c4d", preset, overrides=[*overrides, f"gt_pointmaps.static_bias={json.dumps(bias)}"])
    num_frames = scene.num_frames
    start = time.perf_counter()
    edges = graph_from_config(num_frames, cfg.graph)
    pairs = [tuple(map(int, e)) for e in edges]
    pw = build_pointmaps("gt", cfg, scene=scene).pointmaps(scene.rgb, edges)
    flows = build_flow(flow_spec, scene=scene).flow(scene.rgb, pairs)
    tracks = oracle_tracks(scene) if tracker is None else tracker.track(scene.rgb)
    arrays = track_arrays(tracks)  # (T,N,2) tracks, (T,N) visible, ... as numpy
    gt_masks = ground_truth_motion_masks(scene)
    if masks_from == "gt":
        masks = gt_masks
    else:
        masks = correspondence_motion_masks(tracks, flows, pairs, MotionMaskConfig(**dict(cfg.motion_mask.c4d)),
                                            scene.rgb).masks
    out: dict = {"mask_iou": mask_iou(masks, gt_masks)["iou"],
                 "moving_fraction": float(gt_masks.mean()),
                 "seconds": {"inputs": time.perf_counter() - start}, "optimiser_seconds": {}}
    for name in variants:
        variant = RUNS[name]
        run_cfg = load_config("c4d", preset, overrides=list(overrides) + variant)
        start = time.perf_counter()
        res = optimise(pw, num_frames, run_cfg, flows=flows, static_masks=~masks,
                       tracks=arrays["tracks"], visible=arrays["visible"])
        out["seconds"][name] = time.perf_counter() - start
        out["optimiser_seconds"][name] = res.history["seconds"]  # per part: init, stage1, ...
        out[name] = scores(res.depth, res.cam_to_world, scene)
        for row in (row for row, run in STAGE1_OF.items() if run == name):
            out[row] = scores(res.depth_stage1, res.cam_to_world, scene)
    return out


def mean_table(runs: dict, keys: list[str]) -> dict[str, dict[str, float]]:
    """Mean of every metric per variant present in all the runs named in `keys`."""
    present = [v for v in VARIANTS if all(v in runs[k] for k in keys)]
    return {v: {m: float(np.mean([runs[k][v][m] for k in keys])) for m in METRICS} for v in present}


def markdown(tables: dict, counts: dict) -> str:
    lines = []
    for title, table in tables.items():
        lines += [f"### {title} ({counts[title]} scenes)", "",
                  "| variant | ATE | RPE trans | RPE rot (deg) | Abs Rel | RMSE | delta<1.25 |",
                  "|---|---|---|---|---|---|---|"]
        for v, r in table.items():
            lines.append(f"| {v} | {r['ate']:.4f} | {r['rpe_trans']:.4f} | {r['rpe_rot']:.3f} | "
                         f"{r['abs_rel']:.4f} | {r['rmse']:.4f} | {r['delta_1_25']:.3f} |")
        lines.append("")
    return "\n".join(lines)


# the arguments that change a scene's cached run (OUT/runs/*.json); the others choose which runs
SETTINGS = ("dynamic", "static", "size", "stride", "frames", "preset", "flow", "masks", "tracker", "overrides")


def check_settings(out: Path, args: argparse.Namespace) -> None:
    """Record the settings of the runs cached in `out` (OUT/settings.json) on the first call and
    refuse other settings later: a resumed ablation never mixes runs made two ways."""
    settings = {key: getattr(args, key) for key in SETTINGS}
    path = out / "settings.json"
    if not path.is_file():
        write_json(path, settings, indent=1)
        return
    before = json.loads(path.read_text())
    changed = [key for key in SETTINGS if before.get(key) != settings[key]]
    if changed:
        was = ", ".join(f"{key} {before.get(key)!r}, now {settings[key]!r}" for key in changed)
        raise UserError(f"{out} holds runs made with other settings ({was}); give another --out, "
                        "or the same settings to resume")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m c4d_pipeline.ablation", description=__doc__.split("\n\n")[0])
    parser.add_argument("--dynamic", help="shards of dynamic scenes (datagen output)")
    parser.add_argument("--static", help="shards of static scenes (no tossed objects)")
    parser.add_argument("--out", required=True, help="output folder (resumable)")
    parser.add_argument("--max-scenes", type=int, default=None, help="per scene set")
    parser.add_argument("--only", default=None,
                        help="comma-separated scene indices to run (e.g. to split work over processes)")
    parser.add_argument("--size", type=int, default=64, help="longer image side for the optimisation")
    parser.add_argument("--stride", type=int, default=1, help="use every S-th frame of each scene")
    parser.add_argument("--frames", type=int, default=None,
                        help="use the first N (strided) frames of each scene")
    parser.add_argument("--preset", default="default", help="c4d config preset or YAML")
    parser.add_argument("--flow", default="gt", help="flow estimator: gt | dis[:PRESET] | raft:PATH")
    parser.add_argument("--masks", default="c4d", choices=("c4d", "gt"), help="motion masks used by CMA")
    parser.add_argument("--tracker", default=None, metavar="CKPT",
                        help="DynPT checkpoint (c4d train) whose tracks and mobility make the c4d masks and "
                        "feed PTS (default: the oracle, each scene's true tracks and mobility)")
    parser.add_argument("--bias", default="on,off", help="static-world bias settings to run")
    parser.add_argument("--variants", default=",".join(RUNS),
                        help="comma-separated stage-1 runs out of " + ", ".join(RUNS)
                        + "".join(f" ('{row}' comes with {run})" for row, run in STAGE1_OF.items()))
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument("overrides", nargs="*", help="config key=value overrides")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    torch.set_num_threads(args.threads)
    from datagen import read_scenes

    load_config("c4d", args.preset, overrides=args.overrides)  # fail early on a bad override
    if args.stride < 1 or (args.frames is not None and args.frames < 2):
        raise UserError(f"--stride must be >= 1 and --frames >= 2; got --stride {args.stride} "
                        f"--frames {args.frames}")
    if not (args.dynamic or args.static):
        raise UserError("give --dynamic and/or --static scene shards (c4d datagen output)")
    biases = [b.strip() for b in args.bias.split(",")]
    if not set(biases) <= {"on", "off"}:
        raise UserError(f"--bias takes on, off or on,off; got {args.bias!r}")
    variants = [v.strip() for v in args.variants.split(",")]
    if not set(variants) <= set(RUNS):
        raise UserError(f"--variants takes names out of {', '.join(RUNS)}; got {args.variants!r}")
    tracker = None
    if args.tracker is not None:
        from dynpt.inference import load_tracker
        tracker = load_tracker(args.tracker)
    out = Path(args.out)
    (out / "runs").mkdir(parents=True, exist_ok=True)
    check_settings(out, args)
    runs, groups = {}, {}
    for group, source in (("dynamic", args.dynamic), ("static", args.static)):
        if not source:
            continue
        for n, scene in enumerate(read_scenes(source)):
            if args.max_scenes is not None and n >= args.max_scenes:
                break
            if args.only is not None and n not in {int(i) for i in args.only.split(",")}:
                continue
            scene = resize_scene(scene, args.size, args.frames, args.stride)
            for bias in biases:
                key = f"{group}-{n:03d}-bias-{bias}"
                path = out / "runs" / f"{key}.json"
                if path.is_file():
                    runs[key] = json.loads(path.read_text())
                else:
                    log.info("%s: %d frames %dx%d", key, scene.num_frames, *scene.image_size)
                    runs[key] = ablate_scene(scene, args.preset, list(args.overrides), bias == "on",
                                             args.flow, args.masks, variants, tracker)
                    write_json(path, runs[key], indent=1)
                    log.info("%s: ATE %s", key, ", ".join(
                        f"{v} {runs[key][v]['ate']:.4f}" for v in VARIANTS if v in runs[key]))
                groups.setdefault(f"{group} scenes, static-world bias {bias}", []).append(key)
    tables = {title: mean_table(runs, keys) for title, keys in groups.items()}
    counts = {title: len(keys) for title, keys in groups.items()}
    summary = {"args": vars(args), "tables": tables, "counts": counts, "runs": runs}
    write_json(out / "ablation.json", summary, indent=1)
    md = markdown(tables, counts)
    write_text(out / "ablation.md", md)
    print(md)
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except UserError as exc:
        print(f"ablation: error: {exc}", file=sys.stderr)
        sys.exit(2)
