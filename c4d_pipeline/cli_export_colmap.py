"""`c4d export colmap RECON OUT`: a `c4d run` reconstruction as COLMAP's text model.

    c4d export colmap runs/video colmap/            # cameras.txt, images.txt, points3D.txt
    colmap model_converter --input_path colmap/ --output_path colmap/ --output_type BIN

The dataset formats of `c4d export` live in `datagen.export`; `c4d.cli` sends the `colmap` form
here (`FORMS`), since a reconstruction belongs to c4d_pipeline. Conventions: docs/FORMAT.md,
"Exports", `colmap`.
"""

from __future__ import annotations

import argparse
import logging

from c4d_pipeline.colmap import MAX_POINTS, export_colmap

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("format", metavar="FORMAT", choices=["colmap"],
                        help="colmap: a reconstruction as COLMAP's text model")
    parser.add_argument("recon", metavar="RECON", help="the reconstruction: the --out folder of `c4d run`")
    parser.add_argument("out", metavar="OUT", help="output folder (cameras.txt, images.txt, points3D.txt)")
    parser.add_argument("--stride", type=int, default=None, metavar="N",
                        help="keep every N-th static pixel, in (frame, row, column) order (default: "
                        f"the smallest N keeping at most {MAX_POINTS} points)")


def run(args: argparse.Namespace) -> int:
    points = export_colmap(args.recon, args.out, args.stride, args.overwrite)
    log.info("wrote a COLMAP text model with %d static points to %s", points, args.out)
    return 0
