"""Exports of a datagen dataset into other projects' layouts, so their code reads our scenes
unchanged: `c4d export FORMAT DATA OUT` (docs/FORMAT.md, "Exports").

`FORMATS` maps each name to its `ExportFormat` (base.py): `kubric` (Kubric's MOVi worker folders,
kubric.py), `cotracker` (CoTracker's Kubric training folders, cotracker.py) and `tapvid` (a
TAP-Vid pickle, tapvid.py). `export(name, data, out)` runs one, resumably.
"""

from __future__ import annotations

from pathlib import Path

from c4d_core.errors import UserError
from datagen.export import cotracker, kubric, tapvid
from datagen.export.base import ExportFormat
from datagen.export.base import export as _export

FORMATS: dict[str, ExportFormat] = {fmt.name: fmt for fmt in (kubric.FORMAT, cotracker.FORMAT,
                                                              tapvid.FORMAT)}


def export_format(name: str) -> ExportFormat:
    """The format called `name`; a UserError listing the formats for any other name."""
    if name not in FORMATS:
        raise UserError(f"unknown export format {name!r}; choose one of {', '.join(FORMATS)}")
    return FORMATS[name]


def export(name: str, data: str | Path, out: str | Path, overwrite: bool = False) -> tuple[int, int]:
    """Export the dataset `data` as the format `name` into `out`; returns (scenes written, scenes
    already there from an earlier run). `overwrite`: replace another command's output there
    (`c4d_core.ownership`)."""
    return _export(export_format(name), data, out, overwrite)
