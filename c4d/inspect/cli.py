"""`c4d inspect SOURCE --out DIR`: a browsable report (index.html) of a shard set or a reconstruction.

SOURCE is a shard set (a directory of shards, a .tar, a glob), other projects' Kubric data
(TFDS MOVi records, CoTracker or Kubric worker folders: `datagen.foreign`) or a directory written
by `c4d run`; which one is detected from its files. `--check` validates every scene (or every reconstruction
file) and exits non-zero if anything is wrong.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from c4d_core.config import load_config, refuse_override_as_positional
from c4d_core.errors import UserError, refuse_unused
from c4d_core.ownership import output_folder

log = logging.getLogger(__name__)

VIDEO_FORMATS = (".webm", ".mp4", ".gif", ".avi")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("source", metavar="SOURCE",
                        help="shard set (directory of .tar shards, one .tar, or a quoted glob), "
                             "Kubric data (TFDS MOVi records, e.g. DIR/movi_e/256x256/1.0.0:"
                             "validation; CoTracker or Kubric worker folders) or a reconstruction "
                             "directory written by `c4d run`")
    parser.add_argument("--out", type=Path,
                        help="folder for the report (index.html, plots, videos); "
                             "optional with --check, which then also writes check.json there")
    parser.add_argument("--split", help="read only shards (or TFDS records) of this split "
                                        "(train, val, test; validation)")
    parser.add_argument("--scene", type=int, metavar="I",
                        help="detail report of the I-th scene (0-based, in reading order)")
    parser.add_argument("--num-samples", type=int, metavar="K",
                        help="scenes shown with a contact sheet and a video (config key `samples`)")
    parser.add_argument("--check", action="store_true",
                        help="decode and validate every scene (or reconstruction file), list every "
                             "problem with its shard and scene key, exit 1 if there is any")
    parser.add_argument("--gt", metavar="SOURCE",
                        help="reconstructions: shard set holding the ground truth of the video")
    parser.add_argument("--scene-index", type=int, metavar="I",
                        help="reconstructions: which scene of --gt (0-based, reading order)")
    parser.add_argument("--compare", action="append", default=[], metavar="LABEL=DIR",
                        help="reconstructions: another reconstruction of the same video to draw "
                             "and score beside it, e.g. \"GA only=recon-ga/\" (repeatable)")
    parser.add_argument("--video-format", choices=VIDEO_FORMATS, default=".webm",
                        help="container of the videos (.webm plays in browsers; default)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--config", action="append", default=[], metavar="FILE",
                        help="YAML file merged over configs/inspect/default.yaml (repeatable)")
    parser.add_argument("overrides", nargs="*", metavar="key=value",
                        help="config overrides right after SOURCE, e.g. flythrough.static_points=20000")


def load_inspect_config(args):
    """configs/inspect/default.yaml, then --config files, then flags and key=value overrides."""
    refuse_override_as_positional(args.source, "SOURCE", args.overrides,
                                  "`c4d inspect SOURCE [--out DIR] [key=value ...]`")
    overrides = list(args.overrides)
    if args.num_samples is not None:
        if args.num_samples < 0:
            raise UserError(f"--num-samples must be >= 0, got {args.num_samples}")
        overrides.append(f"samples={args.num_samples}")
    return load_config("inspect", "default", args.config, overrides)


def _run_reconstruction(args, cfg) -> int:
    from c4d.inspect import recon_report
    from c4d_pipeline.outputs import is_reconstruction, read_reconstruction

    if args.check and args.out is None:
        recon = read_reconstruction(args.source, strict=False)
        for problem in recon.problems:
            print(f"{args.source}: {problem}")
        print(f"{args.source}: {len(recon.problems)} problems")
        return 1 if recon.problems else 0
    if args.out is None:
        raise UserError("--out DIR is required to write a report (or use --check alone)")
    compare = {}
    for item in args.compare:
        label, sep, folder = item.partition("=")
        if not sep or not label or not is_reconstruction(folder):
            raise UserError(f"--compare {item!r}: give LABEL=DIR with DIR a reconstruction of `c4d run`")
        compare[label] = Path(folder)
    gt = None
    if args.gt:
        from c4d_pipeline.eval_recon import check_ground_truth, pick_scene

        gt = pick_scene(args.gt, args.scene_index)
        for folder in (args.source, *compare.values()):  # each is scored against it
            check_ground_truth(read_reconstruction(folder, strict=False), gt)
    gt_name = "" if gt is None else gt.name(args.scene_index)
    summary = recon_report.build_recon_report(args.source, args.out, cfg, gt, gt_name,
                                              video_ext=args.video_format, compare=compare)
    for problem in summary["problems"]:
        log.warning("%s: %s", args.source, problem)
    log.info("report written to %s", args.out / "index.html")
    return 1 if args.check and summary["problems"] else 0


def _count(number: int, noun: str) -> str:
    return f"{number} {noun}{'' if number == 1 else 's'}"


def _run_check(args, cfg) -> int:
    from c4d.inspect.dataset_check import check_dataset
    from datagen.shards import index_ranges, scene_indices

    result = check_dataset(args.source, cfg, args.split, progress=not args.no_progress)
    for shard, key, problem in result.problems:
        print(f"{shard} {key}: {problem}")
    for path in result.missing:
        print(f"{path}: missing, though the dataset file beside it lists it (scenes "
              f"{index_ranges(scene_indices(path))})")
    summary = (f"checked {_count(result.num_samples, 'scene')} in {_count(result.num_shards, 'shard')}: "
               f"{result.num_bad_samples} with problems ({len(result.problems)} problems)")
    if result.missing:
        scenes = [i for path in result.missing for i in scene_indices(path)]
        summary += f"; {_count(len(result.missing), 'shard')} missing (scenes {index_ranges(scenes)})"
    print(summary)
    if result.num_unverified:
        log.warning("warning: %d scenes carry no checksums (shards written before format 3), so "
                    "damaged bytes in them may go unnoticed; regenerate them to add checksums",
                    result.num_unverified)
    if args.out is not None:
        from c4d_core.files import write_json

        write_json(args.out / "check.json", {
            "source": args.source, "scenes": result.num_samples, "shards": result.num_shards,
            "missing_shards": [str(path) for path in result.missing],
            "problems": [{"shard": s, "key": k, "problem": p} for s, k, p in result.problems]})
    return 1 if result.problems or result.missing else 0


def run(args) -> int:
    """`c4d inspect`: `--out` is claimed as a report folder (`c4d_core.ownership`); a failure
    leaves no folder behind that this run created."""
    if args.out is None:
        return _run(args)
    with output_folder(args.out, "inspect", args.overwrite):
        return _run(args)


def refuse_unused_options(args, reconstruction: bool) -> None:
    """One `UserError` for an option given where it does nothing: for the other kind of SOURCE
    (`reconstruction` or shard set), without the option it refines, or with --check where no
    report is written; then `--scene-index` defaults to 0."""
    shards_only = f"shard sets, and {args.source} is a reconstruction"
    recon_only = f"reconstructions, and {args.source} is not one"
    checked = args.check and not reconstruction  # a shard set's check writes no report
    no_report = args.check and reconstruction and args.out is None
    refuse_unused([
        ("--scene", args.scene is not None and reconstruction,
         f"{shards_only} (its ground truth: --gt DATA --scene-index I)"),
        ("--split", args.split is not None and reconstruction, shards_only),
        ("--num-samples", args.num_samples is not None and reconstruction, shards_only),
        ("--gt", args.gt is not None and not reconstruction, recon_only),
        ("--compare", bool(args.compare) and not reconstruction, recon_only),
        ("--scene-index", args.scene_index is not None and not args.gt,
         "--gt DATA (which of its scenes is the video's)"),
        ("--scene", args.scene is not None and checked, "a report (--check checks every scene)"),
        ("--num-samples", args.num_samples is not None and checked,
         "a report (--check checks every scene)"),
        ("--gt", args.gt is not None and no_report, "a report (--out DIR)"),
        ("--compare", bool(args.compare) and no_report, "a report (--out DIR)"),
    ])
    if args.scene_index is None:
        args.scene_index = 0


def _run(args) -> int:
    from c4d_pipeline.outputs import is_reconstruction

    cfg = load_inspect_config(args)
    reconstruction = is_reconstruction(args.source)
    refuse_unused_options(args, reconstruction)
    if reconstruction:
        return _run_reconstruction(args, cfg)
    if args.check:
        return _run_check(args, cfg)
    if args.out is None:
        raise UserError("--out DIR is required to write a report (or use --check alone)")
    from c4d.inspect import dataset_report

    if args.scene is not None:
        page = dataset_report.build_scene_report(args.source, args.out, args.scene, cfg, args.split,
                                                 video_ext=args.video_format)
        log.info("scene report written to %s", page)
        return 0
    summary = dataset_report.build_dataset_report(
        args.source, args.out, cfg, args.split, video_ext=args.video_format,
        progress=not args.no_progress)
    counts = summary["counts"]
    log.info("%d scenes, %d frames, %d objects, %d tracks; report written to %s",
             counts["scenes"], counts["frames"], counts["objects"], counts["tracks"],
             args.out / "index.html")
    if counts["unreadable"]:
        log.warning("%d samples could not be read; run `c4d inspect %s --check` for details",
                    counts["unreadable"], args.source)
    return 0
