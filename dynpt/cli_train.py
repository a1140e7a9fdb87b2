"""`c4d train`: train DynPT on datagen shards (see docs/TRAINING.md).

Also runnable under torchrun for multi-GPU / multi-node training:
`torchrun --nproc_per_node 8 -m dynpt.cli_train --config configs/dynpt/paper-gpu.yaml ...`.
"""

from __future__ import annotations

import argparse
import sys

from c4d.config import load_config


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", required=True,
                        help="a preset of configs/dynpt (tiny-cpu, paper-gpu, ...) or a YAML path")
    parser.add_argument("--resume", action="store_true",
                        help="continue the run in train.out_dir from its latest checkpoint")
    parser.add_argument("overrides", nargs="*", metavar="key=value",
                        help="config overrides, e.g. data.sources=[shards/train] train.steps=1000")


def run(args: argparse.Namespace) -> int:
    from dynpt.train import train

    cfg = load_config("dynpt", args.config, overrides=args.overrides)
    train(cfg, resume=args.resume)
    return 0


if __name__ == "__main__":  # torchrun -m dynpt.cli_train ...
    from c4d.cli import main

    sys.exit(main(["train", *sys.argv[1:]]))
