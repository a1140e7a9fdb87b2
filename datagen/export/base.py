"""What every export shares: the scenes of a dataset, the layers a format needs, the output's
identity, and the resumable per-scene loop.

A folder format (kubric, cotracker) writes one folder per scene, named by the scene index
(`00000042`, as Kubric's job folders are integers), into its scene root: OUT itself (cotracker),
or a sub-folder of it that holds nothing but scene folders (kubric: `OUT/scenes/`, the data path
of Kubric's builders, which read every entry of their path as a scene; `ExportFormat.subfolder`).
OUT holds the ownership marker (`c4d_core.ownership`) beside them. Each scene is written whole
into `NAME.partial` (`c4d_core.files.staged_folder`) and renamed when complete, so a folder `NAME`
is always a finished scene and a finished export holds no other entry; the first file of each is
`c4d_export.json` (`RECORD`): the format and the dataset it came from. A rerun into the same OUT
skips the finished scenes and redoes the partial ones; an OUT holding anything else (other files,
another format, another dataset, another layout) is refused before anything is written. A file
format (tapvid) writes one file atomically.
"""

from __future__ import annotations

import io
import itertools
import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import cv2
import numpy as np
from tqdm import tqdm

from c4d_core.errors import UserError
from c4d_core.files import atomic_path, disk_error, staged_folder, write_json
from c4d_core.ownership import MARKER, check_file, output_folder
from datagen.scene import Scene
from datagen.shards import decode_scene, iter_samples, list_shards, scenes_in_shard

log = logging.getLogger(__name__)

RECORD = "c4d_export.json"  # in every exported scene folder, written first
PARTIAL = ".partial"  # staged_folder's suffix for a scene folder being written

# layers an export may need that a Scene can lack -> how a dataset gets them (`c4d datagen`)
MADE_BY_EVERY_PRESET = "every preset makes it: regenerate the dataset with `c4d datagen`"
LAYER_SWITCHES = {
    "depth": MADE_BY_EVERY_PRESET,
    "segmentation": MADE_BY_EVERY_PRESET,
    "flow_fwd": MADE_BY_EVERY_PRESET,
    "flow_bwd": MADE_BY_EVERY_PRESET,
    "object_to_world": MADE_BY_EVERY_PRESET,
    "moving": MADE_BY_EVERY_PRESET,
    "normal": "layers.normal=true",
    "object_coordinates": "layers.object_coordinates=true",
    "instances": "layers.instances=true",
    "events": "layers.events=true",
}


@dataclass(frozen=True)
class ExportFormat:
    """One export: `c4d export NAME DATA OUT`.

    `fields`: the Scene fields it reads (None: all); `layers`: the optional ones of those it cannot
    do without (a scene without one is refused, naming the layer and its `LAYER_SWITCHES` entry).
    A folder format has `write_scene(scene, folder, name)`, writing the scene `name` into its
    (empty, staged) folder, and `subfolder`, the folder of OUT its scene folders go into ("": OUT
    itself); a file format has `write_file(scenes, path)`, writing every (name, scene) pair of
    `scenes` into one file and returning how many.
    """

    name: str
    summary: str
    fields: tuple[str, ...] | None
    layers: tuple[str, ...]
    write_scene: Callable[[Scene, Path, str], None] | None = None
    write_file: Callable[[Iterator[tuple[str, Scene]], Path], int] | None = None
    subfolder: str = ""

    def scene_root(self, out: Path) -> Path:
        """The folder of `out` that holds this folder format's scene folders."""
        return out / self.subfolder if self.subfolder else out


def write_member(path: Path, data: bytes) -> None:
    """Write one file of a staged scene folder (in place: the folder is renamed when complete),
    its bytes encoded in memory (`in_memory`): the libraries' own file writes answer a full disk
    with a bare False or an empty file (OpenCV), or an OSError without its errno (numpy). A disk
    error becomes `disk_error`'s one line naming the file."""
    try:
        path.write_bytes(data)
    except OSError as exc:
        raise disk_error(path, exc) from exc


def in_memory(save: Callable[[io.BytesIO], Any]) -> bytes:
    """The bytes `save(file)` writes into a file object (`PIL.Image.save`, `np.save`)."""
    buffer = io.BytesIO()
    save(buffer)
    return buffer.getvalue()


def write_png(path: Path, rgb: np.ndarray) -> None:
    """An RGB(A) PNG of uint8 or uint16 (H,W,3|4) channels in RGB(A) order (`write_member`)."""
    channels = [2, 1, 0, 3][:rgb.shape[-1]]
    ok, data = cv2.imencode(".png", np.ascontiguousarray(rgb[..., channels]))
    if not ok:
        raise ValueError(f"OpenCV cannot encode a {rgb.dtype} {rgb.shape} image as PNG ({path})")
    write_member(path, data.tobytes())


def source_of(meta: dict[str, Any]) -> dict[str, Any]:
    """The identity of the dataset a scene belongs to: split, seed and config digest."""
    return {"split": meta.get("split"), "seed": meta.get("seed"),
            "config_digest": meta.get("config_digest")}


def describe(source: dict[str, Any]) -> str:
    """`source_of`'s identity in words: `split 'train', seed 5, config_digest '601f84c5c1834a09'`."""
    return ", ".join(f"{key} {value!r}" for key, value in source.items())


def scene_name(key: str) -> str:
    """An exported scene's name, from its webdataset key: the index part (`train-00000042` ->
    `00000042`)."""
    return key.rpartition("-")[2]


def check_layers(fmt: ExportFormat, scene: Scene, where: str) -> None:
    """UserError naming every layer `fmt` needs that `scene` lacks, and how to generate it."""
    missing = [name for name in fmt.layers if getattr(scene, name) is None]
    if missing:
        how = "; ".join(f"{name}: {LAYER_SWITCHES[name]}" for name in missing)
        raise UserError(f"{where} lacks the layer(s) {', '.join(missing)}, which the {fmt.name} "
                        f"export needs; generate the dataset with them ({how})")


class _Scenes:
    """The scenes of DATA in reading order, each checked to be of one dataset (that of the first
    scene: `source`) and to have the layers of the format."""

    def __init__(self, fmt: ExportFormat, data: str | Path):
        self.fmt, self.data = fmt, data
        self.fields = None if fmt.fields is None else (*fmt.fields, "meta")
        self.shards = list_shards(data)
        counts = [scenes_in_shard(shard) for shard in self.shards]
        self.total = None if None in counts else sum(counts)
        self.source = self._source(self.shards[0])
        for shard in self.shards[1:]:  # one dataset: checked before anything is written
            self._check(self._source(shard), f"the first scene of {shard}")
        self.skipped = 0

    @staticmethod
    def _source(shard: Path) -> dict[str, Any]:
        """The dataset identity of the first scene of `shard` (only its meta is decoded)."""
        for sample in iter_samples(shard, fields=("meta",)):
            return source_of(decode_scene(sample, fields=("meta",)).meta)
        raise UserError(f"{shard} holds no scene; rerun `c4d datagen`")

    def _check(self, source: dict[str, Any], where: str) -> None:
        if source != self.source:
            raise UserError(f"{self.data} mixes datasets: {where} is of {describe(source)}, the "
                            f"first scene of {describe(self.source)}; export one dataset at a time")

    def pending(self, done: set[str] = frozenset()) -> Iterator[tuple[str, Scene]]:
        """(name, scene) of every scene whose name is not in `done`, decoded and checked; the
        others are read but not decoded, and counted in `skipped`."""
        for shard in self.shards:
            for sample in iter_samples(shard, self.fields):
                name = scene_name(sample["__key__"])
                if name in done:
                    self.skipped += 1
                else:
                    yield name, self._decode(sample)

    def _decode(self, sample: dict[str, Any]) -> Scene:
        scene = decode_scene(sample, self.fields)
        where = f"scene {sample['__key__']!r} of {sample['__url__']}"
        self._check(source_of(scene.meta), where)
        check_layers(self.fmt, scene, where)
        return scene


def _progress(fmt: ExportFormat, scenes: Iterator[tuple[str, Scene]], total: int | None,
              done: int) -> Iterator[tuple[str, Scene]]:
    """`scenes` with a progress bar (a scene counts once the consumer asks for the next), which
    opens only once the first scene is decoded and checked: a refused dataset prints one line."""
    first = next(scenes, None)
    if first is None:
        return
    with tqdm(total=total, initial=done, unit="scene", desc=f"export {fmt.name}",
              dynamic_ncols=True) as bar:
        for item in itertools.chain([first], scenes):
            yield item
            bar.update()


def _read_record(folder: Path) -> dict[str, Any] | None:
    try:
        record = json.loads((folder / RECORD).read_text())
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) else None


def _entries(folder: Path) -> list[Path]:
    """The entries of `folder` (none where it is missing) but its ownership marker, by name."""
    return sorted(p for p in folder.iterdir() if p.name != MARKER) if folder.is_dir() else []


def _refuse(fmt: ExportFormat, out: Path, source: dict[str, Any], what: str) -> UserError:
    return UserError(f"{out} is not empty and is not a {fmt.name} export of this dataset "
                     f"({describe(source)}): it holds {what}; choose a new or empty folder")


def _claim_folder(fmt: ExportFormat, out: Path, source: dict[str, Any]) -> set[str]:
    """The names of the finished scenes in `out`; a UserError unless `out` is missing, empty, or
    holds (beside its marker, in `fmt`'s scene root) only scene folders, finished or partial, of
    a `fmt` export of the dataset `source`."""
    if out.exists() and not out.is_dir():
        raise UserError(f"{out} is a file; the {fmt.name} export writes a folder of scene folders: "
                        "choose a new or empty folder")
    root = fmt.scene_root(out)
    for entry in _entries(out) if fmt.subfolder else ():
        if entry.name == fmt.subfolder and entry.is_dir():
            continue
        if (_read_record(entry) or {}).get("format") == fmt.name:
            raise UserError(f"{out} holds the scene folder {entry.name} of an earlier {fmt.name} "
                            f"export, which wrote scene folders into OUT itself; they now go "
                            f"into {root}: move them there (mkdir {root} && mv {out}/[0-9]* "
                            f"{root}/) or choose a new folder")
        raise _refuse(fmt, out, source, f"{entry.name}, which no {fmt.name} export writes there")
    finished = set()
    for entry in _entries(root):
        name = entry.name.removesuffix(PARTIAL)
        record = _read_record(entry) if entry.is_dir() and name.isdigit() else None
        if record == {"format": fmt.name, "source": source, "scene": name}:
            if name == entry.name:
                finished.add(name)  # complete: renamed into place as a whole
            continue  # a scene of this export, finished or partial
        if record is None and entry.name.endswith(PARTIAL) and entry.is_dir() and not any(entry.iterdir()):
            continue  # a partial scene killed before its first file
        theirs = record.get("source") if record else None
        raise _refuse(fmt, out, source,
                      f"{entry.name}, a {record.get('format')} export of "
                      f"{describe(theirs) if isinstance(theirs, dict) else theirs}" if record else
                      f"{entry.name}, which no {fmt.name} export writes")
    return finished


def export_folders(fmt: ExportFormat, data: str | Path, out: Path) -> tuple[int, int]:
    """Export every scene of `data` into `ROOT/NAME/` (ROOT: `fmt.scene_root(out)`; `out` claimed
    by the caller), skipping finished ones; returns (written, already there)."""
    scenes = _Scenes(fmt, data)
    finished = _claim_folder(fmt, out, scenes.source)
    root = fmt.scene_root(out)
    written = 0
    for name, scene in _progress(fmt, scenes.pending(finished), scenes.total, len(finished)):
        with staged_folder(root / name) as stage:
            write_json(stage / RECORD, {"format": fmt.name, "source": scenes.source, "scene": name})
            fmt.write_scene(scene, stage, name)
        written += 1
    return written, scenes.skipped


def export_file(fmt: ExportFormat, data: str | Path, out: Path, overwrite: bool) -> tuple[int, int]:
    """Export every scene of `data` into the one file `out`, written atomically; returns
    (written, 0). An existing `out` is refused unless `overwrite` (it cannot carry a marker)."""
    if out.is_dir():
        raise UserError(f"{out} is a folder; the {fmt.name} export writes one file: give a file "
                        "name such as OUT.pkl")
    if out.exists() and not overwrite:
        raise UserError(f"{out} already exists; remove it, choose another name, or pass "
                        "--overwrite to replace it")
    check_file(out, f"export-{fmt.name}", overwrite)  # not inside another command's folder
    scenes = _Scenes(fmt, data)
    items = _progress(fmt, scenes.pending(), scenes.total, 0)
    first = next(items)  # decoded and checked before the temporary file (and its folder) is made
    with atomic_path(out) as tmp:
        written = fmt.write_file(itertools.chain([first], items), tmp)
    return written, 0


def export(fmt: ExportFormat, data: str | Path, out: str | Path,
           overwrite: bool = False) -> tuple[int, int]:
    """Export the dataset `data` (a shard folder, shard, glob or list, as `datagen.read_scenes`
    takes) as `fmt` into `out`; returns (scenes written, scenes already there). `overwrite`:
    replace another command's output at `out` (`c4d_core.ownership`)."""
    start = time.perf_counter()
    out = Path(out)
    if fmt.write_scene is None:
        written, skipped = export_file(fmt, data, out, overwrite)
    else:
        with output_folder(out, f"export-{fmt.name}", overwrite):
            written, skipped = export_folders(fmt, data, out)
    log.info("exported %d scenes as %s to %s in %.0f s%s", written, fmt.name,
             out if fmt.write_scene is None else fmt.scene_root(out), time.perf_counter() - start,
             f" ({skipped} already there)" if skipped else "")
    return written, skipped
