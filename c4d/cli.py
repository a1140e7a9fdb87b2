"""The `c4d` command: one entry point, a subcommand per job.

Each subcommand lives in the package that owns the work, in a module exposing
`add_arguments(parser)` and `run(args) -> int | None`. Only the chosen subcommand's module is
imported, so `c4d --help` is instant and a broken optional dependency only affects its command.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
import traceback

from c4d import __version__
from c4d_core.errors import UserError
from c4d_core.system import configure_threads, prepare_allocator, prepare_openmp, set_thread_override

# name -> (module, one-line help), in the order of the data flow.
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "datagen": ("datagen.cli", "generate MOVi-style synthetic videos with exact labels as shards"),
    "inspect": ("c4d.inspect.cli", "report, pictures and validation of shard sets and reconstructions"),
    "view": ("c4d.view.cli", "the 4D view of a reconstruction or a generated scene in the browser "
                             "(one offline HTML page: serve, --save or --screenshot)"),
    "pretrain-pointmaps": ("c4d_pipeline.cli_pretrain",
                           "train a small DUSt3R-shaped pointmap network (DynPT's 3D-aware encoder)"),
    "train": ("dynpt.cli_train", "train the dynamic-aware point tracker (DynPT) on shards"),
    "eval": ("dynpt.cli_eval", "evaluate a tracker checkpoint: D-ACC and TAP-Vid metrics"),
    "track": ("dynpt.cli_track", "track points in a video and write tracks plus an overlay video"),
    "run": ("c4d_pipeline.cli_run", "reconstruct a monocular video with C4D (depth, poses, masks, 3D tracks)"),
    "eval-recon": ("c4d_pipeline.cli_eval_recon", "score a reconstruction against ground truth"),
    "export": ("datagen.export.cli", "write a dataset as Kubric, CoTracker or TAP-Vid files their own code "
                                     "reads, or a reconstruction as a COLMAP text model (export colmap)"),
    "demo": ("c4d.demo", "the whole chain on a small generated dataset, in minutes on a CPU"),
    "config": ("c4d.cli_config", "print a preset's fully resolved config: config show GROUP/PRESET [key=value ...]"),
}

# (subcommand, its first positional) -> the module of that form of the subcommand, where another
# package owns it: `c4d export colmap RECON OUT` exports a reconstruction (c4d_pipeline), which the
# dataset exports of `datagen.export` may not import (docs/ARCHITECTURE.md).
FORMS: dict[tuple[str, str], str] = {("export", "colmap"): "c4d_pipeline.cli_export_colmap"}

# The subcommands that write outputs (c4d_core.ownership), and what --overwrite adds for each.
WRITERS: dict[str, str] = {name: "" for name in SUBCOMMANDS if name != "config"}
WRITERS["run"] = "; also needed to replace a reconstruction already in --out"

log = logging.getLogger("c4d")


def build_parser(chosen: str | None, module: str | None = None) -> argparse.ArgumentParser:
    """The top-level parser; only the `chosen` subcommand gets its full argument list, from
    `module` (default: the subcommand's module in `SUBCOMMANDS`)."""
    parser = argparse.ArgumentParser(
        prog="c4d",
        description="Dynamic-aware point tracking and C4D reconstruction. "
        "Run `c4d SUBCOMMAND --help` for the options of one subcommand.",
    )
    parser.add_argument("--version", action="version", version=f"c4d {__version__}")
    parser.add_argument(
        "-v", "--verbose", action="store_true", help="debug logging and full tracebacks"
    )
    subparsers = parser.add_subparsers(dest="command", metavar="SUBCOMMAND", required=True)
    for name, (module_name, help_text) in SUBCOMMANDS.items():
        sub = subparsers.add_parser(name, help=help_text, description=help_text)
        sub.add_argument(
            "-v", "--verbose", action="store_true", default=argparse.SUPPRESS,
            help="debug logging and full tracebacks",
        )
        sub.add_argument(
            "--threads", type=int, default=argparse.SUPPRESS, metavar="N",
            help="intra-op CPU threads of this process (default: the usable cores minus the "
            "worker processes the command starts; for train, pretrain-pointmaps and run also "
            "the config key `threads`)",
        )
        if name in WRITERS:
            sub.add_argument(
                "--overwrite", action="store_true",
                help="replace an output made by another c4d command, or a file c4d did not write "
                "(the old one is kept until the new output is complete; a folder holding files "
                "c4d did not write is never replaced)" + WRITERS[name])
        if name == chosen:
            importlib.import_module(module or module_name).add_arguments(sub)
    return parser


def _chosen_subcommand(argv: list[str]) -> str | None:
    return next((a for a in argv if a in SUBCOMMANDS), None)


def _command_module(argv: list[str], chosen: str) -> str:
    """The module that runs `chosen` as `argv` uses it: a `FORMS` entry when the first positional
    after the subcommand (skipping options and the value of `--threads`) names one."""
    rest = argv[argv.index(chosen) + 1:]
    first = next((a for a, before in zip(rest, ["", *rest])
                  if not a.startswith("-") and before != "--threads"), None)
    return FORMS.get((chosen, first), SUBCOMMANDS[chosen][0])


def parse_arguments(argv: list[str]) -> argparse.Namespace:
    """Parse `argv`; `key=value` overrides may stand anywhere, also after options.

    argparse only gives a trailing `nargs="*"` positional the tokens right after the other
    positionals, so stray `key=value` tokens are collected here and appended to `args.overrides`.
    """
    chosen = _chosen_subcommand(argv)
    module = _command_module(argv, chosen) if chosen else None
    parser = build_parser(chosen, module)
    args, extra = parser.parse_known_args(argv)
    args.command_module = module
    if extra:
        stray = [a for a in extra if a.startswith("-") or "=" not in a]
        if stray or not hasattr(args, "overrides"):
            parser.error(f"unrecognized arguments: {' '.join(stray or extra)}")
        args.overrides = [*(args.overrides or []), *extra]
    return args


def run_subcommand(argv: list[str]) -> int:
    """Parse `argv` and run its subcommand; exceptions propagate (for callers such as `c4d demo`).

    Chooses OpenMP's wait policy if torch has not loaded yet (`prepare_openmp`), keeps freed
    memory for reuse (`prepare_allocator`), then sets the process's CPU threads
    (`c4d_core.system.configure_threads`); a command that starts worker processes sets them
    again, leaving a core to each worker."""
    if "torch" not in sys.modules:  # OpenMP reads its wait policy once, when torch loads (parsing
        log.debug("OpenMP wait policy: %s", prepare_openmp())  # imports the subcommand's module)
    log.debug("malloc keeps freed memory: %s", prepare_allocator())
    args = parse_arguments(argv)
    if getattr(args, "threads", None) is not None:
        set_thread_override(args.threads)
    configure_threads()
    return int(importlib.import_module(args.command_module).run(args) or 0)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    verbose = "-v" in argv or "--verbose" in argv
    set_thread_override(None)
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(asctime)s %(name)s %(levelname)s: %(message)s" if verbose else "%(message)s",
        datefmt="%H:%M:%S",
    )
    try:
        return run_subcommand(argv)
    except UserError as exc:
        if verbose:
            traceback.print_exc()
        print(f"c4d: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # one of the system no command turned into a UserError: still one line
        from c4d_core.files import DISK_ERRNOS, disk_error

        if exc.errno is None:  # not the operating system's: a bug, shown in full
            raise
        if verbose:
            traceback.print_exc()
        verb = "write" if exc.errno in DISK_ERRNOS else "use"  # DISK_ERRNOS: errors of writes
        message = (disk_error(exc.filename, exc, verb) if exc.filename is not None
                   else exc.strerror or exc)
        print(f"c4d: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("c4d: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
