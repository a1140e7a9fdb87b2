"""Folders in Kubric's worker layout read as `Scene`s: what Kubric's MOVi worker
(`challenges/movi/movi_def_worker.py`) writes per scene, and what `c4d export kubric` writes.

A source is one scene folder, a folder of them (Kubric's job folder), or the OUT of `c4d export
kubric`, whose scene folders are in OUT/scenes/ (`scene_root`). A unit is one scene folder
(reference kubric_movi.md 2.1-2.5; docs/FORMAT.md "Reading Kubric's data"), frames i = 0..T-1
(T = `metadata.num_frames`), H x W pixels:

- `rgba_{i:05d}.png` 8-bit RGBA; `depth_{i:05d}.tiff` float32 Euclidean distance from the camera
  centre; `segmentation_{i:05d}.png` 8-bit palette indices; `forward_flow_`, `backward_flow_`,
  `normal_`, `object_coordinates_{i:05d}.png` 16-bit RGB;
- `metadata.json` (`metadata`, `camera`, `instances`), `data_ranges.json` (flow ranges) and
  `events.json` (`collisions`).

Every file is required, as Kubric's own TFDS builder requires them (`is_complete_dir`). Decoded
into our conventions (docs/FORMAT.md "Conventions"), K objects = Kubric's instances, in its order
(the objects visible in some frame, most visible pixels first):

- rgb (T,H,W,3) uint8: rgba's colour channels;
- depth (T,H,W) float32 z-depth: range d / |K^-1 [u, v, 1]| at each pixel centre (u, v), the
  inverse of the export's `euclidean_range`;
- segmentation (T,H,W) int32: the palette indices, 0 background, k = instance k-1;
- flow_fwd, flow_bwd (T,H,W,2) float32 (dx, dy) pixels: v / 65535 (max - min) + min with
  `data_ranges.json`'s min/max gives Kubric's (drow, dcol); forward is ours with the axes swapped,
  backward is Kubric's motion from t-1 to t, so ours (t to t-1) is minus it. Kubric renders a
  frame beyond each end, so every frame's flow is valid (`meta["flow_*_valid"]` all True, as
  the TFDS reader says; `c4d export kubric` stores our invalid ends as zero flow);
- normal (T,H,W,3) world unit normals v / 65535 x 2 - 1; object_coordinates v / 65535;
- intrinsics (T,3,3): `camera.K`, Kubric's normalised matrix with Blender's signs
  [[fx/W, 0, -(cx+0.5)/W], [0, -fy/H, -(cy+0.5)/H], [0, 0, -1]], in pixels (raster principal
  point minus 0.5: our pixel centres); Kubric's lens is fixed in a scene;
- cam_to_world (T,4,4): `camera.positions` and `camera.quaternions` (w,x,y,z) are Blender's
  camera axes (x right, y up, looking along -z): times diag(1, -1, -1) gives OpenCV's;
- object_to_world (K,T,4,4): `instances[k].positions` and `.quaternions` (w,x,y,z);
- objects: each instance's per-object values (asset_id, scale, mass, ...; `tossed` =
  `is_dynamic` where the folder does not record it); instances and events: Kubric's records in
  `INSTANCE_KEYS` / `EVENT_KEYS` form (pixels from its normalised raster coordinates, event frames
  counted from 0, not Kubric's 1);
- MOVi-F's older worker (`movi_f.py`'s conventions, reference kubric_movi.md 1.8: its metadata has
  `height` and `width`, and `c4d export kubric` marks such folders `flags.tfds_builder =
  "movi_f.py"`) stored the flow ranges in units of a 512-pixel frame: they are multiplied by 512,
  as movi_f.py does. Its `scale` is relative to the raw GSO mesh; only for our own exports is it
  turned back into units (times the stand-in's scale_factor), since the GSO table is not here;
- `c4d export kubric` names each object by a GSO stand-in for Kubric's builders and keeps ours as
  `c4d_asset_id` (datagen/export/kubric.py `STAND_INS`): `asset_id` is ours again there, the
  stand-in's kept as `gso_asset_id`;
- tracks: drawn by TAP-Vid-Kubric's recipe (`datagen.annotate.tapvid_kubric_tracks`, 256 tracks)
  from these layers, seeded by [options.seed, unit.index], with world positions and displacement
  from the object poses; `moving` by `options.mobility_rule` and `.mobility_threshold`
  (`datagen.foreign.ReadOptions`: a track's world displacement since the previous frame, or its
  object's position change, > 0.01 units by default).

The reader interface is `datagen.foreign`'s (KIND, EXPECTED, detect, units, read_units).
`options.fields` without the flows, normal, object_coordinates, instances or events skips
decoding them (they are left None); the other layers are always read, as the tracks need them.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any, Callable, Iterator

import cv2
import numpy as np
from PIL import Image, UnidentifiedImageError

from c4d_core.errors import UserError
from c4d_core.geometry import make_pose, quat_to_matrix
from c4d_core.ownership import read_marker
from datagen.annotate import tapvid_kubric_tracks
from datagen.export.kubric import (BLENDER_AXES, LENS, MOVI_F_FLOW_UNIT, SHAPE, STAND_INS,
                                   euclidean_range)
from datagen.export.kubric import FORMAT as EXPORT
from datagen.export.base import PARTIAL
from datagen.foreign import ReadOptions, Unit, mobility_labels
from datagen.scene import EVENT_KEYS, INSTANCE_KEYS, OPTIONAL_LAYERS, Scene

KIND = "kubric-worker"
EXPECTED = ("Kubric worker scene folders: a folder of scene folders (or one) holding "
            "rgba_00000.png, depth_00000.tiff, segmentation_, forward_flow_, backward_flow_, "
            "normal_, object_coordinates_ frames and metadata.json, data_ranges.json, events.json")
NUM_TRACKS = 256  # TAP-Vid-Kubric's tracks per video
# Per-frame files: layer -> file suffix (reference kubric_movi.md 2.1)
FRAME_LAYERS = {"rgba": "png", "depth": "tiff", "segmentation": "png", "forward_flow": "png",
                "backward_flow": "png", "normal": "png", "object_coordinates": "png"}
# Kubric's per-frame instance records; the other keys of an instance describe the object
PER_FRAME_KEYS = frozenset({"positions", "quaternions", "velocities", "angular_velocities",
                            "bboxes_3d", "image_positions", "bboxes", "bbox_frames",
                            "visibility"})
UINT16_MAX = 65535
SKIPPABLE = ("flow_fwd", "flow_bwd", "normal", "object_coordinates", "instances", "events")


# --- the layout -----------------------------------------------------------------------------------


def is_scene_folder(path: Path) -> bool:
    """Whether `path` looks like one scene of Kubric's worker (its metadata and first frame)."""
    return (path / "metadata.json").is_file() and (path / "rgba_00000.png").is_file()


def _sub_folders(path: Path) -> list[Path]:
    """The sub-folders of `path` sorted by name, an export's `NAME.partial` (a scene still being
    written) left out."""
    return sorted(p for p in path.iterdir() if p.is_dir() and not p.name.endswith(PARTIAL))


def detect_folders(path: Path, is_unit: Callable[[Path], bool]) -> bool:
    """Whether `path` is a unit folder (`is_unit`) or a folder whose first sub-folders (in name
    order) include one; never raises. Shared by the folder kinds (this one, cotracker-kubric)."""
    try:
        path = Path(path)
        return path.is_dir() and (is_unit(path) or any(map(is_unit, _sub_folders(path)[:8])))
    except OSError:
        return False


def folder_units(path, split: str | None, kind: str, is_unit: Callable[[Path], bool],
                 expected: str) -> list[Unit]:
    """One `Unit` of `kind` per unit folder of `path`: `path` itself where it is one (`is_unit`),
    else its unit sub-folders sorted by name. Such folders hold no split: `split` picks the
    sub-folder of that name where there is one (OUT/train/, OUT/val/); None takes `path` as it
    is. A UserError names what was expected (`expected`) where `path` holds no unit."""
    path = Path(path)
    if split is not None:
        if not (path / split).is_dir():
            raise UserError(f"{path} has no sub-folder {split!r}: {kind} folders are not split; "
                            "give the folder of that split's scenes, without a split")
        path = path / split
    folders = ([path] if is_unit(path) else [p for p in _sub_folders(path) if is_unit(p)]) \
        if path.is_dir() else []
    if not folders:
        raise UserError(f"{path} holds no {kind} scene; expected {expected}")
    return [Unit(kind, str(folder), index, str(folder)) for index, folder in enumerate(folders)]


def scene_root(path: Path) -> Path:
    """The folder of scene folders that `path` stands for: its `scenes/` where `path` is the OUT
    of `c4d export kubric` (marked as that command's output, `c4d_core.ownership`), else `path`
    itself (a scene folder, a folder of them: Kubric's job folder, an export's OUT/scenes/)."""
    path = Path(path)
    return EXPORT.scene_root(path) if read_marker(path) == f"export-{EXPORT.name}" else path


def detect(path: Path) -> bool:
    """Whether `path` is a scene folder in Kubric's worker layout, a folder of them, or a `c4d
    export kubric` OUT (`scene_root`)."""
    return detect_folders(scene_root(path), is_scene_folder)


def units(path, split: str | None = None) -> list[Unit]:
    """One `Unit` per scene folder of `path` (`scene_root`, `folder_units`), the pieces loader
    workers share."""
    return folder_units(scene_root(path), split, KIND, is_scene_folder, EXPECTED)


def read_units(unit: Unit, options: ReadOptions = ReadOptions()) -> Iterator[Scene]:
    """The scene of one scene-folder unit (`read_scene`)."""
    yield read_scene(Path(unit.path), unit.index, options)


# --- decoding -------------------------------------------------------------------------------------


def _missing(folder: Path, name: str) -> UserError:
    return UserError(f"{folder} is not a complete Kubric worker scene: {name} is missing (expected "
                     f"{EXPECTED}); copy or render the scene again")


def _read_json(folder: Path, name: str) -> dict[str, Any]:
    path = folder / name
    try:
        value = json.loads(path.read_bytes())
    except FileNotFoundError:
        raise _missing(folder, name) from None
    except (OSError, ValueError) as exc:  # ValueError: bad JSON or UTF-8
        raise UserError(f"cannot read {path} as JSON ({exc}); copy or render the scene again") \
            from exc
    if not isinstance(value, dict):
        raise UserError(f"{path} holds a JSON {type(value).__name__}, not Kubric's record (an "
                        "object); copy or render the scene again")
    return value


def _field(record: dict, path: Path, *keys: str, where: str = "") -> Any:
    """record[keys[0]][keys[1]]...; a UserError naming the file `path` and the key (after `where`,
    e.g. "instances[2].") where one is missing."""
    value = record
    for i, key in enumerate(keys):
        if not isinstance(value, dict) or key not in value:
            raise UserError(f"{path} has no {where}{'.'.join(keys[:i + 1])}, which Kubric's worker "
                            "writes; copy or render the scene again")
        value = value[key]
    return value


def _read_image(path: Path, palette: bool = False) -> np.ndarray:
    """One frame file as stored: (H,W) or (H,W,C) in RGB(A) channel order, uint8/uint16/float32;
    `palette`: an 8-bit palette PNG's indices (H,W) (OpenCV would turn them into colours)."""
    try:
        if palette:
            with Image.open(path) as image:
                if image.mode not in ("P", "L"):
                    raise UserError(f"{path} is a {image.mode} image, not Kubric's 8-bit palette "
                                    "segmentation; copy or render the scene again")
                return np.array(image)
        data = np.frombuffer(path.read_bytes(), np.uint8)
    except FileNotFoundError:
        raise _missing(path.parent, path.name) from None
    except (OSError, UnidentifiedImageError, ValueError) as exc:
        raise UserError(f"cannot decode {path} (corrupt or not an image: {exc}); copy or render "
                        "the scene again") from exc
    image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if image is None:
        raise UserError(f"cannot decode {path} (corrupt or not an image); copy or render the "
                        "scene again")
    return image[..., [2, 1, 0, 3][:image.shape[-1]]] if image.ndim == 3 else image


def _frames(folder: Path, layer: str, num_frames: int, channels: int | None,
            dtype: type) -> np.ndarray:
    """The T frames of `layer` stacked, (T,H,W) or (T,H,W,channels), checked to be `dtype` and of
    one size."""
    frames = []
    for t in range(num_frames):
        path = folder / f"{layer}_{t:05d}.{FRAME_LAYERS[layer]}"
        image = _read_image(path, palette=layer == "segmentation")
        if image.ndim == 3 and channels is None and image.shape[-1] == 1:
            image = image[..., 0]  # a (H,W,1) depth TIFF
        shape = image.shape[:2] + (() if channels is None else (channels,))
        if image.dtype != dtype or image.shape != shape or (frames and shape != frames[0].shape):
            want = "(H,W)" if channels is None else f"(H,W,{channels})"
            raise UserError(f"{path} is {image.dtype} {image.shape}, expected Kubric's "
                            f"{np.dtype(dtype)} {want} frames of one size; copy or render the "
                            "scene again")
        frames.append(image)
    return np.stack(frames)


def decode_range(values: np.ndarray, low: float, high: float, sign: float = 1.0) -> np.ndarray:
    """Kubric's 16-bit scaled layers (flows, normals, object coordinates, TFDS depth): float32
    sign x (v / 65535 (high - low) + low) of the codes `values` (any shape, unsigned ints), as
    Kubric's TFDS decodes them; the inverse of the export's `encode_flow`, within one step of the
    stored value. One float32 multiply-add (within 1e-7 relative of float64), no float64 copy;
    the one decoder of these layers, for worker folders and TFDS records (`tfds_movi`) alike."""
    scale, offset = np.float32(sign * (high - low) / UINT16_MAX), np.float32(sign * low)
    decoded = np.multiply(values, scale, dtype=np.float32, casting="unsafe")
    decoded += offset
    return decoded


def intrinsics_from_kubric(k_normalised: np.ndarray, height: int, width: int) -> np.ndarray:
    """Our K in pixels (3,3) of Kubric's `camera.K` (normalised, Blender's signs: the inverse of
    the export's `normalised_intrinsics`)."""
    k = np.asarray(k_normalised, np.float64)
    return np.array([[k[0, 0] * width, 0.0, -k[0, 2] * width - 0.5],
                     [0.0, -k[1, 1] * height, -k[1, 2] * height - 0.5],
                     [0.0, 0.0, 1.0]])


def pixels_from_kubric(positions: np.ndarray, height: int, width: int) -> np.ndarray:
    """Our pixel (x, y) (...,2), pixel centres at integers, of Kubric's image positions (...,2):
    (x, y) normalised by the image's width and height, pixel edges at integers."""
    return np.asarray(positions) * [width, height] - 0.5


def pose_from_kubric(positions: np.ndarray, quaternions: np.ndarray) -> np.ndarray:
    """(...,4,4) float64 poses of Kubric's positions (...,3) and (w,x,y,z) quaternions (...,4)."""
    return make_pose(quat_to_matrix(np.asarray(quaternions, np.float64)), positions)


def camera_from_kubric(positions: np.ndarray, quaternions: np.ndarray) -> np.ndarray:
    """OpenCV cam_to_world (T,4,4) of Kubric's camera positions and quaternions (Blender axes)."""
    pose = pose_from_kubric(positions, quaternions)
    pose[..., :3, :3] = pose[..., :3, :3] @ BLENDER_AXES  # diag(1,-1,-1) is its own inverse
    return pose


def _array(record: dict, path: Path, shape: tuple[int, ...], *keys: str,
           where: str = "") -> np.ndarray:
    """record[keys...] as a float64 array of `shape` (an empty list fits any shape of size 0); a
    UserError naming the file and the key (after `where`) if it is not one."""
    try:
        value = np.asarray(_field(record, path, *keys, where=where), np.float64)
    except (TypeError, ValueError):
        value = None
    if value is not None and value.size == 0 and np.prod(shape) == 0:
        value = value.reshape(shape)
    if value is None or value.shape != shape:
        got = "not numbers" if value is None else f"of shape {value.shape}"
        raise UserError(f"{path}'s {where}{'.'.join(keys)} is {got}, expected {shape}; copy or "
                        "render the scene again")
    return value


def _object(inst: dict, movi_f: bool) -> dict[str, Any]:
    """One object's record (our `objects` entry) of a Kubric instance: its per-object values, with
    our asset id and scale back where `c4d export kubric` wrote a GSO stand-in (module
    docstring)."""
    obj = {key: value for key, value in inst.items() if key not in PER_FRAME_KEYS}
    obj.setdefault("tossed", bool(inst.get("is_dynamic", False)))
    if "c4d_asset_id" in obj:
        obj["gso_asset_id"], obj["asset_id"] = obj["asset_id"], obj.pop("c4d_asset_id")
        if movi_f and "scale" in obj:
            obj["scale"] = obj["scale"] * STAND_INS.get(obj["asset_id"], SHAPE).scale_factor
    return obj


def _instances(instances: list[dict], path: Path, num_frames: int, height: int, width: int,
               movi_f: bool) -> tuple[np.ndarray, list[dict], dict[str, np.ndarray]]:
    """object_to_world (K,T,4,4), objects (K dicts) and `Scene.instances` (INSTANCE_KEYS) of
    metadata.json's `instances` (K entries, Kubric's order); `movi_f`: movi_f.py's conventions."""
    t = num_frames
    poses, objects = [], []
    values = {key: [] for key in INSTANCE_KEYS}
    for k, inst in enumerate(instances):
        where = f"instances[{k}]."
        if not isinstance(inst, dict):
            raise UserError(f"{path}'s {where[:-1]} is no record; copy or render the scene again")

        def array(key, shape):
            return _array(inst, path, shape, key, where=where)

        poses.append(pose_from_kubric(array("positions", (t, 3)), array("quaternions", (t, 4))))
        objects.append(_object(inst, movi_f))
        frames = array("bbox_frames", (len(inst.get("bbox_frames", ())),)).astype(np.int64)
        if frames.size and (frames.min() < 0 or frames.max() >= t):
            raise UserError(f"{path}'s instances[{k}].bbox_frames lie outside frames 0..{t - 1}; "
                            "copy or render the scene again")
        box = np.full((t, 4), np.nan)  # [ymin, xmin, ymax, xmax] / (H, W, H, W); NaN: not seen
        box[frames] = array("bboxes", (len(frames), 4))
        values["bbox_3d"].append(array("bboxes_3d", (t, 8, 3)))
        values["bbox_2d"].append(box)
        values["visible_pixels"].append(array("visibility", (t,)))
        values["image_position"].append(pixels_from_kubric(array("image_positions", (t, 2)),
                                                           height, width))
        values["velocity"].append(array("velocities", (t, 3)))
        values["angular_velocity"].append(array("angular_velocities", (t, 3)))
        values["is_dynamic"].append(bool(_field(inst, path, "is_dynamic", where=where)))
    num_objects = len(instances)
    arrays = {}
    for key, (dtype, tail) in INSTANCE_KEYS.items():  # (K,) per object, else (K,T,...)
        shape = (num_objects,) if tail is None else (num_objects, t, *tail)
        arrays[key] = np.asarray(values[key], dtype).reshape(shape)
    object_to_world = np.asarray(poses, np.float32).reshape(num_objects, t, 4, 4)
    return object_to_world, objects, arrays


def _events(collisions: list[dict], path: Path, height: int, width: int) -> dict[str, np.ndarray]:
    """`Scene.events` (EVENT_KEYS, (E,...) each) of events.json's `collisions`: instances as
    Kubric's instance indices (-1 the floor), frames from 0, image positions in pixels."""
    tails = {key: shape for key, (_, shape) in EVENT_KEYS.items()}
    values = {key: [] for key in EVENT_KEYS}
    if not isinstance(collisions, list):
        raise UserError(f"{path}'s collisions are no list; copy or render the scene again")
    for e, event in enumerate(collisions):
        for key in EVENT_KEYS:
            values[key].append(_array(event, path, tails[key], key, where=f"collisions[{e}]."))
    if collisions:
        values["frame"] = [frame - 1.0 for frame in values["frame"]]  # Kubric's frame 1 is our 0
        values["image_position"] = [p * [width, height] - 0.5 for p in values["image_position"]]
    return {key: np.asarray(values[key], dtype).reshape((len(collisions),) + tails[key])
            for key, (dtype, _) in EVENT_KEYS.items()}


def read_scene(folder: str | Path, index: int = 0, options: ReadOptions = ReadOptions()) -> Scene:
    """The `Scene` of one Kubric worker scene folder (module docstring), `index` its place in
    its source's reading order (with `options.seed`, the seed of its tracks)."""
    folder = Path(folder)
    meta_path = folder / "metadata.json"
    meta_json, ranges = _read_json(folder, "metadata.json"), _read_json(folder, "data_ranges.json")
    if not (folder / "events.json").is_file():  # read below only where events are wanted
        raise _missing(folder, "events.json")
    num_frames = int(_array(meta_json, meta_path, (), "metadata", "num_frames"))
    rgba = _frames(folder, "rgba", num_frames, 4, np.uint8)
    t, height, width = rgba.shape[:3]

    def layer(name, channels, dtype):
        frames = _frames(folder, name, num_frames, channels, dtype)
        if frames.shape[1:3] != (height, width):
            raise UserError(f"{folder}'s {name} frames are {frames.shape[2]}x{frames.shape[1]} "
                            f"pixels, its rgba frames {width}x{height}; copy or render the scene "
                            "again")
        return frames

    instances = _field(meta_json, meta_path, "instances")
    segmentation = layer("segmentation", None, np.uint8).astype(np.int32)
    listed = len(instances) if isinstance(instances, list) else 0
    if not isinstance(instances, list) or segmentation.max() > listed:
        raise UserError(f"{folder}'s segmentation shows instance {segmentation.max()}, but "
                        f"{meta_path} lists {listed} instances; copy or render the scene again")
    camera = _field(meta_json, meta_path, "camera")
    intrinsics = intrinsics_from_kubric(_array(meta_json, meta_path, (3, 3), "camera", "K"),
                                        height, width)
    intrinsics = np.broadcast_to(intrinsics, (t, 3, 3)).astype(np.float32)
    cam_to_world = camera_from_kubric(_array(meta_json, meta_path, (t, 3), "camera", "positions"),
                                      _array(meta_json, meta_path, (t, 4), "camera", "quaternions"))
    ray_length = euclidean_range(np.ones((1, height, width)), intrinsics[:1])  # (1,H,W): one lens
    depth = layer("depth", None, np.float32) / ray_length  # Euclidean range -> z-depth
    info = meta_json.get("metadata") if isinstance(meta_json.get("metadata"), dict) else {}
    flags = meta_json.get("flags") if isinstance(meta_json.get("flags"), dict) else {}
    movi_f = flags.get("tfds_builder") == "movi_f.py" or "height" in info  # module docstring
    object_to_world, objects, instance_arrays = _instances(instances, meta_path, t, height, width,
                                                           movi_f)
    decoded: dict[str, Any] = {}  # the layers the caller wants (options.fields)
    flows = (("flow_fwd", "forward_flow", 1.0), ("flow_bwd", "backward_flow", -1.0))
    for ours, theirs, sign in flows:
        if options.wants(ours):
            low, high = (float(_array(ranges, folder / "data_ranges.json", (), theirs, end))
                         * (MOVI_F_FLOW_UNIT if movi_f else 1.0) for end in ("min", "max"))
            # channels (dcol, drow) = (dx, dy), (T,H,W,2)
            decoded[ours] = decode_range(layer(theirs, 3, np.uint16)[..., 1::-1], low, high, sign)
    if options.wants("normal"):
        decoded["normal"] = decode_range(layer("normal", 3, np.uint16), -1.0, 1.0)
    if options.wants("object_coordinates"):
        decoded["object_coordinates"] = decode_range(layer("object_coordinates", 3, np.uint16),
                                                     0.0, 1.0)
    if options.wants("instances"):
        decoded["instances"] = instance_arrays
    if options.wants("events"):
        events_path = folder / "events.json"
        decoded["events"] = _events(_field(_read_json(folder, "events.json"), events_path,
                                           "collisions"), events_path, height, width)

    meta = {
        "generator": "kubric", "source_format": KIND, "preset": flags.get("preset") or "kubric",
        "split": flags.get("split"), "scene_index": index, "video_name": folder.name,
        "folder": str(folder), "seed": info.get("seed"), "fps": info.get("frame_rate"),
        "resolution": [height, width], "num_frames": t, "motion_blur": info.get("motion_blur"),
        "background": info.get("background"),
        "mobility_threshold": options.mobility_threshold, "mobility_rule": options.mobility_rule,
        "track_seed": [options.seed, index],
        "flow_fwd_valid": [True] * t, "flow_bwd_valid": [True] * t,
        "camera": {key: camera[key] for key in LENS if key in camera},
        "layers": {name: name in decoded for name in OPTIONAL_LAYERS},
    }
    scene = Scene(
        rgb=np.ascontiguousarray(rgba[..., :3]), depth=depth.astype(np.float32),
        segmentation=segmentation, flow_fwd=decoded.get("flow_fwd"),
        flow_bwd=decoded.get("flow_bwd"), intrinsics=intrinsics,
        cam_to_world=cam_to_world.astype(np.float32), object_to_world=object_to_world,
        objects=objects, tracks=np.zeros((0, t, 2), np.float32), occluded=np.zeros((0, t), bool),
        query_frame=np.zeros(0, np.int32), track_object=np.zeros(0, np.int32),
        tracks_world=None, displacement=None, moving=None, normal=decoded.get("normal"),
        object_coordinates=decoded.get("object_coordinates"), instances=decoded.get("instances"),
        events=decoded.get("events"), meta=meta)
    if not options.wants("tracks"):  # the caller draws its own (the paper protocol)
        return scene
    drawn = tapvid_kubric_tracks(scene, [options.seed, index], NUM_TRACKS)  # from the layers above
    return dataclasses.replace(
        scene, tracks=drawn.tracks, occluded=drawn.occluded, query_frame=drawn.query_frame,
        track_object=drawn.track_object, tracks_world=drawn.tracks_world,
        displacement=drawn.displacement, moving=mobility_labels(drawn, object_to_world, options))
