"""Writers of other projects' Kubric data for the tests, from the formats' published facts alone
(reference kubric_movi.md 2.2, 2.5, 8.2), never from the readers under test: a reader that
reads these back equal to the scene they were made of reads the format, not its own writer.

- `write_tfds_movi(root, scenes, ...)`: a TFDS MOVi dataset folder
  ROOT/NAME/CONFIG/VERSION/{dataset_info.json, features.json, NAME-SPLIT.tfrecord-NNNNN-of-NNNNN}
  of our scenes: TFRecord framing with masked CRC-32C, `tf.train.Example`s serialised by the
  protobuf library itself (the message types built here from tensorflow's example.proto /
  feature.proto field numbers), PNG frames written by a small encoder of the PNG spec here
  (8-bit RGB video, 8-bit grey segmentation, 16-bit grey depth as Euclidean distance over
  metadata/depth_range, 16-bit RGB normal and object coordinates), flows as int64 lists of
  uint16 (drow, dcol) over their ranges, camera and objects as float lists (Blender camera axes,
  (w, x, y, z) quaternions).
- `damage_record(path, record, how)`: spoil one record's bytes as a disk or a download would.

Imported as `tests.foreign_writers`; no module of the project uses it.
"""

from __future__ import annotations

import json
import struct
import zlib
from functools import lru_cache
from pathlib import Path

import crc32c
import numpy as np

from c4d_core import geometry
from datagen.scene import Scene

BLENDER = np.diag([1.0, -1.0, -1.0])  # OpenCV camera axes <-> Blender's (right-multiplied)
FOCAL_MM = 35.0  # Kubric's lens: 35 mm on a 32 mm wide sensor, horizontal fit


# --- bytes of the formats ------------------------------------------------------------------------


def png_bytes(image: np.ndarray) -> bytes:
    """A PNG (spec: signature, IHDR, one zlib IDAT of filter-0 rows, IEND) of uint8 or uint16
    (H,W) grey or (H,W,3) RGB; 16-bit samples big-endian."""
    image = np.asarray(image)
    height, width = image.shape[:2]
    channels = 1 if image.ndim == 2 else image.shape[2]
    depth = 16 if image.dtype == np.uint16 else 8
    samples = image.astype(">u2" if depth == 16 else np.uint8).reshape(height, -1).view(np.uint8)
    rows = np.concatenate([np.zeros((height, 1), np.uint8), samples], axis=1)  # filter 0: none

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))

    colour = {1: 0, 3: 2}[channels]  # grey, truecolour
    header = struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header)
            + chunk(b"IDAT", zlib.compress(rows.tobytes(), 1)) + chunk(b"IEND", b""))


def masked_crc32c(data: bytes) -> int:
    """TensorFlow's record checksum: CRC-32C rotated right by 15 bits plus 0xa282ead8."""
    crc = crc32c.crc32c(data)
    return ((((crc >> 15) | (crc << 17)) & 0xFFFFFFFF) + 0xA282EAD8) & 0xFFFFFFFF


def tfrecord_bytes(records: list[bytes]) -> bytes:
    """TFRecord framing of each record: uint64 length, uint32 masked CRC-32C of the length, the
    data, uint32 masked CRC-32C of the data, little-endian."""
    out = bytearray()
    for data in records:
        length = struct.pack("<Q", len(data))
        out += length + struct.pack("<I", masked_crc32c(length))
        out += data + struct.pack("<I", masked_crc32c(data))
    return bytes(out)


@lru_cache(maxsize=1)
def example_class():
    """`tensorflow.Example` as a protobuf message class, from tensorflow's field numbers:
    Example{Features features=1}, Features{map<string,Feature> feature=1},
    Feature{oneof{BytesList bytes_list=1; FloatList float_list=2; Int64List int64_list=3}},
    BytesList{repeated bytes value=1}, FloatList{repeated float value=1 [packed]},
    Int64List{repeated int64 value=1 [packed]}."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    fd = descriptor_pb2.FieldDescriptorProto
    proto = descriptor_pb2.FileDescriptorProto(name="c4d_tests_example.proto",
                                               package="tensorflow", syntax="proto3")
    for name, kind in (("BytesList", fd.TYPE_BYTES), ("FloatList", fd.TYPE_FLOAT),
                       ("Int64List", fd.TYPE_INT64)):
        proto.message_type.add(name=name).field.add(name="value", number=1, type=kind,
                                                    label=fd.LABEL_REPEATED)
    feature = proto.message_type.add(name="Feature")
    feature.oneof_decl.add(name="kind")
    for number, name in enumerate(("BytesList", "FloatList", "Int64List"), 1):
        feature.field.add(name=f"{name[:-4].lower()}_list", number=number, type=fd.TYPE_MESSAGE,
                          type_name=f".tensorflow.{name}", label=fd.LABEL_OPTIONAL, oneof_index=0)
    features = proto.message_type.add(name="Features")
    entry = features.nested_type.add(name="FeatureEntry")
    entry.options.map_entry = True
    entry.field.add(name="key", number=1, type=fd.TYPE_STRING, label=fd.LABEL_OPTIONAL)
    entry.field.add(name="value", number=2, type=fd.TYPE_MESSAGE,
                    type_name=".tensorflow.Feature", label=fd.LABEL_OPTIONAL)
    features.field.add(name="feature", number=1, type=fd.TYPE_MESSAGE, label=fd.LABEL_REPEATED,
                       type_name=".tensorflow.Features.FeatureEntry")
    proto.message_type.add(name="Example").field.add(
        name="features", number=1, type=fd.TYPE_MESSAGE, type_name=".tensorflow.Features",
        label=fd.LABEL_OPTIONAL)
    pool = descriptor_pool.DescriptorPool()
    pool.Add(proto)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName("tensorflow.Example"))


def example_bytes(features: dict) -> bytes:
    """A serialised tf.train.Example: list of bytes -> bytes_list, float array -> float_list,
    integer array -> int64_list."""
    example = example_class()()
    for key, values in features.items():
        feature = example.features.feature[key]
        if isinstance(values, list):
            feature.bytes_list.value.extend(values)
        elif np.asarray(values).dtype.kind == "f":
            feature.float_list.value.extend(np.asarray(values, np.float32).ravel().tolist())
        else:
            feature.int64_list.value.extend(np.asarray(values, np.int64).ravel().tolist())
    return example.SerializeToString()


# --- a MOVi record of one of our scenes --------------------------------------------------------


def quantise(values: np.ndarray, low: float, high: float, rounding: bool) -> np.ndarray:
    """uint16 of (values - low) / (high - low) * 65535, rounded (depth) or truncated (the PNG
    layers and flows, as Kubric's worker writes them)."""
    scaled = (np.asarray(values, np.float64) - low) / (high - low) * 65535
    return (np.round(scaled) if rounding else scaled).astype(np.uint16)


def euclidean_distance(depth: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
    """(T,H,W) distance from the camera centre of z-depth (T,H,W): z |K^-1 [u, v, 1]|."""
    t, h, w = depth.shape
    pixels = np.concatenate([geometry.pixel_grid(h, w), np.ones((h, w, 1))], axis=-1)
    rays = pixels @ np.linalg.inv(intrinsics[0].astype(np.float64)).T  # (H,W,3)
    return depth * np.linalg.norm(rays, axis=-1)


def lens_of(scene: Scene) -> tuple[float, float]:
    """(focal_length, sensor_width) in mm of the scene's camera, which must be Kubric's kind: a
    horizontal-fit lens (fx = f / sensor * W) with square pixels, centred, the same every frame."""
    h, w = scene.image_size
    k = scene.intrinsics.astype(np.float64)
    sensor = FOCAL_MM * w / k[0, 0, 0]
    expected = geometry.intrinsics_from_lens(FOCAL_MM, sensor, h, w)
    assert np.allclose(k, expected[None], atol=1e-4), "no Kubric camera: square pixels, centred"
    return FOCAL_MM, sensor


def movi_features(scene: Scene, omit: tuple[str, ...] = ()) -> dict:
    """The features of a MOVi record (movi_e.py's, flattened by TFDS) of `scene`, instances in
    our object order; `omit` leaves features out."""
    t, h, w = scene.rgb.shape[:3]
    k = len(scene.objects)
    focal, sensor = lens_of(scene)
    camera = scene.cam_to_world.astype(np.float64)
    camera_rotation = camera[:, :3, :3] @ BLENDER
    distance = euclidean_distance(scene.depth.astype(np.float64), scene.intrinsics)
    d_lo, d_hi = float(distance.min()), float(distance.max())
    poses = scene.object_to_world.astype(np.float64)  # (K,T,4,4)
    features = {
        "video": [png_bytes(frame) for frame in scene.rgb],
        "segmentations": [png_bytes(frame.astype(np.uint8)) for frame in scene.segmentation],
        "depth": [png_bytes(frame) for frame in quantise(distance, d_lo, d_hi, rounding=True)],
        "metadata/depth_range": np.array([d_lo, d_hi], np.float32),
        "metadata/video_name": [str(scene.meta.get("scene_index", 0)).encode()],
        "metadata/width": np.array([w]), "metadata/height": np.array([h]),
        "metadata/num_frames": np.array([t]), "metadata/num_instances": np.array([k]),
        "background": [b"test_hdri"],
        "camera/focal_length": np.array([focal], np.float32),
        "camera/sensor_width": np.array([sensor], np.float32),
        "camera/field_of_view": np.array([2 * np.arctan(sensor / (2 * focal))], np.float32),
        "camera/positions": camera[:, :3, 3].astype(np.float32),
        "camera/quaternions": geometry.matrix_to_quat(camera_rotation).astype(np.float32),
        "instances/positions": poses[..., :3, 3].astype(np.float32),
        "instances/quaternions": geometry.matrix_to_quat(poses[..., :3, :3]).astype(np.float32),
        **instance_features(scene),
        "instances/visibility": np.stack([(scene.segmentation == i + 1).sum(axis=(1, 2))
                                          for i in range(k)]).reshape(k, t),
        "instances/asset_id": [str(o.get("asset_id", i)).encode() for i, o in enumerate(scene.objects)],
        "instances/category": np.arange(k) % 17,
        "instances/scale": np.array([o.get("scale", 1.0) for o in scene.objects], np.float32),
        "instances/mass": np.array([o.get("mass", 1.0) for o in scene.objects], np.float32),
        "instances/friction": np.full(k, 0.5, np.float32),
        "instances/restitution": np.full(k, 0.5, np.float32),
        "instances/is_dynamic": np.array([bool(o.get("tossed")) for o in scene.objects], np.int64),
        "instances/bbox_frames/ragged_flat_values": np.zeros(0, np.int64),
        "instances/bbox_frames/ragged_row_lengths_0": np.zeros(k, np.int64),
        "instances/bboxes/ragged_flat_values": np.zeros(0, np.float32),
        "instances/bboxes/ragged_row_lengths_0": np.zeros(k, np.int64),
        "events/collisions/instances": np.zeros(0, np.int64),
        "events/collisions/frame": np.zeros(0, np.int64),
        "events/collisions/force": np.zeros(0, np.float32),
        "events/collisions/position": np.zeros(0, np.float32),
        "events/collisions/image_position": np.zeros(0, np.float32),
        "events/collisions/contact_normal": np.zeros(0, np.float32),
    }
    # flows: Kubric's (drow, dcol); backward is the motion from t-1 to t (minus ours)
    for theirs, flow in (("forward_flow", scene.flow_fwd[..., ::-1]),
                         ("backward_flow", -scene.flow_bwd[..., ::-1])):
        low, high = float(flow.min()), float(flow.max())
        high = high if high > low else low + 1.0
        features[theirs] = quantise(flow, low, high, rounding=False)
        features[f"metadata/{theirs}_range"] = np.array([low, high], np.float32)
    if scene.normal is not None:
        features["normal"] = [png_bytes(f) for f in quantise((scene.normal + 1) / 2, 0, 1, False)]
    if scene.object_coordinates is not None:
        features["object_coordinates"] = [png_bytes(f) for f in quantise(
            np.clip(scene.object_coordinates, 0, 1), 0, 1, False)]
    return {key: value for key, value in features.items() if key not in omit}


def instance_features(scene: Scene) -> dict[str, np.ndarray]:
    """The per-frame `instances/*` features of MOVi: the scene's where it has `instances`, zeros
    where not (K,T,...); image positions as Kubric stores them, (x, y) normalised by the image's
    width and height with pixel edges at integers."""
    k, t = len(scene.objects), scene.num_frames
    h, w = scene.image_size
    inst = scene.instances
    if inst is None:
        return {"instances/velocities": np.zeros((k, t, 3), np.float32),
                "instances/angular_velocities": np.zeros((k, t, 3), np.float32),
                "instances/bboxes_3d": np.zeros((k, t, 8, 3), np.float32),
                "instances/image_positions": np.zeros((k, t, 2), np.float32)}
    return {"instances/velocities": inst["velocity"],
            "instances/angular_velocities": inst["angular_velocity"],
            "instances/bboxes_3d": inst["bbox_3d"],
            "instances/image_positions": ((inst["image_position"] + 0.5) / [w, h]).astype(np.float32)}


def write_tfds_movi(root: Path, scenes: list[Scene], name: str = "movi_e", config: str | None = None,
                    split: str = "validation", num_files: int = 2, version: str = "1.0.0",
                    omit: tuple[str, ...] = ()) -> Path:
    """Write `scenes` as split `split` of a TFDS MOVi dataset under `root` (module docstring),
    spread over `num_files` record files in order; returns the version folder. Other splits
    already in the folder stay listed in its dataset_info.json."""
    h, w = scenes[0].image_size
    folder = Path(root) / name / (config or f"{h}x{w}") / version
    folder.mkdir(parents=True, exist_ok=True)
    chunks = np.array_split(np.arange(len(scenes)), num_files)
    lengths, total = [], 0
    for i, chunk in enumerate(chunks):
        data = tfrecord_bytes([example_bytes(movi_features(scenes[j], omit)) for j in chunk])
        (folder / f"{name}-{split}.tfrecord-{i:05d}-of-{num_files:05d}").write_bytes(data)
        lengths.append(str(len(chunk)))
        total += len(data)
    info_path = folder / "dataset_info.json"
    info = json.loads(info_path.read_text()) if info_path.exists() else {
        "name": name, "version": version, "configName": config or f"{h}x{w}",
        "fileFormat": "tfrecord", "splits": []}
    info["splits"] = [s for s in info["splits"] if s["name"] != split] + [
        {"name": split, "shardLengths": lengths, "numBytes": str(total),
         "filepathTemplate": "{DATASET}-{SPLIT}.{FILEFORMAT}-{SHARD_X_OF_Y}"}]
    info_path.write_text(json.dumps(info, indent=2))
    names = sorted(movi_features(scenes[0], omit))
    (folder / "features.json").write_text(json.dumps({
        "pythonClassName": "tensorflow_datasets.core.features.features_dict.FeaturesDict",
        "featuresDict": {"features": {key: {} for key in names}}}, indent=2))
    return folder


def damage_record(path: Path, record: int, how: str) -> None:
    """Spoil record `record` of a TFRecord file: "data" flips a byte of its data (its data
    checksum fails), "length" a byte of its length (its header checksum fails), "cut" cuts the
    file inside it."""
    raw = bytearray(Path(path).read_bytes())
    offset = 0
    for _ in range(record):
        offset += 16 + struct.unpack_from("<Q", raw, offset)[0]
    length = struct.unpack_from("<Q", raw, offset)[0]
    if how == "data":
        raw[offset + 12 + length // 2] ^= 0xFF
    elif how == "length":
        raw[offset] ^= 0x01
    elif how == "cut":
        del raw[offset + 12 + length // 2:]
    else:
        raise ValueError(how)
    Path(path).write_bytes(bytes(raw))
