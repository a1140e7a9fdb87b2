"""`c4d eval`: D-ACC and TAP-Vid metrics of a DynPT checkpoint on shards or TAP-Vid pickles."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from c4d_core.config import load_config
from c4d_core.errors import UserError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--ckpt", required=True, help="DynPT checkpoint written by `c4d train`")
    parser.add_argument("--data", required=True,
                        help="datagen shards (directory, .tar or glob) or a TAP-Vid pickle "
                             "(tapvid_davis.pkl, or the folder of Kinetics *_of_0010.pkl)")
    parser.add_argument("--mode", choices=("first", "strided"), default="first",
                        help="TAP-Vid query mode (default: first)")
    parser.add_argument("--out", default=None,
                        help="folder for eval.json and eval.md (default: next to the checkpoint)")
    parser.add_argument("--config", default="paper-gpu",
                        help="config whose eval: section is used (default: paper-gpu: 256 tracks "
                             "per scene at 256x256, all scenes)")
    parser.add_argument("--device", default=None, help="cpu, cuda, cuda:1 ... (default: auto)")
    parser.add_argument("overrides", nargs="*", metavar="key=value",
                        help="eval overrides, e.g. eval.num_scenes=10")


def run(args: argparse.Namespace) -> int:
    from dynpt.baselines import ZeroMotionBaseline
    from dynpt.evaluate import evaluate_items, load_source, write_report
    from dynpt.inference import load_tracker

    cfg = load_config("dynpt", args.config, overrides=args.overrides).eval
    tracker = load_tracker(args.ckpt, args.device)
    skipped: list[str] = []  # scenes that could not be read (warned about, counted in the table)
    items, kind = load_source(args.data, cfg, skipped)
    if not items:
        raise UserError(f"no readable scene in {args.data} ({len(skipped)} skipped, see the "
                        "warnings above); check it with `c4d inspect SOURCE --check`")
    result = evaluate_items(tracker, items, args.mode)
    # The reference that gives the numbers a meaning: no motion, always visible, all static.
    baseline = evaluate_items(ZeroMotionBaseline(), items, args.mode)
    for summary in (result["summary"], baseline["summary"]):
        summary["num_skipped"] = len(skipped)
    title = f"{Path(args.data).name} ({args.mode})"
    stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", Path(args.data).stem) or "data"
    out = Path(args.out) if args.out else Path(args.ckpt).parent / f"eval-{stem}-{args.mode}"
    info = {"checkpoint": str(args.ckpt), "data": str(args.data), "kind": kind, "mode": args.mode,
            "skipped": skipped,
            "resolution": list(cfg.resolution), "num_tracks": cfg.num_tracks if kind == "shards" else None}
    json_path, md_path = write_report(result, baseline, out, title, info)
    print(md_path.read_text(), end="")
    print(f"wrote {json_path} and {md_path}")
    return 0
