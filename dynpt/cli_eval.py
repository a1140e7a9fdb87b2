"""`c4d eval`: D-ACC and TAP-Vid metrics of a DynPT checkpoint on shards or TAP-Vid pickles."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from omegaconf import OmegaConf

from c4d_core.config import flag_overrides, load_config, parse_overrides
from c4d_core.errors import UserError
from c4d_core.schema import device as device_rule


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--ckpt", required=True, help="DynPT checkpoint written by `c4d train`")
    parser.add_argument("--data", required=True,
                        help="datagen shards (directory, .tar or glob) or a TAP-Vid pickle "
                             "(tapvid_davis.pkl, or the folder of Kinetics *_of_0010.pkl)")
    parser.add_argument("--mode", choices=("first", "strided"), default=None,
                        help="TAP-Vid query mode (key eval.query_mode; default: the checkpoint's "
                        "own, else first)")
    parser.add_argument("--out", default=None,
                        help="folder for eval.json and eval.md (default: next to the checkpoint)")
    parser.add_argument("--config", default=None,
                        help="config whose eval: section is used (default: the one the checkpoint "
                             "was trained with, else paper-gpu's: 256 tracks per scene at 256x256)")
    parser.add_argument("--device", default=None, help="cpu, cuda, cuda:1 ... (default: auto)")
    parser.add_argument("overrides", nargs="*", metavar="key=value",
                        help="eval overrides, e.g. eval.num_scenes=10")


def eval_config(ckpt: dict, config: str | None, overrides: list[str]):
    """The `eval:` section used: `config`'s if given, else the one saved with the checkpoint by
    `c4d train` (its own resolution, track count and query mode; keys it lacks from paper-gpu),
    else paper-gpu's; `overrides` on top."""
    cfg = load_config("dynpt", config or "paper-gpu", overrides=overrides).eval
    saved = ckpt["extra"].get("train_config", {}).get("eval")
    if config or not saved:
        return cfg
    return OmegaConf.merge(cfg, saved, parse_overrides(overrides).get("eval", {}))


def run(args: argparse.Namespace) -> int:
    from dynpt.baselines import ZeroMotionBaseline
    from dynpt.evaluate import evaluate_items, load_source, write_report
    from dynpt.checkpoint import load_checkpoint, model_from_checkpoint
    from dynpt.inference import Tracker

    if args.device is not None:
        device_rule().check("--device", args.device)
    ckpt = load_checkpoint(args.ckpt)
    overrides = [*args.overrides, *flag_overrides({"eval.query_mode": args.mode}, args.overrides)]
    cfg = eval_config(ckpt, args.config, overrides)
    mode = cfg.query_mode
    tracker = Tracker(model_from_checkpoint(ckpt, args.ckpt), args.device)
    skipped: list[str] = []  # scenes that could not be read (warned about, counted in the table)
    items, kind = load_source(args.data, cfg, skipped)
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
    stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", Path(args.data).stem) or "data"
    out = Path(args.out) if args.out else Path(args.ckpt).parent / f"eval-{stem}-{mode}"
    info = {"checkpoint": str(args.ckpt), "data": str(args.data), "kind": kind, "mode": mode,
            "skipped": skipped,
            "resolution": list(cfg.resolution), "num_tracks": cfg.num_tracks if kind == "shards" else None}
    json_path, md_path = write_report(result, baseline, out, title, info)
    print(md_path.read_text(), end="")
    print(f"wrote {json_path} and {md_path}")
    return 0
