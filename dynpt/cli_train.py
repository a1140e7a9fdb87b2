"""`c4d train`: train DynPT on datagen shards (see docs/TRAINING.md).

`--nproc-per-node N` starts N DDP processes on this machine (torchrun's `--standalone` mode, run
in this process). Under torchrun itself, for several machines:
`torchrun --nproc_per_node 8 -m dynpt.cli_train --config paper-gpu ...`.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys

from c4d_core.config import add_training_arguments, training_config
from c4d_core.errors import UserError
from c4d_core.ownership import output_folder
from c4d_core.system import configure_threads, export_threads_for, prepare_allocator


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_training_arguments(parser, "dynpt")
    parser.add_argument("--init", metavar="cotracker3:PATH", default=None,
                        help="start from CoTracker3's released weights (same as model.init_from=...)")
    parser.add_argument("--nproc-per-node", type=int, default=1, metavar="N",
                        help="DDP processes on this machine (one per GPU; gloo on CPUs); for "
                        "several machines run torchrun itself (docs/TRAINING.md)")


def run(args: argparse.Namespace) -> int:
    from dynpt.train import check_schedule, train

    if args.init:
        args.overrides = [*args.overrides, f"model.init_from={args.init}"]
    cfg = training_config("dynpt", args)
    if args.nproc_per_node < 1:
        raise UserError(f"--nproc-per-node must be at least 1, got {args.nproc_per_node}")
    if args.nproc_per_node > 1 and "LOCAL_RANK" not in os.environ:
        check_schedule(cfg.train, args.nproc_per_node)  # a mistake: one line, no process started
        child = [*(["--config", args.config] if args.config else []), *args.overrides,
                 *(["--resume"] if args.resume else [])]
        export_threads_for(args.nproc_per_node, cfg.data.num_workers, cfg.threads)
        with output_folder(cfg.train.out_dir, "train", args.overwrite):  # claimed here, once
            return launch(args.nproc_per_node, child, verbose=getattr(args, "verbose", False))
    configure_threads(workers=cfg.data.num_workers, threads=cfg.threads)
    prepare_allocator(every_size=True)  # each step reuses the last one's memory, large blocks too
    if int(os.environ.get("RANK", "0")) > 0:  # under torchrun: rank 0 claims the folder
        train(cfg, resume=args.resume)
        return 0
    with output_folder(cfg.train.out_dir, "train", args.overwrite):
        train(cfg, resume=args.resume)
    return 0


def launch(nproc: int, argv: list[str], verbose: bool = False) -> int:
    """`torchrun --standalone --nproc_per_node nproc -m dynpt.cli_train *argv` in this process;
    a failed process becomes one line (its own message is printed above by that process), and
    Ctrl-C, which torchrun's agent turns into a `SignalException` once it has stopped the
    processes, a `KeyboardInterrupt` (`c4d: interrupted`, status 130)."""
    from torch.distributed.elastic.multiprocessing.api import SignalException
    from torch.distributed.elastic.multiprocessing.errors import ChildFailedError
    from torch.distributed.run import get_args_parser
    from torch.distributed.run import run as torchrun

    if not verbose:  # torchrun's agent logs each failure and signal as a report with a traceback;
        for name in list(logging.root.manager.loggerDict):  # each of its loggers has its own level
            if name.startswith("torch.distributed.elastic"):
                logging.getLogger(name).setLevel(logging.CRITICAL)
    try:
        torchrun(get_args_parser().parse_args(["--standalone", "--nproc_per_node", str(nproc),
                                               "-m", "dynpt.cli_train", *argv]))
    except ChildFailedError as exc:
        rank, failure = exc.get_first_failure()
        raise UserError(f"training failed: process {rank} of {nproc} exited with status "
                        f"{failure.exitcode} (its message is above)") from None
    except SignalException as exc:
        if exc.sigval != signal.SIGINT:
            raise
        raise KeyboardInterrupt from None
    return 0


if __name__ == "__main__":  # torchrun -m dynpt.cli_train ...
    from c4d.cli import main

    sys.exit(main(["train", *sys.argv[1:]]))
