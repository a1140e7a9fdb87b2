"""`c4d pretrain-pointmaps`: train a small DUSt3R-shaped pointmap network on datagen shards.

Its output, `OUT_DIR/pointmap_net.pth`, is an official-layout DUSt3R checkpoint: DynPT takes its
frozen encoder with `model.encoder_3d.checkpoint=...`, and `c4d run` its pointmaps with
`pointmaps.checkpoint=...` (see docs/TRAINING.md).
"""

from __future__ import annotations

import argparse

from c4d_core.config import add_training_arguments, training_config
from c4d_core.ownership import output_folder
from c4d_core.system import configure_threads


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_training_arguments(parser, "pointmaps", default="tiny-cpu")


def run(args: argparse.Namespace) -> int:
    from c4d_pipeline.pointmap_training import train_pointmap_net

    cfg = training_config("pointmaps", args)
    configure_threads(threads=cfg.threads)
    with output_folder(cfg.train.out_dir, "pretrain-pointmaps", args.overwrite):
        train_pointmap_net(cfg, resume=args.resume)
    return 0
