"""`c4d export FORMAT DATA OUT`: a datagen dataset in another project's layout.

    c4d export kubric data/movi-e kubric/         # Kubric's MOVi worker folders, in kubric/scenes/
    c4d export cotracker data/movi-e cotracker/   # CoTracker's Kubric training folders
    c4d export tapvid data/val val.pkl            # a TAP-Vid pickle for tapnet's evaluation

`c4d export colmap RECON OUT` (a reconstruction, not a dataset) is c4d_pipeline's
`cli_export_colmap`: `c4d.cli` sends that form there, as datagen may not import the pipeline.

Folder exports write each scene folder whole and rename it into place, so rerunning the same
command after a crash finishes the missing scenes; OUT must be new, empty, or such an export of
the same dataset.
"""

from __future__ import annotations

import argparse

from datagen.export import FORMATS, export


def add_arguments(parser: argparse.ArgumentParser) -> None:
    formats = "; ".join([*(f"{name}: {fmt.summary}" for name, fmt in FORMATS.items()),
                         "colmap: a `c4d run` reconstruction as COLMAP's text model "
                         "(`c4d export colmap RECON OUT`, see `c4d export colmap --help`)"])
    parser.add_argument("format", metavar="FORMAT", help=f"the layout to write ({formats})")
    parser.add_argument("data", metavar="DATA",
                        help="the dataset: a `c4d datagen` folder, a shard or a glob of shards")
    parser.add_argument("out", metavar="OUT",
                        help="output folder (kubric, cotracker) or file (tapvid, e.g. val.pkl)")


def run(args: argparse.Namespace) -> int:
    export(args.format, args.data, args.out, args.overwrite)
    return 0
