"""TFDS MOVi records (movi_e, panning_movi_e, movi_f; any resolution config) read as `Scene`s,
without TensorFlow.

A source is a folder in TFDS's layout, or record files of one:

    ROOT/movi_e/256x256/1.0.0/dataset_info.json, features.json,
                              movi_e-validation.tfrecord-00000-of-00004, ...

given as ROOT (or any folder above exactly one version folder), the version folder, a record
file, a glob of record files, or "FOLDER:SPLIT" (TFDS's way of naming a split, e.g.
`data/movi_e/256x256/1.0.0:validation`). A folder with several splits needs the split named.

How the bytes are read (reference kubric_movi.md 2.2, 8.2):
- TFRecord framing, per record: uint64 length, uint32 masked CRC-32C of the length, the data,
  uint32 masked CRC-32C of the data (all little-endian; mask: ((crc >> 15) | (crc << 17)) +
  0xa282ead8). Both checksums are verified: a damaged record is a `UserError` naming the file and
  the record. Listing a source reads only the 12-byte headers (`scan_records`).
- The data is a `tf.train.Example` (protobuf): a map from feature name to a bytes, float or int64
  list, decoded here from the wire format (`parse_example`); packed int64 lists (the flows, T*H*W*2
  uint16 values each) are decoded with numpy, all varints at once (`varints`).
- Images: one PNG per frame (`video` 8-bit RGB, `segmentations` 8-bit grey, `depth` 16-bit grey,
  `normal` and `object_coordinates` 16-bit RGB), decoded with OpenCV (Pillow reads 16-bit RGB
  PNGs as 8-bit).

What each feature becomes (our conventions, docs/FORMAT.md):
- rgb = video; segmentation = segmentations (0 background, k = instances[k-1], as ours).
- depth: the records hold the Euclidean distance from the camera centre d as uint16 over
  `metadata/depth_range` [lo, hi]: d = v / 65535 * (hi - lo) + lo; our z-depth is
  z = d / |K^-1 [u, v, 1]| at each pixel centre (u, v).
- intrinsics: Kubric's camera has `focal_length` f and `sensor_width` s (mm) with a horizontal
  sensor fit: the sensor's width spans the image's W pixels, so fx = f / s * W; pixels are
  square, so fy = fx = f / s * W as well (also on non-square frames: TAP-Vid-Kubric's
  `get_camera_matrices` uses f / s * H / W for the height-normalised fy, which needs W / H, and
  misplaces tracks by up to 24 px there, reference 8.4); the principal point is the image
  centre, raster (W/2, H/2), ours ((W - 1) / 2, (H - 1) / 2) (`intrinsics_from_lens`).
- cam_to_world: `camera/positions` and `camera/quaternions` (w, x, y, z) give Blender's camera
  (looking down -z, y up); OpenCV's (z forward, y down) is its rotation times diag(1, -1, -1).
- object_to_world (K,T,4,4): `instances/positions` and `instances/quaternions` (w, x, y, z), a
  rigid pose (Kubric's object scale is in `bboxes_3d`, the box (bounds x scale) carried by this
  pose, and in `objects[k]["scale"]`; a point on the object moves with the rigid pose).
- flow_fwd = `forward_flow` (drow, dcol) as (dx, dy); flow_bwd = minus `backward_flow` as (dx, dy)
  (Kubric's backward flow is the motion from t-1 to t, ours from t to t-1). Kubric renders a
  frame beyond each end, so every frame's flow is valid (`meta["flow_*_valid"]` all True).
- normal = v / 65535 * 2 - 1 (world space); object_coordinates = v / 65535.
- objects[k]: asset_id, category (the class index), scale, mass, friction, restitution and
  tossed = is_dynamic, where the record has them. `instances` (`INSTANCE_KEYS`): 3-D boxes,
  image positions, velocities and is_dynamic from `instances/*`, the pixel counts and 2-D boxes
  counted on the record's segmentation (Kubric's are at its render resolution); `events` None.
- Tracks: the records have none; they are drawn as TAP-Vid-Kubric draws them
  (`datagen.annotate.tapvid_kubric_tracks`: 256 tracks on a stride-4 grid, at most 10 % of a
  segment's grid points, 1 % depth tolerance), seeded by [options.seed, unit.index]. As there,
  a background query is lifted to 3-D from the depth and an object query from its
  `object_coordinates` in the object's `instances/bboxes_3d` (`datagen.annotate.BoxLift`; the
  16-bit depth alone leaves object tracks up to 0.05 px off Kubric's, docs/RESULTS.md 7.1).
- moving: by `options.mobility_rule` ("point": the track's world displacement since the previous
  frame > 0.01, our label; "object": its object's position change > 0.01, the paper appendix's
  rule), `datagen.foreign.ReadOptions`.

Downscaled configs (128x128) were made by Kubric's builder with nearest-neighbour subsampling
(pixel (i, j) of the full frame at (2i, 2j)) for every layer but the video (box average), so
their labels sit a quarter pixel off the small frame's pixel centres; we do not correct this,
as TAP-Vid-Kubric does not.
"""

from __future__ import annotations

import functools
import glob
import json
import logging
import re
import struct
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path

import crc32c
import cv2
import numpy as np

from c4d_core import geometry
from c4d_core.errors import UserError
from datagen.annotate import BoxLift, segment_boxes, tapvid_kubric_tracks
from datagen.export.kubric import euclidean_range
from datagen.foreign import ReadOptions, Unit, mobility_labels
from datagen.foreign.kubric_worker import (camera_from_kubric, decode_range, pixels_from_kubric,
                                           pose_from_kubric)
from datagen.scene import INSTANCE_KEYS, OPTIONAL_LAYERS, Scene

log = logging.getLogger(__name__)

KIND = "tfds-movi"
EXPECTED = ("TFDS MOVi records (movi_e, panning_movi_e, movi_f): a folder with dataset_info.json "
            "beside NAME-SPLIT.tfrecord-NNNNN-of-NNNNN files, or such files")
INFO_FILE = "dataset_info.json"
# NAME-SPLIT.tfrecord[-NNNNN-of-NNNNN]: TFDS's file names (`filepathTemplate`)
RECORD_NAME = re.compile(r"^(?P<name>.+)-(?P<split>[^-]+)\.tfrecord(?:-(?P<shard>\d+)-of-(?P<of>\d+))?$")
HEADER = struct.Struct("<QI")  # length, masked CRC-32C of the length
FOOTER = struct.Struct("<I")  # masked CRC-32C of the data
MASK_DELTA = 0xA282EAD8
NUM_TRACKS = 256  # TAP-Vid-Kubric's tracks per video
# The features every MOVi record has that a Scene needs (the others are optional).
REQUIRED = ("video", "segmentations", "depth", "metadata/depth_range", "camera/focal_length",
            "camera/sensor_width", "camera/positions", "camera/quaternions",
            "instances/positions", "instances/quaternions")


# --- TFRecord framing -------------------------------------------------------------------------


def masked_crc(data: bytes) -> int:
    """TFRecord's masked CRC-32C of `data`: ((crc >> 15) | (crc << 17)) + 0xa282ead8, 32 bits."""
    crc = crc32c.crc32c(data)
    return ((((crc >> 15) | (crc << 17)) & 0xFFFFFFFF) + MASK_DELTA) & 0xFFFFFFFF


def scan_records(path: Path) -> tuple[list[int], str | None]:
    """Byte offsets of the records of a TFRecord file, from their headers alone (the data is
    sought past, not read), and the damage that stopped the scan (None: the file ends cleanly
    after its last record). A header whose length fails its checksum, or a file cut inside a
    record, ends the scan: the records after it cannot be found."""
    offsets: list[int] = []
    size = path.stat().st_size
    with open(path, "rb") as handle:
        offset = 0
        while offset < size:
            header = handle.read(HEADER.size)
            if len(header) < HEADER.size:
                return offsets, f"the file ends inside the header of record {len(offsets)}"
            length, crc = HEADER.unpack(header)
            if masked_crc(header[:8]) != crc:
                return offsets, (f"the length of record {len(offsets)} fails its checksum (at "
                                 f"byte {offset})")
            end = offset + HEADER.size + length + FOOTER.size
            if end > size:
                return offsets, f"the file ends inside record {len(offsets)}"
            offsets.append(offset)
            offset = end
            handle.seek(offset)
    return offsets, None


def read_record(path: str, offset: int, name: str) -> bytes:
    """The data of the record at byte `offset` of `path`, both checksums verified (`UserError`
    naming `name`, the record, where one fails)."""
    with open(path, "rb") as handle:
        handle.seek(offset)
        header = handle.read(HEADER.size)
        if len(header) < HEADER.size:
            raise UserError(f"{name}: the file ends inside its header (cut short?); fetch the "
                            "file again")
        length, crc = HEADER.unpack(header)
        if masked_crc(header[:8]) != crc:
            raise UserError(f"{name} is damaged: its length fails its checksum; fetch the file "
                            "again")
        data = handle.read(length)
        footer = handle.read(FOOTER.size)
    if len(data) < length or len(footer) < FOOTER.size:
        raise UserError(f"{name}: the file ends inside the record (cut short?); fetch the file "
                        "again")
    if masked_crc(data) != FOOTER.unpack(footer)[0]:
        raise UserError(f"{name} is damaged: its data fails its CRC-32C checksum; fetch the file "
                        "again")
    return data


# --- tf.train.Example, from the protobuf wire format -----------------------------------------
# Example { Features features = 1 }  Features { map<string, Feature> feature = 1 }
# Feature { oneof { BytesList bytes_list = 1; FloatList float_list = 2; Int64List int64_list = 3 } }
# BytesList { repeated bytes value = 1 }  FloatList { repeated float value = 1 [packed] }
# Int64List { repeated int64 value = 1 [packed] }
BYTES, FLOATS, INTS = 1, 2, 3


def _varint(data: bytes, pos: int) -> tuple[int, int]:
    """One base-128 varint at `pos`: (value, position after it)."""
    value = shift = 0
    while True:
        byte = data[pos]
        pos += 1
        value |= (byte & 0x7F) << shift
        if byte < 0x80:
            return value, pos
        shift += 7
        if shift > 63:
            raise ValueError("a varint longer than 10 bytes")


def _fields(data: bytes, start: int, end: int) -> Iterator[tuple[int, int, int, int]]:
    """The fields of the message data[start:end]: (field number, wire type, a, b) with
    data[a:b] the payload of a length-delimited (2) or fixed (1, 5) field, and (value, -1) for a
    varint (0)."""
    pos = start
    while pos < end:
        tag, pos = _varint(data, pos)
        number, wire = tag >> 3, tag & 7
        if wire == 0:
            value, pos = _varint(data, pos)
            yield number, wire, value, -1
            continue
        if wire == 2:
            length, pos = _varint(data, pos)
        elif wire in (1, 5):
            length = 8 if wire == 1 else 4
        else:
            raise ValueError(f"wire type {wire} is not used by tf.train.Example")
        if pos + length > end:
            raise ValueError("a field runs past the end of its message")
        yield number, wire, pos, pos + length
        pos += length


def parse_example(data: bytes) -> dict[str, tuple[int, int, int]]:
    """feature name -> (kind, a, b): the kind (BYTES, FLOATS, INTS; 0 for an empty Feature) and
    the bounds of its list message in `data`, decoded later by `feature_values` (so features
    not needed are never decoded). Raises ValueError for bytes that are no Example."""
    features: dict[str, tuple[int, int, int]] = {}
    for number, wire, a, b in _fields(data, 0, len(data)):
        if number != 1 or wire != 2:
            continue
        for entry_number, entry_wire, ea, eb in _fields(data, a, b):
            if entry_number != 1 or entry_wire != 2:
                continue
            key, value = None, (0, ea, ea)
            for part, part_wire, pa, pb in _fields(data, ea, eb):
                if part == 1 and part_wire == 2:
                    key = data[pa:pb].decode("utf-8")
                elif part == 2 and part_wire == 2:
                    for kind, kind_wire, ka, kb in _fields(data, pa, pb):
                        if kind in (BYTES, FLOATS, INTS) and kind_wire == 2:
                            value = (kind, ka, kb)
            if key is None:
                raise ValueError("a feature without a name")
            features[key] = value
    return features


def varints(raw: np.ndarray, small: bool = False) -> np.ndarray:
    """The values of packed varints `raw` (uint8): each value's 7-bit groups, least significant
    first, its last byte < 0x80; all values at once, one pass per group. int64 (negative ones
    take 10 bytes), or with `small` uint32, for values of at most 4 bytes (28 bits; a MOVi
    flow's uint16 values take 1-3), assembled in uint32 either way where they fit."""
    if raw.size == 0:
        return np.zeros(0, np.uint32 if small else np.int64)
    ends = np.flatnonzero(raw < 0x80)  # the last byte of each value
    if ends.size == 0 or ends[-1] != raw.size - 1:
        raise ValueError("packed varints end inside a value")
    lengths = np.diff(ends, prepend=-1).astype(np.int32)  # bytes per value
    longest = int(lengths.max())
    if small and longest > 4:
        raise ValueError(f"varints of {longest} bytes where at most 4 were expected")
    dtype = np.uint32 if longest <= 4 else np.uint64
    value = raw[ends].astype(dtype)  # the most significant group (its high bit is 0)
    for k in range(1, longest):  # then the next lower group, of the values that have one
        value = np.where(lengths > k, (value << dtype(7)) | (raw[ends - k] & 0x7F), value)
    if small:
        return value
    return value.astype(np.int64) if dtype == np.uint32 else value.view(np.int64)


def feature_values(data: bytes, feature: tuple[int, int, int], small: bool = False):
    """A feature's values: list[bytes] (BYTES), float32 (n,) (FLOATS) or int64 (n,) (INTS; with
    `small` uint32, for values below 2^28, `varints`); packed and unpacked lists alike."""
    kind, a, b = feature
    if kind == BYTES:
        return [data[x:y] for number, wire, x, y in _fields(data, a, b) if number == 1]
    chunks = []
    for number, wire, x, y in _fields(data, a, b):
        if number != 1:
            continue
        if kind == FLOATS:
            chunks.append(np.frombuffer(data, "<f4", (y - x) // 4, x) if wire in (2, 5)
                          else np.zeros(0, np.float32))
        elif wire == 2:
            chunks.append(varints(np.frombuffer(data, np.uint8, y - x, x), small))
        else:
            chunks.append(np.array([x], np.uint64).view(np.int64))
    dtype = np.float32 if kind == FLOATS else np.uint32 if small else np.int64
    return np.concatenate(chunks).astype(dtype, copy=False) if chunks else np.zeros(0, dtype)


# --- the source: folders, splits, units --------------------------------------------------------


def _record_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and RECORD_NAME.match(p.name))


def _version_folders(path: Path, depth: int = 3) -> list[Path]:
    """Folders at or below `path` (up to `depth` levels) holding dataset_info.json and records."""
    if (path / INFO_FILE).is_file() and _record_files(path):
        return [path]
    if depth == 0:
        return []
    try:
        children = sorted(p for p in path.iterdir() if p.is_dir())
    except OSError:
        return []
    return [found for child in children for found in _version_folders(child, depth - 1)]


def detect(path: Path) -> bool:
    """A record file (by its name), or a folder with a TFDS version folder at or up to three
    levels below it."""
    try:
        if path.is_file():
            return RECORD_NAME.match(path.name) is not None
        return path.is_dir() and bool(_version_folders(path))
    except OSError:
        return False


@functools.lru_cache(maxsize=16)
def dataset_info(folder: str) -> dict:
    """The version folder's dataset_info.json ({} where there is none or it is unreadable: the
    records alone are enough to read)."""
    try:
        return json.loads((Path(folder) / INFO_FILE).read_text())
    except (OSError, ValueError):
        return {}


def _split_of(path: Path) -> str:
    return RECORD_NAME.match(path.name)["split"]


def _choose_split(files: list[Path], split: str | None, where: object) -> list[Path]:
    """The record files of `split` (None: the only split there is)."""
    splits = sorted({_split_of(p) for p in files})
    if split is None:
        if len(splits) > 1:
            raise UserError(f"{where} holds the splits {', '.join(splits)}; name one, e.g. "
                            f"{where}:{'validation' if 'validation' in splits else splits[0]}")
        return files
    if split not in splits:
        raise UserError(f"{where} has no split {split!r}; its splits: {', '.join(splits)}")
    return [p for p in files if _split_of(p) == split]


def _shard_order(path: Path) -> tuple[str, int]:
    match = RECORD_NAME.match(path.name)
    return match["split"], int(match["shard"] or 0)


def _warn_missing(folder: Path, split: str, files: list[Path]) -> None:
    """One warning where dataset_info.json lists more record files of `split` than are there."""
    for entry in dataset_info(str(folder)).get("splits", []):
        listed = len(entry.get("shardLengths", []))
        if entry.get("name") == split and listed > len(files):
            log.warning("%s: %d of the %d record files of split %s that its %s lists are "
                        "missing; reading the %d there", folder, listed - len(files), listed,
                        split, INFO_FILE, len(files))


def _listed_lengths(folder: Path, split: str) -> dict[int, int]:
    """shard index -> the records dataset_info.json lists for that file of `split`."""
    for entry in dataset_info(str(folder)).get("splits", []):
        if entry.get("name") == split:
            return {i: int(n) for i, n in enumerate(entry.get("shardLengths", []))}
    return {}


def units(path, split: str | None = None) -> list[Unit]:
    """One `Unit` per record of the source (module docstring), in file order then record order;
    `where` is the record's byte offset. A file cut short or with a damaged header gives a last
    unit with the `problem` (the records after the damage cannot be found)."""
    text = str(path)
    if any(c in text for c in "*?["):
        files = sorted(Path(p) for p in glob.glob(text) if RECORD_NAME.match(Path(p).name))
        if not files:
            raise UserError(f"no TFDS record file matches {text!r} (NAME-SPLIT.tfrecord-*)")
        files = _choose_split(files, split, text)
    elif Path(text).is_file():
        if not RECORD_NAME.match(Path(text).name):
            raise UserError(f"{text} is not named as a TFDS record file (NAME-SPLIT.tfrecord-*)")
        files = [Path(text)]
    else:
        folders = _version_folders(Path(text))
        if len(folders) != 1:
            raise UserError(
                f"{text} holds {len(folders)} TFDS datasets ({', '.join(str(f) for f in folders)})"
                "; give one of their folders" if folders else
                f"{text} holds no TFDS records; expected {EXPECTED}")
        files = _choose_split(_record_files(folders[0]), split, text)
        _warn_missing(folders[0], _split_of(files[0]), files)
    result: list[Unit] = []
    for file in sorted(files, key=_shard_order):
        offsets, problem = scan_records(file)
        for number, offset in enumerate(offsets):
            result.append(Unit(KIND, str(file), len(result), f"{file} record {number}", offset))
        listed = _listed_lengths(file.parent, _split_of(file)).get(_shard_order(file)[1])
        if problem is None and listed is not None and listed > len(offsets):
            problem = (f"it holds {len(offsets)} records where its {INFO_FILE} lists {listed} "
                       "(the file is cut short)")
        if problem is not None:
            result.append(Unit(KIND, str(file), len(result), f"{file} record {len(offsets)}",
                               problem=f"{file} is damaged: {problem}; fetch the file again"))
    if not result:
        raise UserError(f"{text} holds no records (empty record files)")
    return result


# --- one record -> Scene ------------------------------------------------------------------------


def _png(frame: bytes, name: str, feature: str, dtype: type, channels: int) -> np.ndarray:
    """One PNG of `feature` as (H,W,channels) of `dtype`, RGB order."""
    image = cv2.imdecode(np.frombuffer(frame, np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise UserError(f"{name}: a frame of {feature!r} is no image it can decode; fetch the "
                        "file again")
    image = image.reshape(image.shape[:2] + (-1,))
    if image.dtype != dtype or image.shape[2] < channels:
        raise UserError(f"{name}: {feature!r} holds {image.shape[2]}-channel {image.dtype} "
                        f"frames, a MOVi record {channels}-channel {np.dtype(dtype)} ones")
    return image[..., 2::-1] if channels == 3 else image[..., :channels]


class LazyFrames:
    """Frames (T,H,W,C) indexed by integer arrays [t, y, x] (N,) -> (N,C), decoding only the
    frames in t, each once: `decode(t)` gives frame t (H,W,C)."""

    def __init__(self, decode: Callable[[int], np.ndarray]):
        self.decode, self.decoded = decode, {}

    def __getitem__(self, index: tuple[np.ndarray, np.ndarray, np.ndarray]) -> np.ndarray:
        t, y, x = (np.asarray(i) for i in index)
        out = None
        for frame in np.unique(t):
            if frame not in self.decoded:
                self.decoded[frame] = self.decode(int(frame))
            image = self.decoded[frame]
            if out is None:
                out = np.empty(t.shape + image.shape[2:], image.dtype)
            at = t == frame
            out[at] = image[y[at], x[at]]
        return out


class Record:
    """The features of one record and their decoding, errors naming the record."""

    def __init__(self, data: bytes, name: str):
        self.data, self.name = data, name
        try:
            self.features = parse_example(data)
        except (ValueError, IndexError, UnicodeDecodeError) as exc:
            raise UserError(f"{name} is no tf.train.Example ({exc}); is this a TFDS record "
                            "file?") from None

    def has(self, key: str) -> bool:
        return key in self.features

    def values(self, key: str, size: int | None = None, small: bool = False):
        """The values of feature `key` (`feature_values`); with `size`, exactly that many (else
        a `UserError`)."""
        if key not in self.features:
            raise UserError(f"{self.name} lacks the feature {key!r}, which MOVi records have; "
                            "is it a MOVi dataset (movi_e, panning_movi_e, movi_f)?")
        try:
            values = feature_values(self.data, self.features[key], small)
        except ValueError as exc:
            raise UserError(f"{self.name}: feature {key!r} cannot be decoded ({exc}); fetch the "
                            "file again") from None
        if size is not None and len(values) != size:
            raise UserError(f"{self.name}: feature {key!r} holds {len(values)} values, not the "
                            f"{size} its frames and objects need")
        return values

    def frames(self, key: str, dtype: type, channels: int, shape: tuple[int, int] | None = None
               ) -> np.ndarray:
        """(T,H,W,channels) of an image feature, one PNG per frame; `shape` (H, W) to match."""
        pngs = self.values(key)
        first = _png(pngs[0], self.name, key, dtype, channels) if pngs else None
        if first is None:
            raise UserError(f"{self.name}: feature {key!r} holds no frames")
        if shape is not None and first.shape[:2] != shape:
            raise UserError(f"{self.name}: {key!r} frames are {first.shape[:2]}, the video's "
                            f"{shape}")
        out = np.empty((len(pngs),) + first.shape, first.dtype)
        out[0] = first
        for t in range(1, len(pngs)):
            frame = _png(pngs[t], self.name, key, dtype, channels)
            if frame.shape != first.shape:
                raise UserError(f"{self.name}: frame {t} of {key!r} is {frame.shape[:2]}, "
                                f"frame 0 {first.shape[:2]}")
            out[t] = frame
        return out

    def lazy_frames(self, key: str, dtype: type, channels: int, shape: tuple[int, int, int],
                    low: float, high: float) -> LazyFrames:
        """An image feature's frames decoded on first use, v / 65535 (high - low) + low
        (`decode_range`): for a layer read only at a few frames. `shape` (T, H, W) to match."""
        pngs = self.values(key)
        if len(pngs) != shape[0]:
            raise UserError(f"{self.name}: feature {key!r} holds {len(pngs)} frames, the video "
                            f"{shape[0]}")

        def decode(t: int) -> np.ndarray:
            frame = _png(pngs[t], self.name, key, dtype, channels)
            if frame.shape[:2] != shape[1:]:
                raise UserError(f"{self.name}: {key!r} frames are {frame.shape[:2]}, the "
                                f"video's {shape[1:]}")
            return decode_range(frame, low, high)
        return LazyFrames(decode)

    def scalar(self, key: str, default=None):
        if key not in self.features:
            return default
        values = self.values(key)
        if not len(values):
            return default
        value = values[0]
        return value.decode("utf-8") if isinstance(value, bytes) else value.item()

    def flow(self, key: str, shape: tuple[int, int, int], sign: float) -> np.ndarray:
        """float32 (T,H,W,2) (dx, dy) of a flow feature: uint16 (drow, dcol) values in an int64
        list, v / 65535 * (hi - lo) + lo over its range `metadata/KEY_range`, times `sign`
        (`decode_range`)."""
        lo, hi = self.values(f"metadata/{key}_range", 2).astype(np.float64)
        raw = self.values(key, int(np.prod(shape)) * 2, small=True).reshape(shape + (2,))
        return decode_range(raw[..., ::-1], lo, hi, sign)  # dx = dcol, dy = drow


OBJECT_KEYS = {"asset_id": "asset_id", "category": "category", "scale": "scale", "mass": "mass",
               "friction": "friction", "restitution": "restitution", "is_dynamic": "tossed"}


def _objects(record: Record, count: int) -> list[dict]:
    """The K objects' scalar records: {ours: value} of each `instances/KEY` present."""
    objects: list[dict] = [{} for _ in range(count)]
    for key, ours in OBJECT_KEYS.items():
        if not record.has(f"instances/{key}"):
            continue
        values = record.values(f"instances/{key}", count)
        for k in range(count):
            value = values[k]
            objects[k][ours] = (value.decode("utf-8") if isinstance(value, bytes)
                                else bool(value) if key == "is_dynamic" else value.item())
    return objects


INSTANCE_FEATURES = ("bboxes_3d", "image_positions", "velocities", "angular_velocities",
                     "is_dynamic")


def _instances(record: Record, segmentation: np.ndarray, count: int
               ) -> dict[str, np.ndarray] | None:
    """`Scene.instances` (INSTANCE_KEYS) of the record's `instances/*` features: 3-D boxes, image
    positions, velocities, is_dynamic; pixel counts and 2-D boxes counted on the record's own
    segmentation (K,T) (Kubric's are at its render resolution). None where a feature is missing."""
    if not all(record.has(f"instances/{key}") for key in INSTANCE_FEATURES):
        return None
    num_frames, height, width = segmentation.shape

    def per_frame(key: str, *tail: int) -> np.ndarray:
        size = count * num_frames * int(np.prod(tail))
        return record.values(f"instances/{key}", size).reshape((count, num_frames) + tail)
    visible, boxes_2d = segment_boxes(segmentation, count)
    values = {"bbox_3d": per_frame("bboxes_3d", 8, 3), "bbox_2d": boxes_2d,
              "visible_pixels": visible,
              "image_position": pixels_from_kubric(per_frame("image_positions", 2), height, width),
              "velocity": per_frame("velocities", 3),
              "angular_velocity": per_frame("angular_velocities", 3),
              "is_dynamic": record.values("instances/is_dynamic", count).astype(bool)}
    return {key: np.ascontiguousarray(values[key], dtype)
            for key, (dtype, _) in INSTANCE_KEYS.items()}


def _box_lift(record: Record, layers: dict, count: int, shape: tuple[int, int, int]
              ) -> BoxLift | None:
    """Object points lifted from `object_coordinates` in `instances/bboxes_3d`, as
    TAP-Vid-Kubric lifts them (exact, where the records' 16-bit depth is not); None where the
    record lacks either (then from depth)."""
    if not (record.has("object_coordinates") and record.has("instances/bboxes_3d")):
        return None
    boxes = record.values("instances/bboxes_3d", count * shape[0] * 24)
    coordinates = layers.get("object_coordinates")
    if coordinates is None:  # not wanted whole: only the query frames are decoded
        coordinates = record.lazy_frames("object_coordinates", np.uint16, 3, shape, 0.0, 1.0)
    return BoxLift(coordinates, boxes.reshape(count, shape[0], 8, 3).astype(np.float64))


def decode_record(data: bytes, unit: Unit, options: ReadOptions) -> Scene:
    """The Scene of one record's bytes (module docstring), tracks drawn with `options`."""
    record = Record(data, unit.name)
    missing = [key for key in REQUIRED if not record.has(key)]
    if missing:
        raise UserError(f"{unit.name} lacks the features {', '.join(missing)}, which MOVi "
                        "records have; is it a MOVi dataset (movi_e, panning_movi_e, movi_f)?")
    rgb = record.frames("video", np.uint8, 3)  # (T,H,W,3)
    num_frames, height, width = rgb.shape[:3]
    size = (height, width)
    segmentation = record.frames("segmentations", np.uint8, 1, size)[..., 0].astype(np.int32)
    distance = record.frames("depth", np.uint16, 1, size)[..., 0]  # (T,H,W) uint16
    if len(segmentation) != num_frames or len(distance) != num_frames:
        raise UserError(f"{unit.name}: video, segmentations and depth differ in frames "
                        f"({num_frames}, {len(segmentation)}, {len(distance)})")
    lo, hi = record.values("metadata/depth_range", 2).astype(np.float64)

    focal = float(record.values("camera/focal_length", 1)[0])  # mm
    sensor = float(record.values("camera/sensor_width", 1)[0])  # mm, spanning the width
    K = geometry.intrinsics_from_lens(focal, sensor, height, width)  # (3,3) float64
    intrinsics = np.repeat(K[None].astype(np.float32), num_frames, axis=0)
    # z = d / |K^-1 [u, v, 1]|, d = v / 65535 (hi - lo) + lo (`decode_range`), in float32
    inverse_ray = 1 / euclidean_range(np.ones((1, height, width), np.float32), K[None])  # (1,H,W)
    depth = decode_range(distance, lo, hi)
    depth *= inverse_ray
    cam_to_world = camera_from_kubric(  # (T,4,4) OpenCV axes
        record.values("camera/positions", num_frames * 3).reshape(-1, 3),
        record.values("camera/quaternions", num_frames * 4).reshape(-1, 4)).astype(np.float32)
    positions = record.values("instances/positions")
    count = len(positions) // (num_frames * 3)
    if count * num_frames * 3 != len(positions):
        raise UserError(f"{unit.name}: instances/positions holds {len(positions)} values, no "
                        f"multiple of {num_frames} frames x 3")
    object_to_world = pose_from_kubric(  # (K,T,4,4)
        positions.reshape(count, num_frames, 3),
        record.values("instances/quaternions", count * num_frames * 4).reshape(count, -1, 4)
    ).astype(np.float32)
    if segmentation.max(initial=0) > count:
        raise UserError(f"{unit.name}: segmentations name object {segmentation.max()}, the "
                        f"record has {count} instances")

    flows = {ours: record.flow(theirs, (num_frames, height, width), sign)
             for ours, theirs, sign in (("flow_fwd", "forward_flow", 1.0),
                                        ("flow_bwd", "backward_flow", -1.0))
             if options.wants(ours) and record.has(theirs)}
    layers = {}
    if options.wants("normal") and record.has("normal"):
        layers["normal"] = decode_range(record.frames("normal", np.uint16, 3, size), -1.0, 1.0)
    if options.wants("object_coordinates") and record.has("object_coordinates"):
        layers["object_coordinates"] = decode_range(
            record.frames("object_coordinates", np.uint16, 3, size), 0.0, 1.0)
    if options.wants("instances"):
        instances = _instances(record, segmentation, count)
        if instances is not None:
            layers["instances"] = instances

    name = record.scalar("metadata/video_name", str(unit.index))
    file_name = RECORD_NAME.match(Path(unit.path).name)
    info = dataset_info(str(Path(unit.path).parent))
    meta = {
        "generator": "kubric", "source_format": KIND,
        "preset": info.get("name") or (file_name["name"] if file_name else "movi"),
        "config": info.get("configName") or Path(unit.path).parent.parent.name,
        "split": file_name["split"] if file_name else None, "scene_index": unit.index,
        "video_name": name, "record": unit.name, "resolution": [height, width],
        "num_frames": num_frames, "fps": 12,
        "mobility_threshold": options.mobility_threshold, "mobility_rule": options.mobility_rule,
        "track_seed": [options.seed, unit.index],
        "flow_fwd_valid": [True] * num_frames, "flow_bwd_valid": [True] * num_frames,
        "camera": {"focal_length": focal, "sensor_width": sensor,
                   "field_of_view": record.scalar("camera/field_of_view")},
        "background": record.scalar("background"),
        "motion_blur": record.scalar("metadata/motion_blur"),
        "depth_range": [lo, hi],
        "layers": {layer: layer in layers for layer in OPTIONAL_LAYERS},
    }
    empty = np.zeros((0, num_frames), bool)
    scene = Scene(
        rgb=rgb, depth=depth, segmentation=segmentation, flow_fwd=flows.get("flow_fwd"),
        flow_bwd=flows.get("flow_bwd"), intrinsics=intrinsics, cam_to_world=cam_to_world,
        object_to_world=object_to_world, objects=_objects(record, count),
        tracks=np.zeros((0, num_frames, 2), np.float32), occluded=empty,
        query_frame=np.zeros(0, np.int32), track_object=np.zeros(0, np.int32),
        tracks_world=None, displacement=None, moving=None,
        normal=layers.get("normal"), object_coordinates=layers.get("object_coordinates"),
        instances=layers.get("instances"), meta=meta)
    if not options.wants("tracks"):  # the caller draws its own (the paper protocol)
        return scene
    drawn = tapvid_kubric_tracks(scene, [options.seed, unit.index], NUM_TRACKS,
                                 _box_lift(record, layers, count, (num_frames,) + size))
    return replace(scene, tracks=drawn.tracks, occluded=drawn.occluded,
                   query_frame=drawn.query_frame, track_object=drawn.track_object,
                   tracks_world=drawn.tracks_world, displacement=drawn.displacement,
                   moving=mobility_labels(drawn, object_to_world, options))


def read_units(unit: Unit, options: ReadOptions) -> Iterator[Scene]:
    """The scene of one record unit (module docstring); a damaged record is a `UserError`."""
    if unit.problem is not None:
        raise UserError(unit.problem)
    yield decode_record(read_record(unit.path, unit.where, unit.name), unit, options)
