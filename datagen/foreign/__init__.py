"""Other projects' Kubric data read as our `Scene`s, and the one place that says what a data path is.

`source_kind(path)` names the kind of a training or evaluation source:

    "shards"            our own `c4d datagen` shards (datagen.shards): a folder of *.tar, a .tar,
                        a glob of them, or a list of these
    "tfds-movi"         TFDS MOVi records: movi_e, panning_movi_e, movi_f at any resolution
                        config, in TFDS's folder layout (datagen/foreign/tfds_movi.py)
    "cotracker-kubric"  CoTracker's Kubric folders (datagen/foreign/cotracker_kubric.py)
    "kubric-worker"     scene folders as Kubric's MOVi worker writes them
                        (datagen/foreign/kubric_worker.py)

A path that is none of them is one `UserError` naming what each kind looks like. The commands
read every kind through this module: `c4d train data.sources=[...]` (dynpt/data.py
`ShardStream`, our shards mixed with the others by `data.weights`), `c4d eval --data`
(dynpt/evaluate.py `load_source`) and `c4d inspect [--check]` (c4d/inspect/dataset_check.py).

The reader interface
--------------------
A reader module M (named in `READERS`) exposes:

    M.KIND: str
        its kind, a key of `READERS` (e.g. "tfds-movi").
    M.EXPECTED: str
        what a source of this kind is, in a few words, for the refusal of a path that is no kind
        (e.g. "TFDS MOVi records: a folder with dataset_info.json beside NAME-SPLIT.tfrecord-*").
    M.detect(path: Path) -> bool
        True where `path` is a source of this kind. Looks at names and at most a few small files;
        never raises, never reads a data file through.
    M.units(path: Path, split: str | None) -> list[Unit]
        The scenes of the source, one `Unit` each, in a fixed reading order (sorted names): a
        scene folder, or one record of a record file. Listing is cheap (no decoding): training
        lists every source once and shares the units out among DDP ranks and loader workers.
        `split` names a split where the kind has splits (None: the only one present; several
        present is a `UserError` naming them). No scene at all is a `UserError`. Damage found
        while listing (a record file cut short) is not raised here but kept in `Unit.problem`.
    M.read_units(unit: Unit, options: ReadOptions) -> Iterator[Scene]
        The scene of `unit` (exactly one) in our conventions (docs/FORMAT.md): OpenCV cameras,
        z-depth, pixel centres at integer coordinates, flow as (dx, dy). Where the data has no
        tracks of its own they are drawn by TAP-Vid-Kubric's recipe, seeded by
        [options.seed, unit.index], unless `options.fields` leaves out "tracks" (then the scene
        has none); `options.fields` names the fields the caller needs (the rest
        may be None), `options.mobility_rule` how `moving` is labelled where the data allows a
        choice. A damaged or incomplete unit (or one with a `problem`) raises `UserError` naming
        the file, the record or folder and what is wrong; whether it is skipped is the caller's
        choice (`data.foreign=skip`, `eval.foreign=skip`).

`Unit` and `ReadOptions` are defined here; `read_unit` and `read_source` read any kind.
"""

from __future__ import annotations

import glob
import importlib
import os
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

import numpy as np

from c4d_core.errors import UserError
from datagen.scene import Scene

SHARDS = "shards"
# kind -> the module of its reader; a module not (yet) there is left out of the dispatch.
READERS = {
    "tfds-movi": "datagen.foreign.tfds_movi",
    "cotracker-kubric": "datagen.foreign.cotracker_kubric",
    "kubric-worker": "datagen.foreign.kubric_worker",
}
SHARDS_EXPECTED = "our datagen shards: a folder of SPLIT-NNNNNN.tar (made by `c4d datagen`)"
MOBILITY_RULES = ("point", "object")


@dataclass(frozen=True)
class Unit:
    """One scene of a foreign source: what loader workers share out and readers read.

    kind: the reader's KIND; path: the file or folder it is read from; index: its place in the
    source's reading order (seeds its tracks); name: how messages name it (e.g.
    "movi_e-validation.tfrecord-00000-of-00004 record 3"); where: a locator inside `path` for
    the reader (a record's byte offset; 0 where unused); problem: damage found while listing,
    which reading raises as a `UserError`.
    """

    kind: str
    path: str
    index: int
    name: str
    where: int = 0
    problem: str | None = None

    def __str__(self) -> str:
        return self.name


@dataclass(frozen=True)
class ReadOptions:
    """How a reader makes a Scene of a unit.

    seed: seeds the tracks drawn where the data has none, with the unit's index.
    mobility_rule: how `moving` (N,T) is labelled where the data has per-object poses:
        "point": our label, a track's world displacement since the previous frame
            > `mobility_threshold` (units), so a rotating object's points move;
        "object": the paper appendix's rule, an object's position change since the previous
            frame > `mobility_threshold`, given to all its points (the background never moves).
    mobility_threshold: world units per frame (0.01, Kubric's scale, as datagen's).
    fields: the Scene fields the caller needs (None: all); readers may leave the others None and
        skip decoding them (training skips the flows, normals and object coordinates).
    """

    seed: int = 0
    mobility_rule: str = "point"
    mobility_threshold: float = 0.01
    fields: tuple[str, ...] | None = None

    def __post_init__(self):
        if self.mobility_rule not in MOBILITY_RULES:
            raise UserError(f"mobility_rule={self.mobility_rule!r} is not a rule; choose one of "
                            f"{', '.join(MOBILITY_RULES)}")

    def wants(self, field: str) -> bool:
        return self.fields is None or field in self.fields


def options_from(cfg, seed: int, fields: Sequence[str] | None = None) -> ReadOptions:
    """`ReadOptions` from a config section (`data:` or `eval:`): its `mobility_rule` (default
    "point") and `mobility_threshold` (default 0.01) where it has them."""
    get = cfg.get if hasattr(cfg, "get") else (lambda key, default: default)
    return ReadOptions(seed=int(seed), mobility_rule=str(get("mobility_rule", "point")),
                       mobility_threshold=float(get("mobility_threshold", 0.01)),
                       fields=None if fields is None else tuple(fields))


# --- mobility ----------------------------------------------------------------------------------


def object_moving(object_to_world: np.ndarray, threshold: float) -> np.ndarray:
    """bool (K+1,T): segment k moves at frame t where its object's position changed by more than
    `threshold` since frame t-1 (t = 0: to frame 1, as our point label); row 0, the background,
    never moves. object_to_world (K,T,4,4)."""
    positions = np.asarray(object_to_world, np.float64)[:, :, :3, 3]  # (K,T,3)
    step = np.linalg.norm(np.diff(positions, axis=1), axis=-1)  # (K,T-1)
    moved = np.concatenate([step[:, :1], step], axis=1) > threshold if step.shape[1] else \
        np.zeros(positions.shape[:2], bool)
    return np.concatenate([np.zeros((1, positions.shape[1]), bool), moved], axis=0)


def mobility_labels(tracks, object_to_world: np.ndarray, options: ReadOptions) -> np.ndarray:
    """bool (N,T) `moving` of `tracks` (`datagen.annotate.Tracks`) by `options.mobility_rule`:
    "point" keeps the tracks' own label (world displacement > threshold), "object" gives each
    track its object's `object_moving`."""
    if options.mobility_rule == "point":
        return tracks.moving
    return object_moving(object_to_world, options.mobility_threshold)[tracks.track_object]


# --- which kind --------------------------------------------------------------------------------


def readers() -> dict[str, ModuleType]:
    """kind -> reader module, of the readers present in this installation."""
    found = {}
    for kind, module in READERS.items():
        try:
            found[kind] = importlib.import_module(module)
        except ModuleNotFoundError as exc:
            if exc.name != module:  # the reader is there but lacks something it imports
                raise
    return found


def reader(kind: str) -> ModuleType:
    return readers()[kind]


def expected_kinds() -> str:
    """Every kind a source may be, as one line for messages."""
    return "; ".join([SHARDS_EXPECTED] + [m.EXPECTED for m in readers().values()])


def _split_suffix(text: str) -> tuple[str, str | None]:
    """"FOLDER:SPLIT" -> (FOLDER, SPLIT) where FOLDER is an existing folder and the whole text is
    no existing path (TFDS names splits so: movi_e/256x256/1.0.0:validation); else (text, None)."""
    head, sep, tail = text.rpartition(":")
    if sep and tail and "/" not in tail and Path(head).is_dir() and not Path(text).exists():
        return head, tail
    return text, None


def source_kind(source) -> str:
    """The kind of `source` (module docstring). A list, a .tar, a glob of .tar files or a path
    that does not exist is "shards" (whose reader names what is wrong with it); a folder that is
    no kind at all is a `UserError` naming every kind expected."""
    if isinstance(source, (list, tuple)):
        return SHARDS
    text, _ = _split_suffix(os.fspath(source))
    if any(c in text for c in "*?["):
        paths = [Path(p) for p in glob.glob(text)]
    else:
        paths = [Path(text)]
    if not paths or not paths[0].exists():
        return SHARDS
    for kind, module in readers().items():
        if all(module.detect(p) for p in paths):
            return kind
    path = paths[0]
    if path.is_dir() and not any(path.glob("*.tar")) and not any(path.glob("dataset-*.json")):
        raise UserError(f"{path} holds no shards nor other data c4d reads; expected one of: "
                        f"{expected_kinds()}")
    return SHARDS


def source_units(source, split: str | None = None) -> list[Unit]:
    """The units of a foreign `source` (any kind but "shards"), in reading order. A split given
    as "FOLDER:SPLIT" overrides `split`."""
    text, named = _split_suffix(os.fspath(source))
    kind = source_kind(text)
    if kind == SHARDS:
        raise ValueError(f"{source} is a shard source; list it with datagen.shards.list_shards")
    return reader(kind).units(Path(text) if not any(c in text for c in "*?[") else text,
                              named or split)


def read_unit(unit: Unit, options: ReadOptions) -> Scene:
    """The one scene of `unit` (`UserError` where it is damaged or incomplete)."""
    scenes = list(reader(unit.kind).read_units(unit, options))
    if len(scenes) != 1:
        raise UserError(f"{unit}: holds {len(scenes)} scenes, not one")
    return scenes[0]


def read_source(source, split: str | None = None, options: ReadOptions = ReadOptions(),
                on_bad: Callable[[UserError], None] | None = None) -> Iterator[tuple[Unit, Scene]]:
    """(unit, scene) of every unit of a foreign `source`, in reading order. A damaged unit raises
    its `UserError`, or, with `on_bad`, is passed to it and skipped."""
    for unit in source_units(source, split):
        try:
            scene = read_unit(unit, options)
        except UserError as exc:
            if on_bad is None:
                raise
            on_bad(exc)
            continue
        yield unit, scene
