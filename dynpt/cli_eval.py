"""`c4d eval`: D-ACC and TAP-Vid metrics of a DynPT checkpoint on shards or TAP-Vid pickles.

It scores every video of --data unless `eval.num_scenes=N` on the command line asks for the first
N (shards only): the `eval.num_scenes` of a training config is the size of the periodic
validation during training, not of this evaluation. It prints how many videos it scored of how
many, and where it wrote its report.
"""

from __future__ import annotations

import argparse
import contextlib
import re
from pathlib import Path

from omegaconf import OmegaConf

from c4d_core.config import flag_overrides, load_config, parse_overrides
from c4d_core.errors import UserError
from c4d_core.ownership import check_folder, output_folder
from c4d_core.schema import device as device_rule


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--ckpt", required=True, help="DynPT checkpoint written by `c4d train`")
    parser.add_argument("--data", required=True,
                        help="datagen shards (directory, .tar or glob) or a TAP-Vid pickle "
                             "(tapvid_davis.pkl, or the folder of Kinetics *_of_0010.pkl)")
    parser.add_argument("--mode", choices=("first", "strided"), default=None,
                        help="TAP-Vid query mode (key eval.query_mode; default: the checkpoint's "
                        "own, else first)")
    parser.add_argument("--protocol", choices=("scene", "c4d-paper"), default=None,
                        help="key eval.protocol: scene (default: the scenes' own tracks at "
                             "eval.resolution, --mode queries) or c4d-paper (the paper's D-ACC "
                             "protocol: the first 24 frames at 256x256, 256 tracks drawn as "
                             "TAP-Vid-Kubric draws them, seeded by eval.seed)")
    parser.add_argument("--out", default=None,
                        help="folder for eval.json and eval.md (default: next to the checkpoint, "
                             "CKPT_FOLDER/eval-DATA-MODE)")
    parser.add_argument("--config", default=None,
                        help="config whose eval: section is used (default: the one the checkpoint "
                             "was trained with, else paper-gpu's: 256 tracks per scene at 256x256); "
                             "its eval.num_scenes is not: every video is scored")
    parser.add_argument("--device", default=None, help="cpu, cuda, cuda:1 ... (default: auto)")
    parser.add_argument("overrides", nargs="*", metavar="key=value",
                        help="eval overrides, e.g. eval.num_scenes=10 (score only the first 10 "
                             "videos of --data; default: all of them)")


def eval_config(ckpt: dict, config: str | None, overrides: list[str]):
    """The `eval:` section used: `config`'s if given, else the one saved with the checkpoint by
    `c4d train` (its own resolution, track count and query mode; keys it lacks from paper-gpu),
    else paper-gpu's; `overrides` on top. `num_scenes` is 0 (every video) unless `overrides` set
    it: the configs' value is the size of the validation during training."""
    cfg = load_config("dynpt", config or "paper-gpu", overrides=overrides).eval
    asked = parse_overrides(overrides).get("eval", {})
    saved = ckpt["extra"].get("train_config", {}).get("eval")
    if saved and not config:
        cfg = OmegaConf.merge(cfg, saved, asked)
    return OmegaConf.merge(cfg, {"num_scenes": asked.get("num_scenes", 0)})  # checked by load_config


def apply_protocol(cfg, overrides: list[str]):
    """(`cfg`, query mode) under `cfg.protocol`: `scene` keeps both as they are; c4d-paper fixes
    256 tracks at 256x256, queried at their drawn points (mode 'sampled'), and refuses a
    command-line setting that contradicts it."""
    from dynpt.evaluate import PAPER_RESOLUTION, PAPER_TRACKS, protocol_query_mode

    if cfg.protocol != "c4d-paper":
        return cfg, protocol_query_mode(cfg)
    fixed = {"resolution": list(PAPER_RESOLUTION), "num_tracks": PAPER_TRACKS}
    asked = parse_overrides(overrides).get("eval", {})
    size = f"{PAPER_RESOLUTION[0]}x{PAPER_RESOLUTION[1]}"
    for key in ("resolution", "num_tracks", "query_mode"):
        if key in asked and asked[key] != fixed.get(key):
            raise UserError(f"eval.{key}={asked[key]} contradicts --protocol c4d-paper, which scores "
                            f"{PAPER_TRACKS} tracks at {size} queried at their drawn points: "
                            f"leave {'--mode' if key == 'query_mode' else 'eval.' + key} out")
    return OmegaConf.merge(cfg, fixed), protocol_query_mode(cfg)


def source_scenes(source: str) -> int:
    """How many scenes `source` holds: for shards, each shard's count from its dataset file, else
    its scenes counted by reading past them (nothing is decoded; an unreadable rest is not
    counted); for Kubric's data (datagen.foreign), its listed scenes."""
    from datagen.foreign import SHARDS, source_kind, source_units
    from datagen.shards import iter_samples, list_shards, scenes_in_shard

    if source_kind(source) != SHARDS:
        return len(source_units(source))
    total = 0
    for shard in list_shards(source):
        planned = scenes_in_shard(shard)
        if planned is not None:
            total += planned
            continue
        with contextlib.suppress(UserError):
            for _ in iter_samples(shard, fields=()):
                total += 1
    return total


def scored_line(scored: int, total: int, data: str, limit: int, skipped: int, no_tracks: int) -> str:
    """What `c4d eval` prints under its table: "scored N of M videos of DATA", and why not all."""
    why = []
    if limit and scored + skipped + no_tracks < total:
        why.append(f"the first {limit}, as eval.num_scenes={limit} asked; without it every video is scored")
    if skipped:
        why.append(f"{skipped} unreadable, skipped (see the warnings above)")
    if no_tracks:
        why.append(f"{no_tracks} with no visible track to query")
    return f"scored {scored} of {total} videos of {data}" + (f" ({'; '.join(why)})" if why else "")


def run(args: argparse.Namespace) -> int:
    from dynpt.baselines import ZeroMotionBaseline
    from dynpt.evaluate import evaluate_items, load_source, write_report
    from dynpt.checkpoint import load_checkpoint, model_from_checkpoint
    from dynpt.inference import Tracker
    from dynpt.postprocess import Postprocess, PostprocessedTracker

    if args.device is not None:
        device_rule().check("--device", args.device)
    ckpt = load_checkpoint(args.ckpt)
    overrides = [*args.overrides, *flag_overrides({"eval.query_mode": args.mode,
                                                   "eval.protocol": args.protocol}, args.overrides)]
    cfg, mode = apply_protocol(eval_config(ckpt, args.config, overrides), overrides)
    stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", Path(args.data).stem) or "data"
    how = "c4d-paper" if cfg.protocol == "c4d-paper" else mode
    out = Path(args.out) if args.out else Path(args.ckpt).parent / f"eval-{stem}-{how}"
    check_folder(out, "eval", args.overwrite)  # before the work
    tracker = PostprocessedTracker(Tracker(model_from_checkpoint(ckpt, args.ckpt), args.device),
                                   Postprocess.from_config(cfg))
    skipped: list[str] = []  # scenes that could not be read (warned about, counted in the table)
    items, kind = load_source(args.data, cfg, skipped)  # the first eval.num_scenes (0: all)
    read_all = not cfg.num_scenes or len(items) < cfg.num_scenes
    total = len(items) + len(skipped) if read_all else source_scenes(args.data)
    if not items:
        raise UserError(f"no readable scene in {args.data} ({len(skipped)} skipped, see the "
                        "warnings above); check it with `c4d inspect SOURCE --check`")
    result = evaluate_items(tracker, items, mode)
    # The reference that gives the numbers a meaning: no motion, always visible, all static.
    baseline = evaluate_items(ZeroMotionBaseline(), items, mode)
    for summary in (result["summary"], baseline["summary"]):
        summary["num_skipped"] = len(skipped)
    size = "x".join(str(v) for v in cfg.resolution)
    tracks = f", {cfg.num_tracks} tracks per video" if kind == "shards" else ""
    title = f"{Path(args.data).name} ({mode} queries, videos at {size}{tracks})"
    if cfg.protocol == "c4d-paper":
        title = (f"{Path(args.data).name} (the c4d-paper protocol: 24 frames at {size}, "
                 f"{cfg.num_tracks} TAP-Vid-Kubric tracks per video, seed {cfg.seed})")
    if cfg.refine != "none":
        title += ", tracks refined by Lucas-Kanade (eval.refine=lk)"
    if cfg.mobility != "head":
        title += ", mobility: the head fused with the tracks' epipolar geometry (eval.mobility=epipolar)"
    info = {"checkpoint": str(args.ckpt), "data": str(args.data), "kind": kind, "mode": mode,
            "protocol": cfg.protocol, "seed": cfg.seed, "mobility": cfg.mobility,
            **({"epipolar": OmegaConf.to_container(cfg.epipolar)} if cfg.mobility != "head" else {}),
            "refine": cfg.refine, **({"lk": OmegaConf.to_container(cfg.lk)} if cfg.refine != "none" else {}),
            "skipped": skipped, "videos_in_data": total, "num_scenes": cfg.num_scenes,
            "resolution": list(cfg.resolution), "num_tracks": cfg.num_tracks if kind == "shards" else None}
    with output_folder(out, "eval", args.overwrite):
        json_path, md_path = write_report(result, baseline, out, title, info)
    print(md_path.read_text(), end="")
    scored = result["summary"]["num_videos"]
    print(scored_line(scored, total, args.data, cfg.num_scenes, len(skipped), len(items) - scored))
    where = "" if args.out else " (next to the checkpoint; --out DIR writes elsewhere)"
    print(f"wrote {json_path} and {md_path}{where}")
    return 0
