"""`c4d train`: train DynPT on datagen shards (see docs/TRAINING.md).

Also runnable under torchrun for multi-GPU / multi-node training:
`torchrun --nproc_per_node 8 -m dynpt.cli_train --config configs/dynpt/paper-gpu.yaml ...`.
"""

from __future__ import annotations

import argparse
import sys

from c4d_core.config import add_training_arguments, load_config


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_training_arguments(parser, "dynpt")
    parser.add_argument("--init", metavar="cotracker3:PATH", default=None,
                        help="start from CoTracker3's released weights (same as model.init_from=...)")


def run(args: argparse.Namespace) -> int:
    from dynpt.train import train

    init = [f"model.init_from={args.init}"] if args.init else []
    cfg = load_config("dynpt", args.config, overrides=[*args.overrides, *init])
    train(cfg, resume=args.resume)
    return 0


if __name__ == "__main__":  # torchrun -m dynpt.cli_train ...
    from c4d.cli import main

    sys.exit(main(["train", *sys.argv[1:]]))
