"""Scenes in webdataset tar shards: encode, write atomically, list and read back.

One scene is one webdataset sample: tar members `<key>.<field>.<ext>` next to each other, where
`<key>` is `{split}-{scene_index:08d}`; which member holds each field and its bytes are
`datagen.codecs` (docs/FORMAT.md). A shard's scenes are listed by the dataset file beside it
(`dataset_record`).

A dataset folder is one dataset: where a folder holds a dataset file, `iter_samples` refuses
(`ForeignData`, one line naming the file) a shard that is not one of its shards (a name not of
its `shard_pattern`, an index beyond `num_shards`) and a scene that is not one of its scenes (a
key that does not belong to that shard or repeats, another seed, split, size or config).
"""

from __future__ import annotations

import glob
import io
import json
import logging
import os
import tarfile
from pathlib import Path
from typing import Any, Iterable, Iterator, Sequence

from c4d_core.errors import UserError
from c4d_core.files import check_regular_file, disk_error, remove_quietly, special_file_kind
from c4d_core.geometry import intrinsics_problem
from c4d_core.sniff import EMPTY, TAR, file_format
from datagen.codecs import (ARRAY_FIELDS, CHECKSUMS, DECODE_ERRORS, FORMAT_1_RGB, REQUIRED_FIELDS,
                            crc32, decode_array, decode_field, encode_field, member_suffix,
                            to_json_bytes, wrong_layout)
from datagen.jobs import SHARD_PATTERN, config_digest
from datagen.scene import Scene

log = logging.getLogger(__name__)

KEY_PATTERN = "{split}-{scene_index:08d}"
ALWAYS_READ = ("intrinsics", "meta")  # `decode_scene` needs these whatever fields are asked for


def scene_key(split: str, scene_index: int) -> str:
    """The webdataset key of a scene: no dots, sortable, e.g. `train-00000042`."""
    return KEY_PATTERN.format(split=split, scene_index=scene_index)


# --- scenes -------------------------------------------------------------------------------------


def _check_scene(scene: Scene) -> None:
    """Raise ValueError if an array field breaks the contract's dtype or rank (a generator bug)."""
    for name, (dtype, ndim) in ARRAY_FIELDS.items():
        value = getattr(scene, name)
        got = None if value is None else wrong_layout(name, value)
        if got is not None:
            raise ValueError(f"Scene.{name} must be a {dtype} array of rank {ndim}, got {got}")
    frames = {name: getattr(scene, name).shape[0] for name in ("rgb", "intrinsics", "cam_to_world")}
    if len(set(frames.values())) != 1:
        raise ValueError(f"Scene fields disagree on the number of frames: {frames}")


def encode_scene(scene: Scene, key: str) -> dict[str, Any]:
    """A webdataset sample for `scene`: {'__key__': key, '<field>.<ext>': bytes, ...}.

    Members follow the Scene field order, so `meta.json` comes last: a shard cut anywhere inside
    a scene loses that scene's meta, which `decode_scene` reports.
    """
    if "." in key or "/" in key:
        raise ValueError(f"a sample key may contain neither '.' nor '/': {key!r}")
    _check_scene(scene)
    sample: dict[str, Any] = {"__key__": key}
    for name in Scene.field_names():
        value = getattr(scene, name)
        if value is not None:
            sample[member_suffix(name)] = encode_field(name, value)
    meta = sample.pop(member_suffix("meta"), None)
    sums = {suffix: crc32(data) for suffix, data in sample.items() if suffix != "__key__"}
    if meta is not None:
        sums[member_suffix("meta")] = crc32(meta)
    sample[CHECKSUMS] = to_json_bytes({"crc32": sums})
    if meta is not None:
        sample[member_suffix("meta")] = meta  # still the last member
    return sample


def verify_checksums(sample: dict[str, Any]) -> bool:
    """Check the members of `sample` against its `checksums.json`; False if it has none (format 2).

    Members not read (skipped by `iter_samples(fields=...)`) are only checked for presence, via
    the `__members__` list `iter_samples` adds. Raises `UserError` naming the sample and member
    on a missing member or a checksum mismatch, and on a missing `checksums.json` where the
    sample's `__format__` (from its dataset file) is 3 or newer, which requires one.
    """
    key, where = sample.get("__key__", "?"), _where(sample)
    if CHECKSUMS not in sample:
        version = sample.get("__format__")
        if isinstance(version, int) and version >= 3:
            raise UserError(f"scene {key!r}{where} lacks its member {CHECKSUMS!r}, which its "
                            f"dataset file requires (format {version}; deleted from the shard?); "
                            f"{REGENERATE}")
        return False
    try:
        sums = json.loads(bytes(sample[CHECKSUMS]).decode("utf-8"))["crc32"]
        sums = {str(k): str(v) for k, v in sums.items()}
    except (ValueError, TypeError, KeyError, AttributeError, UnicodeDecodeError) as exc:
        raise UserError(f"scene {key!r}{where}: member {CHECKSUMS!r} is corrupt ({exc}); "
                        f"{REGENERATE}") from exc
    present = set(sample.get("__members__", ())) | {k for k in sample if not k.startswith("__")}
    for suffix, expected in sums.items():
        if suffix not in present:
            raise UserError(f"scene {key!r}{where} lacks its member {suffix!r} (deleted from the "
                            f"shard?); {REGENERATE}")
        if suffix in sample and crc32(sample[suffix]) != expected:
            raise UserError(f"scene {key!r}{where}: member {suffix!r} fails its CRC-32 check "
                            f"(stored {expected}, read {crc32(sample[suffix])}), so the shard is "
                            f"damaged; {REGENERATE}")
    return True


REGENERATE = "regenerate this shard (delete it and rerun the same `c4d datagen` command)"


def _where(sample: dict[str, Any]) -> str:
    return f" in {sample['__url__']}" if "__url__" in sample else ""


def decode_scene(sample: dict[str, Any], fields: Iterable[str] | None = None) -> Scene:
    """The `Scene` of a webdataset sample (raw bytes per member, as `encode_scene` makes them).

    `fields`: decode only these Scene fields (the others are None), e.g. to skip depth and flow
    when training. The members present are checked against `checksums.json` where the sample has
    one. Raises `UserError` naming the sample key (and shard) if a member is missing or corrupt,
    or its intrinsics are no camera's (`c4d_core.geometry.intrinsics_problem`).
    """
    key = sample.get("__key__", "?")
    where = _where(sample)
    wanted = set(Scene.field_names()) if fields is None else set(fields)
    unknown = wanted - set(Scene.field_names())
    if unknown:
        raise UserError(
            f"unknown Scene fields {sorted(unknown)}; choose from {Scene.field_names()}"
        )
    verify_checksums(sample)
    for required in REQUIRED_FIELDS:
        if required != "rgb" and (required in ALWAYS_READ or required in wanted) \
                and member_suffix(required) not in sample:
            raise UserError(
                f"scene {key!r}{where} has no {member_suffix(required)!r} member, so the shard "
                f"is truncated, damaged or was not written by `c4d datagen`; {REGENERATE}"
            )
    if "rgb" in wanted and member_suffix("rgb") not in sample and FORMAT_1_RGB not in sample:
        raise UserError(
            f"scene {key!r}{where} has no rgb member ({member_suffix('rgb')!r}, or "
            f"{FORMAT_1_RGB!r} in format 1 shards); it was written by another version of "
            "`c4d datagen`: read it with that version or regenerate it"
        )
    values: dict[str, Any] = {}
    suffix = member_suffix("intrinsics")
    try:
        num_frames = decode_array(sample[suffix]).shape[0]
        for name in Scene.field_names():
            suffix = member_suffix(name)
            if name == "rgb" and suffix not in sample and FORMAT_1_RGB in sample:
                suffix = FORMAT_1_RGB  # a format 1 shard
            data = sample.get(suffix)
            if name not in wanted or data is None:
                values[name] = None
            else:
                values[name] = decode_field(name, suffix, data, num_frames)
    except DECODE_ERRORS as exc:
        raise UserError(f"scene {key!r}{where}: member {suffix!r} is corrupt ({exc}); {REGENERATE}"
                        ) from exc
    camera = values["intrinsics"] is not None and intrinsics_problem(values["intrinsics"])
    if camera:  # where read, a reader unprojects with them
        raise UserError(f"scene {key!r}{where}: {camera}; {REGENERATE}")
    return Scene(**values)


# --- shard files --------------------------------------------------------------------------------


def _tar_info(name: str, size: int) -> tarfile.TarInfo:
    """A tar header with fixed owner, mode and time, so equal scenes give byte-equal shards."""
    info = tarfile.TarInfo(name)
    info.size, info.mode, info.mtime = size, 0o444, 0
    info.uname = info.gname = ""
    return info


class ShardWriter:
    """Writes one shard under a temporary name and renames it into place on `close()`.

    A crash leaves at most `<name>.partial`, never a half-written `<name>`; a stale partial file
    is overwritten by the next attempt. Use as a context manager: on an exception the partial
    file is removed and disk errors become `UserError`.
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.partial = self.path.with_name(self.path.name + ".partial")
        self.count = 0
        try:
            self._file = open(self.partial, "wb")
        except OSError as exc:
            raise disk_error(self.partial, exc) from exc
        self._tar = tarfile.open(fileobj=self._file, mode="w", format=tarfile.USTAR_FORMAT)

    def write(self, sample: dict[str, Any]) -> None:
        """Append one sample (`__key__` plus `suffix -> bytes`), members in the sample's order."""
        key = sample["__key__"]
        try:
            for suffix, data in sample.items():
                if suffix.startswith("__"):
                    continue
                self._tar.addfile(_tar_info(f"{key}.{suffix}", len(data)), io.BytesIO(data))
        except OSError as exc:
            raise disk_error(self.partial, exc) from exc
        self.count += 1

    def close(self) -> Path:
        """Finish the tar, flush it to disk and rename it to its final name; if that fails (the
        disk fills during the last flush), the partial file is removed before the error."""
        try:
            self._tar.close()
            self._file.flush()
            os.fsync(self._file.fileno())
            self._file.close()
            os.replace(self.partial, self.path)
        except OSError as exc:
            self.abort()
            raise disk_error(self.path, exc) from exc
        return self.path

    def abort(self) -> None:
        """Drop the partial file (after an error)."""
        for close in (self._tar.close, self._file.close):
            try:
                close()
            except OSError:
                pass  # the file is being deleted anyway (e.g. the disk is full)
        remove_quietly(self.partial)

    def __enter__(self) -> "ShardWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


# --- reading ------------------------------------------------------------------------------------


def _is_glob(text: str) -> bool:
    return any(c in text for c in "*?[")


def list_shards(source: str | Path | Sequence[str | Path], split: str | None = None) -> list[Path]:
    """Shard paths of `source`, in reading order.

    `source`: a directory (its `*.tar`, sorted; only `{split}-*.tar` when `split` is given), a
    shard path, a glob (sorted), or a list of these (kept in the given order). The dataset
    files beside them are read first: a damaged one is refused here, before any shard is read;
    a directory missing shards its dataset file lists is named in a warning (`warn_if_incomplete`).
    """
    if isinstance(source, (list, tuple)):
        return [shard for item in source for shard in list_shards(item, split)]
    text = os.fspath(source)
    if _is_glob(text):
        shards = sorted(Path(p) for p in glob.glob(text) if p.endswith(".tar"))
        if not shards:
            raise UserError(f"no shard matches {text!r}; check the pattern (shards end in .tar)")
        return _with_readable_dataset_files(shards)
    path = Path(text)
    if path.is_dir():
        shards = sorted(path.glob(f"{split}-*.tar" if split else "*.tar"))
        if not shards:
            which = f" of split {split!r}" if split else ""
            raise UserError(
                f"no shards{which} in directory {path}; generate some with `c4d datagen`"
            )
        splits = sorted({p.name.rsplit("-", 1)[0] for p in shards})
        if len(splits) > 1:
            raise UserError(
                f"directory {path} holds shards of several splits ({', '.join(splits)}); "
                "pass split=... or a glob such as DIR/train-*.tar"
            )
        _with_readable_dataset_files(shards)
        warn_if_incomplete(path, splits[0], shards)
        return shards
    if path.is_file():
        if kind := not_a_shard(path):
            raise UserError(f"{path} is not a shard of `c4d datagen` (a .tar): it is {kind}; give "
                            "a `c4d datagen` folder, a .tar shard or a glob of shards")
        return _with_readable_dataset_files([path])
    check_regular_file(path, "shard source", "give a directory, a .tar shard or a glob")
    raise UserError(
        f"shard source {text!r} does not exist; give a directory, a .tar shard or a glob"
    )


def not_a_shard(path: str | Path) -> str | None:
    """What the file `path` is where it is plainly no shard ("a Python pickle", "a PNG image",
    ...; `c4d_core.sniff`), else None: a tar archive, or a .tar empty or of no known format (a
    damaged shard, reported as such when read)."""
    kind = file_format(path)
    if kind == TAR or (kind in (None, EMPTY) and Path(path).suffix == ".tar"):
        return None
    return kind or "a file of no format c4d knows, not a tar archive"


def _with_readable_dataset_files(shards: list[Path]) -> list[Path]:
    """`shards`, once the dataset file beside each (one read per folder and split) is known to be
    absent or readable (`_read_dataset_file` raises for a damaged one)."""
    for folder, split in sorted({(s.parent, parsed[0]) for s in shards
                                 if (parsed := _split_and_index(s)) is not None}):
        _read_dataset_file(folder, split)
    return shards


def iter_samples(shard: str | Path, fields: Iterable[str] | None = None) -> Iterator[dict[str, Any]]:
    """Webdataset samples of one shard, in tar order, each with `__key__`, `__url__`,
    `__members__` (the suffixes of all its members, read or not) and, where the shard's dataset
    file (`dataset_record`) gives it, `__format__` (its format version).

    `fields`: read only the members of these Scene fields (and those `decode_scene` always needs);
    the others are skipped by seeking past them, not read (`checksums.json` is always read).
    Default: every member.
    Raises `UserError` naming the shard and the sample key if the tar is truncated or corrupt,
    after yielding the last scene read in full (its `meta.json`, the last member, is complete).
    """
    shard = str(shard)
    if os.path.isdir(shard):
        raise UserError(f"shard {shard} is a folder, not a shard (a .tar file); move it out of "
                        "the shard set or rerun `c4d datagen`")
    check_regular_file(shard, "shard", "move it out of the shard set or rerun `c4d datagen`")
    belongs = DatasetMember.of(shard)
    version = belongs.record.get("format_version") if belongs else None
    wanted = None if fields is None else {*fields, *ALWAYS_READ}
    sample: dict[str, Any] = {}
    name = ""
    error: UserError | None = None
    try:
        with tarfile.open(shard, mode="r:") as tar:  # seekable: skipped members are not read
            for member in tar:
                name = member.name
                if not member.isfile():
                    continue
                key, _, suffix = os.path.basename(name).partition(".")
                # a new scene: another key, or the same key again (a member repeats)
                if sample and (key != sample["__key__"] or suffix in sample["__members__"]):
                    if belongs:
                        belongs.check(sample)
                    yield sample
                    sample = {}
                if not sample:
                    sample = {"__key__": key, "__url__": shard, "__members__": []}
                    if isinstance(version, int):
                        sample["__format__"] = version
                sample["__members__"].append(suffix)
                if wanted is None or suffix == CHECKSUMS or suffix.partition(".")[0] in wanted:
                    sample[suffix] = tar.extractfile(member).read()
            end = tar.offset  # where the end-of-archive marker (two zero blocks) must follow
        with open(shard, "rb") as f:
            f.seek(end)
            if f.read(2 * tarfile.BLOCKSIZE) != bytes(2 * tarfile.BLOCKSIZE):
                error = UserError(
                    f"shard {shard} is truncated or corrupt after member {name!r}: no "
                    "end-of-archive marker follows, so what came after it is lost; delete it "
                    "and rerun `c4d datagen`"
                )
    except (tarfile.TarError, EOFError, OSError) as exc:
        where = f"at member {name!r}" if name else "at its start"
        error = UserError(
            f"shard {shard} is corrupt or truncated {where} (scene "
            f"{(name.partition('.')[0] or '?')!r}): {exc}; delete it and rerun `c4d datagen`"
        )
        error.__cause__ = exc
    if sample and (error is None or member_suffix("meta") in sample):
        if belongs:
            belongs.check(sample)
        yield sample  # the last scene; before an error only if read in full
    if error is not None:
        raise error


DATASET_FILE = "dataset-{split}.json"  # written by `c4d datagen` beside its shards


def _split_and_index(shard: str | Path) -> tuple[str, int] | None:
    """(split, shard index) of a shard named as `c4d datagen` names them, else None."""
    split, _, index = Path(shard).name.removesuffix(".tar").rpartition("-")
    return (split, int(index)) if split and index.isdigit() else None


def _read_dataset_file(folder: Path, split: str) -> dict[str, Any]:
    """The dataset file of `split` in `folder`; {} where there is none. One that is there but
    cannot be read (truncated, not JSON, no permission) is a `UserError` naming it: its shards
    would otherwise all look foreign."""
    path = folder / DATASET_FILE.format(split=split)
    advice = ("delete it and rerun the same `c4d datagen` command to rewrite it (finished shards "
              "are kept), or delete it alone to read the shards without it")
    check_regular_file(path, "the dataset file", advice)  # a named pipe would never be read
    try:
        record = json.loads(path.read_text())
        damage = None if isinstance(record, dict) else "not a JSON object"
    except FileNotFoundError:
        return {}
    except OSError as exc:
        damage = f"unreadable: {exc.strerror or exc}"
    except ValueError as exc:  # a cut-off file: "Expecting ... delimiter: line 9 column 1"
        damage = f"not valid JSON: {exc}"
    if damage:
        raise UserError(f"the dataset file {path} is damaged or unreadable ({damage}); {advice}")
    return record


def dataset_record(shard: str | Path) -> dict[str, Any]:
    """The dataset file (`dataset-{split}.json`: format_version, num_scenes, scenes_per_shard,
    num_shards, ...) beside `shard`; {} if there is none (a damaged one: `UserError`)."""
    parsed = _split_and_index(shard)
    return {} if parsed is None else _read_dataset_file(Path(shard).parent, parsed[0])


class ForeignData(UserError):
    """A shard or scene in a dataset folder that is not part of the dataset its file describes."""


class DatasetMember:
    """What the dataset file beside a shard says the shard must hold: its name, its scene keys
    in order, and its scenes' seed, split, size and config digest. `check` raises `ForeignData`."""

    def __init__(self, shard: str, record: dict[str, Any], split: str, index: int):
        self.shard, self.record = shard, record
        config = record.get("config") if isinstance(record.get("config"), dict) else {}
        self.identity = {"seed": record.get("seed"), "split": split,
                         "resolution": config.get("resolution"), "num_frames": config.get("frames")}
        self.digest = config_digest(config) if config else None
        per_shard, total = record.get("scenes_per_shard"), record.get("num_scenes")
        self.keys: list[str] | None = None
        if isinstance(per_shard, int) and isinstance(total, int):
            self.keys = [scene_key(split, i) for i in
                         range(index * per_shard, min((index + 1) * per_shard, total))]
        self.seen: set[str] = set()

    @classmethod
    def of(cls, shard: str | Path) -> "DatasetMember | None":
        """The membership of `shard` in the dataset of its folder; None where the folder holds no
        dataset file (loose shards). Raises `ForeignData` for a shard that is not one of its
        shards by name."""
        shard = str(shard)
        folder, name = Path(shard).parent, Path(shard).name
        if not any(folder.glob(DATASET_FILE.format(split="*"))):
            return None
        parsed = _split_and_index(shard)
        record = _read_dataset_file(folder, parsed[0]) if parsed else {}
        pattern = str(record.get("shard_pattern", SHARD_PATTERN))
        if not record or name != pattern.format(split=parsed[0], shard=parsed[1]):
            raise ForeignData(f"{shard} does not belong to the dataset in {folder}: its name is not "
                              f"of the dataset's shard_pattern {pattern!r} (from the dataset-SPLIT.json "
                              "there); move it out of the folder")
        num_shards = record.get("num_shards")
        if isinstance(num_shards, int) and parsed[1] >= num_shards:
            raise ForeignData(f"{shard} does not belong to the dataset in {folder}: shard index "
                              f"{parsed[1]} is beyond its num_shards={num_shards}; move it out of "
                              "the folder")
        return cls(shard, record, parsed[0], parsed[1])

    def check(self, sample: dict[str, Any]) -> None:
        """`ForeignData` unless `sample` (raw, with its meta member) is one of this shard's scenes."""
        key = sample["__key__"]
        if self.keys is not None and key not in self.keys:
            raise ForeignData(f"{self.shard}: scene {key!r} does not belong to this shard of the "
                              f"dataset (it holds {self.keys[0]} .. {self.keys[-1]}); the shard is "
                              "from another dataset: move it out of the folder")
        if key in self.seen:
            raise ForeignData(f"{self.shard}: scene key {key!r} repeats; the shard was not written "
                              "by `c4d datagen` for this dataset: move it out of the folder")
        self.seen.add(key)
        raw = sample.get(member_suffix("meta"))
        try:
            meta = json.loads(bytes(raw).decode("utf-8")) if raw is not None else {}
        except (UnicodeDecodeError, ValueError):
            return  # a corrupt meta: `decode_scene` reports it
        meta = meta if isinstance(meta, dict) else {}
        differs = [f"{name} {meta[name]!r}, the dataset's {want!r}" for name, want in self.identity.items()
                   if name in meta and want is not None and meta[name] != want]
        if not differs and self.digest and meta.get("config_digest", self.digest) != self.digest:
            differs.append(f"another config: config_digest {meta['config_digest']!r}, the dataset's "
                           f"{self.digest!r}")
        if differs:
            raise ForeignData(f"{self.shard}: scene {key!r} is from another dataset ({'; '.join(differs)}) "
                              "than the dataset file beside it describes; move the shard out of the folder")


def first_scene_meta(shard: str | Path) -> dict[str, Any]:
    """The `meta.json` of the first scene in `shard` (seed, config_digest, ...), read without the
    scene's other members; {} where the shard or the member cannot be read."""
    suffix = "." + member_suffix("meta")
    if special_file_kind(shard) is not None:  # a named pipe would wait for a writer forever
        return {}
    try:
        with tarfile.open(shard, mode="r:") as tar:
            for member in tar:
                if member.isfile() and member.name.endswith(suffix):
                    meta = json.loads(tar.extractfile(member).read().decode("utf-8"))
                    return meta if isinstance(meta, dict) else {}
    except (tarfile.TarError, EOFError, OSError, UnicodeDecodeError, ValueError):
        pass
    return {}


def scene_indices(shard: str | Path) -> range:
    """The indices of the scenes `shard` was written with, from its dataset file; empty if unknown."""
    parsed, record = _split_and_index(shard), dataset_record(shard)
    try:
        per_shard = int(record["scenes_per_shard"])
        return range(parsed[1] * per_shard, min((parsed[1] + 1) * per_shard, int(record["num_scenes"])))
    except (KeyError, TypeError, ValueError):
        return range(0)


def scenes_in_shard(shard: str | Path) -> int | None:
    """How many scenes `shard` was written with, from its dataset file; None if unknown."""
    return len(scene_indices(shard)) or None


def index_ranges(indices: Iterable[int]) -> str:
    """Sorted indices as runs, e.g. [3, 4, 5, 9] -> "3..5, 9"; "?" for none."""
    runs: list[list[int]] = []
    for index in sorted(indices):
        if runs and index == runs[-1][1] + 1:
            runs[-1][1] = index
        else:
            runs.append([index, index])
    return ", ".join(f"{a}..{b}" if b > a else str(a) for a, b in runs) or "?"


def lost_scenes(shard: str | Path, read: int) -> int:
    """How many scenes an unreadable `shard` lost after `read` of them were read: the rest of
    the scenes its dataset file gives it, at least 1 (1 when unknown)."""
    return max(1, (scenes_in_shard(shard) or 0) - read)


def missing_shards(shards: Sequence[str | Path]) -> list[Path]:
    """The shards that the dataset files beside `shards` list (`num_shards` of them, named by
    SHARD_PATTERN) but that do not exist, in order."""
    missing: list[Path] = []
    for folder, split in sorted({(Path(s).parent, parsed[0]) for s in shards
                                 if (parsed := _split_and_index(s)) is not None}):
        num_shards = _read_dataset_file(folder, split).get("num_shards")
        for index in range(num_shards if isinstance(num_shards, int) else 0):
            path = folder / SHARD_PATTERN.format(split=split, shard=index)
            if not path.exists():
                missing.append(path)
    return missing


_WARNED_INCOMPLETE: set[tuple[str, str]] = set()  # the (folder, split) warned about in this process


def warn_if_incomplete(folder: Path, split: str, shards: Sequence[Path]) -> None:
    """Warn, once per folder and split in a process, where the dataset file of `split` in `folder`
    (whose shards are `shards`) lists shards the folder lacks: how many of its `num_shards`, and
    which of its `num_scenes` they held."""
    key = (str(folder.resolve()), split)
    if key in _WARNED_INCOMPLETE:
        return
    _WARNED_INCOMPLETE.add(key)
    missing = missing_shards(shards)
    if missing:
        record = _read_dataset_file(folder, split)
        scenes = [i for path in missing for i in scene_indices(path)]
        log.warning("%s is an incomplete dataset: %d of the %s shards its %s lists are missing "
                    "(%d of its %s scenes: %s), so they are not read; rerun the same `c4d datagen` "
                    "command to write them", folder, len(missing), record.get("num_shards"),
                    DATASET_FILE.format(split=split), len(scenes), record.get("num_scenes", "?"),
                    index_ranges(scenes))


def read_scenes(
    source: str | Path | Sequence[str | Path],
    split: str | None = None,
    fields: Iterable[str] | None = None,
) -> Iterator[Scene]:
    """Yield the `Scene`s of `source` in a deterministic order (shard order, then tar order).

    `source`: a directory of shards, a shard path, a glob, or a list of these (see `list_shards`).
    `fields`: decode only these Scene fields, the others are None (default: all).
    """
    fields = None if fields is None else list(fields)
    for shard in list_shards(source, split):
        for sample in iter_samples(shard, fields):
            yield decode_scene(sample, fields)
