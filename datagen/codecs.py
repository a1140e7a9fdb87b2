"""One sample's members and their bytes: which member holds each Scene field, and its codec.

One scene is one webdataset sample (written and read by `datagen.shards`): tar members
`<key>.<field>.<ext>`. The members and their encodings (chosen by measurement, see docs/FORMAT.md
and docs/perf/datagen_io.md):

- `rgb.npy`: uint8 (T,H,W,3), an uncompressed .npy (format 2; format 1 wrote `rgb.png`, the
  frames stacked vertically in one PNG, which is still read).
- `segmentation.png`: (T*H, W) 8-bit PNG (16-bit when an id exceeds 255), decoded to int32.
- every other array: `<field>.npy.bsz`, lossless for any dtype (see `encode_array`): a zlib stream
  (RFC 1950) that any inflate reads, written and read with ISA-L's deflate (`isal`): a scene's
  members encode 5.5x and decode 1.4x faster than with zlib's level 1 (docs/perf/datagen_io.md).
- `normal.u16.npy.bsz`, `object_coordinates.u16.npy.bsz`: float32 (T,H,W,3) quantised to uint16
  as Kubric's PNGs are (`QUANTISED`; error at most half a step), then `.npy.bsz`.
- `instances.npy.bsz`: the dict of per-object arrays as one structured array, one record per
  object (`instance_dtype`); `events.npy.bsz`: the dict of per-event arrays as one record per
  event (`EVENT_DTYPE`); both `.npy.bsz`, lossless.
- `meta.json`, `objects.json`: UTF-8 JSON.
- `checksums.json` (format 3): the CRC-32 of every other member of the sample, checked on read.
A field that is `None` has no member and decodes to `None`.
"""

from __future__ import annotations

import io
import json
from typing import Any

import cv2
import numpy as np
from isal import isal_zlib

from c4d_core.files import json_default
from datagen.scene import EVENT_KEYS, INSTANCE_KEYS

FORMAT_VERSION = 3  # 3: a `checksums.json` member; 2: rgb as raw `rgb.npy` (~50x faster than PNG)
# ISA-L's deflate level (0-3) of `.npy.bsz`: level 1 encodes depth and flow 5-10x faster than
# zlib's level 1, 0-11 % larger per field (1-7 % per scene); its level 3 is 2x slower and no
# smaller (docs/perf/datagen_io.md)
DEFLATE_LEVEL = 1
# What decoding a corrupt member raises (`decode_field`, `decode_array`).
DECODE_ERRORS = (ValueError, TypeError, isal_zlib.error, UnicodeDecodeError)
PNG_LEVEL = 1

# field -> (dtype, ndim) of the contract (docs/FORMAT.md); `objects` and `meta` are JSON.
ARRAY_FIELDS: dict[str, tuple[np.dtype, int]] = {
    "rgb": (np.dtype(np.uint8), 4),
    "depth": (np.dtype(np.float32), 3),
    "segmentation": (np.dtype(np.int32), 3),
    "flow_fwd": (np.dtype(np.float32), 4),
    "flow_bwd": (np.dtype(np.float32), 4),
    "intrinsics": (np.dtype(np.float32), 3),
    "cam_to_world": (np.dtype(np.float32), 3),
    "object_to_world": (np.dtype(np.float32), 4),
    "tracks": (np.dtype(np.float32), 3),
    "occluded": (np.dtype(np.bool_), 2),
    "query_frame": (np.dtype(np.int32), 1),
    "track_object": (np.dtype(np.int32), 1),
    "tracks_world": (np.dtype(np.float32), 3),
    "displacement": (np.dtype(np.float32), 2),
    "moving": (np.dtype(np.bool_), 2),
    "normal": (np.dtype(np.float32), 4),
    "object_coordinates": (np.dtype(np.float32), 4),
}
JSON_FIELDS = ("meta", "objects")
RECORD_FIELDS = ("instances", "events")  # dicts of arrays, stored as structured arrays
# field -> (low, high): stored as uint16 q = round((v - low) / (high - low) * 65535), read back as
# low + q / 65535 * (high - low) in float32 (Kubric's normal and object-coordinate PNGs).
QUANTISED = {"normal": (-1.0, 1.0), "object_coordinates": (0.0, 1.0)}
QUANTUM = 65535
SPECIAL_MEMBERS = {"rgb": "rgb.npy", "segmentation": "segmentation.png",
                   "normal": "normal.u16.npy.bsz", "object_coordinates": "object_coordinates.u16.npy.bsz"}
EVENT_DTYPE = np.dtype([(key, dtype, shape) for key, (dtype, shape) in EVENT_KEYS.items()])
FORMAT_1_RGB = "rgb.png"  # format 1's rgb member, still read
# Fields every datagen scene has (docs/FORMAT.md): a sample without one of them is incomplete.
REQUIRED_FIELDS = ("rgb", "intrinsics", "cam_to_world", "objects", "tracks", "occluded",
                   "query_frame", "track_object", "meta")
CHECKSUMS = "checksums.json"  # {"crc32": {member suffix: 8 hex digits}}, before `meta.json`


def member_suffix(name: str) -> str:
    """The tar member suffix (webdataset extension) that holds field `name`."""
    if name in SPECIAL_MEMBERS:
        return SPECIAL_MEMBERS[name]
    return f"{name}.json" if name in JSON_FIELDS else f"{name}.npy.bsz"


def wrong_layout(name: str, value: Any, shape: tuple[int | None, ...] | None = None) -> str | None:
    """None if `value` is an array of array field `name`'s dtype and rank in `ARRAY_FIELDS` (and
    exactly of `shape`, when given); else what it is instead: 'float64 (4, 3)', or its type's name.
    """
    dtype, ndim = ARRAY_FIELDS[name]
    if not isinstance(value, np.ndarray):
        return type(value).__name__
    if value.dtype != dtype or (value.ndim != ndim if shape is None else value.shape != shape):
        return f"{value.dtype} {value.shape}"
    return None


def encode_field(name: str, value: Any) -> bytes:
    """The bytes of the member `member_suffix(name)` that holds the (not None) Scene field `name`."""
    if name == "rgb":
        return encode_rgb(value)
    if name == "segmentation":
        return encode_segmentation(value)
    if name in JSON_FIELDS:
        return to_json_bytes(value)
    if name in QUANTISED:
        return encode_array(quantise(value, *QUANTISED[name]))
    if name == "instances":
        return encode_array(instance_records(value))
    if name == "events":
        return encode_array(event_records(value))
    return encode_array(value)


def decode_field(name: str, suffix: str, data: bytes, num_frames: int) -> Any:
    """Inverse of `encode_field`: Scene field `name` from its member `suffix` (`member_suffix(name)`,
    or `FORMAT_1_RGB` in format 1 shards) of a scene of `num_frames` frames.

    Raises one of `DECODE_ERRORS` on corrupt bytes.
    """
    if suffix == FORMAT_1_RGB:
        return decode_rgb_png(data, num_frames)
    if name == "rgb":
        return decode_rgb(data, num_frames)
    if name == "segmentation":
        return decode_segmentation(data, num_frames)
    if name in JSON_FIELDS:
        return json.loads(bytes(data).decode("utf-8"))
    if name in QUANTISED:
        return dequantise(decode_array(data), *QUANTISED[name])
    if name in RECORD_FIELDS:  # one array per key of the contract (a missing field: ValueError)
        records = decode_array(data)
        keys = INSTANCE_KEYS if name == "instances" else EVENT_KEYS
        return {key: np.ascontiguousarray(records[key]) for key in keys}
    return decode_array(data)


# --- optional layers ----------------------------------------------------------------------------


def quantise(value: np.ndarray, low: float, high: float) -> np.ndarray:
    """float (...) in [low, high] -> uint16 (...), the nearest of 65536 even steps (clipped)."""
    steps = (np.asarray(value, np.float32) - np.float32(low)) * np.float32(QUANTUM / (high - low))
    return np.clip(np.rint(steps), 0, QUANTUM).astype(np.uint16)


def dequantise(steps: np.ndarray, low: float, high: float) -> np.ndarray:
    """Inverse of `quantise`: float32 (...), within half a step ((high - low) / 131070, plus 2 %
    of float32 rounding) of the value quantised; quantising the result gives the same steps."""
    if steps.dtype != np.uint16:
        raise ValueError(f"a quantised layer must be uint16, got {steps.dtype}")
    return steps.astype(np.float32) * np.float32((high - low) / QUANTUM) + np.float32(low)


def instance_dtype(num_frames: int) -> np.dtype:
    """One object's record of `Scene.instances` over `num_frames` frames: a field per key of
    `INSTANCE_KEYS`, of shape (T, ...) (`is_dynamic`: one value)."""
    return np.dtype([(key, dtype) if shape is None else (key, dtype, (num_frames, *shape))
                     for key, (dtype, shape) in INSTANCE_KEYS.items()])


def instance_records(instances: dict[str, np.ndarray]) -> np.ndarray:
    """`Scene.instances` (K objects) -> a structured (K,) array of `instance_dtype`; ValueError
    if the keys, dtypes or shapes are not the contract's."""
    _require_dict("instances", instances)
    shape = np.shape(instances.get("visible_pixels"))
    num_objects, num_frames = shape if len(shape) == 2 else (0, 0)
    return _records("instances", instances, INSTANCE_KEYS, (num_objects, num_frames),
                    instance_dtype(num_frames))


def event_records(events: dict[str, np.ndarray]) -> np.ndarray:
    """`Scene.events` (E events) -> a structured (E,) array of `EVENT_DTYPE`; ValueError if the
    keys, dtypes or shapes are not the contract's."""
    _require_dict("events", events)
    return _records("events", events, EVENT_KEYS, np.shape(events.get("frame"))[:1] or (0,),
                    EVENT_DTYPE)


def _require_dict(name: str, values: Any) -> None:
    if not isinstance(values, dict):
        raise ValueError(f"{name} must be a dict of arrays, got {type(values).__name__}")


def _records(name: str, values: dict[str, np.ndarray], keys: dict, leading: tuple[int, ...],
             dtype: np.dtype) -> np.ndarray:
    """A dict of arrays -> a structured (leading[0],) array of `dtype`, one field per key of
    `keys` (key -> (dtype, shape after the `leading` axes; None: one value per record))."""
    if set(values) != set(keys):
        raise ValueError(f"{name} must have the keys {list(keys)}, got {list(values)}")
    records = np.zeros(leading[0], dtype)
    for key, (want_dtype, shape) in keys.items():
        want = leading[:1] if shape is None else (*leading, *shape)
        value = values[key]
        if not isinstance(value, np.ndarray) or value.dtype != want_dtype or value.shape != want:
            raise ValueError(f"{name}[{key!r}] must be {want_dtype} {want}, got "
                             f"{getattr(value, 'dtype', type(value).__name__)} {np.shape(value)}")
        records[key] = value
    return records


# --- arrays -------------------------------------------------------------------------------------


def encode_array(array: np.ndarray) -> bytes:
    """Lossless `.npy.bsz`: a zlib stream of `shuffled_npy(array)`."""
    return isal_zlib.compress(shuffled_npy(array), DEFLATE_LEVEL)


def shuffled_npy(array: np.ndarray) -> bytes:
    """What `.npy.bsz` compresses: a .npy v1 header, then the data byte-shuffled.

    Byte shuffling stores byte 0 of every element, then byte 1, ...: the sign/exponent bytes of
    float32 labels then form long, very compressible runs, which deflate of the plain .npy misses.
    """
    array = np.ascontiguousarray(array)
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, np.lib.format.header_data_from_array_1_0(array))
    planes = array.reshape(-1).view(np.uint8).reshape(-1, array.itemsize).T  # (itemsize, n)
    return header.getvalue() + np.ascontiguousarray(planes).tobytes()


def _npy_bytes(data: bytes) -> tuple[tuple[int, ...], np.dtype, np.ndarray]:
    """Shape, dtype and the data bytes (uint8, a view of `data`) of an uncompressed .npy v1."""
    raw = io.BytesIO(data)
    np.lib.format.read_magic(raw)
    shape, fortran_order, dtype = np.lib.format.read_array_header_1_0(raw)
    if fortran_order:
        raise ValueError("Fortran-ordered arrays are not part of the format")
    payload = np.frombuffer(data, np.uint8, offset=raw.tell())
    expected = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    if payload.size != expected:
        raise ValueError(f"array data has {payload.size} bytes, expected {expected}")
    return shape, dtype, payload


def decode_array(data: bytes) -> np.ndarray:
    """Inverse of `encode_array` (and of any zlib stream of the same bytes: shards written before
    ISA-L by zlib's level 1 read the same)."""
    shape, dtype, planes = _npy_bytes(isal_zlib.decompress(data))  # planes: (itemsize * count,)
    count = planes.size // dtype.itemsize
    data_bytes = np.ascontiguousarray(planes.reshape(dtype.itemsize, count).T)  # (count, itemsize)
    return data_bytes.view(dtype).reshape(shape)


def _encode_png(image: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, PNG_LEVEL])
    if not ok:
        raise ValueError(f"PNG encoding failed for an image of shape {image.shape}")
    return buf.tobytes()


def _decode_png(data: bytes) -> np.ndarray:
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError("not a readable PNG image")
    return image


def encode_rgb(rgb: np.ndarray) -> bytes:
    """uint8 (T,H,W,3) RGB -> an uncompressed .npy v1 (the header, then the pixels).

    Uncompressed because training decodes every frame of every clip: PNG costs ~50 ms CPU per
    256x256 x 24 scene, more than a loader worker's whole budget per clip (docs/perf).
    """
    rgb = np.ascontiguousarray(rgb)
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, np.lib.format.header_data_from_array_1_0(rgb))
    return header.getvalue() + rgb.tobytes()


def decode_rgb(data: bytes, num_frames: int) -> np.ndarray:
    """Inverse of `encode_rgb`: uint8 (T,H,W,3) RGB, a writable copy."""
    shape, dtype, pixels = _npy_bytes(data)
    if dtype != np.uint8 or len(shape) != 4 or shape[0] != num_frames or shape[3] != 3:
        raise ValueError(f"rgb array {dtype} {shape} does not hold {num_frames} RGB frames")
    return pixels.reshape(shape).copy()


def decode_rgb_png(data: bytes, num_frames: int) -> np.ndarray:
    """Format 1's `rgb.png` (the frames stacked vertically, (T*H, W, 3)) -> uint8 (T,H,W,3) RGB."""
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR_RGB)
    if image is None or image.shape[0] % num_frames:
        shape = None if image is None else image.shape
        raise ValueError(f"rgb image of shape {shape} does not hold {num_frames} RGB frames")
    return image.reshape(num_frames, -1, *image.shape[1:])


def encode_segmentation(segmentation: np.ndarray) -> bytes:
    """int32 (T,H,W) ids -> one 8-bit PNG (16-bit if an id exceeds 255) of the stacked frames."""
    t, h, w = segmentation.shape
    low, high = int(segmentation.min(initial=0)), int(segmentation.max(initial=0))
    if low < 0 or high > np.iinfo(np.uint16).max:
        raise ValueError(f"segmentation ids must lie in [0, 65535], got [{low}, {high}]")
    dtype = np.uint8 if high <= np.iinfo(np.uint8).max else np.uint16
    return _encode_png(segmentation.reshape(t * h, w).astype(dtype))


def decode_segmentation(data: bytes, num_frames: int) -> np.ndarray:
    """Inverse of `encode_segmentation`: int32 (T,H,W)."""
    image = _decode_png(data)
    if image.ndim != 2 or image.shape[0] % num_frames:
        raise ValueError(f"segmentation image {image.shape} does not hold {num_frames} frames")
    return image.astype(np.int32).reshape(num_frames, -1, image.shape[1])


# --- JSON and checksums -------------------------------------------------------------------------


def to_json_bytes(value: Any) -> bytes:
    """UTF-8 JSON; numpy scalars and arrays become numbers and lists, tuples become lists."""
    return json.dumps(value, default=json_default, ensure_ascii=False).encode("utf-8")


def crc32(data: bytes) -> str:
    """The CRC-32 (zlib's, as in gzip and zip) of `data` as 8 hex digits; ~0.07 ms per MB."""
    return f"{isal_zlib.crc32(data):08x}"
