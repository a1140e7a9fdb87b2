"""CoTracker's Kubric folders read as `Scene`s (reference kubric_movi.md 4.1 and 8.5;
docs/FORMAT.md "Reading Kubric's data").

A unit is one sequence folder SEQ, as co-tracker's `KubricMovifDataset`
(`cotracker/datasets/kubric_movif_dataset.py`) reads it:

- `SEQ/frames/*.png`: the RGB frames, in name order (T frames, H x W pixels);
- `SEQ/SEQ.npy`: `np.save` of a dict (a pickled 0-d object array; read here with the project's
  restricted unpickler, `c4d_core.pickles`, never `np.load(allow_pickle=True)`).

Two layouts, told apart by the dict's keys:

(i) CoTracker's original data (`kubric_movi_f_120_frames_dense/movi_f/SEQ/`, converted from
    TAP-Vid-Kubric tracks): `coords` (N,T,2) (x, y) pixels and `visibility` (N,T), which holds the
    OCCLUSION flag (written from TAP-Vid's `occluded`; the loader negates it). Tracking only: no
    camera, depth or objects, so world mobility is unavailable: `moving` is None and the reader
    says so once per folder of sequences (a warning naming it). `c4d export cotracker` writes this
    layout plus our `moving` (N,T) bool, which is read where present.
(ii) The CoTracker3_Kubric release (HF facebook/CoTracker3_Kubric: 512x512, 120 frames) adds
    `coords_depth` (N,T), `depth`, `camera` {`focal_length`, `positions` (T,3), `quaternions`
    (T,4)} and per-frame depth maps `SEQ/depths/000.npy ...`. Each track point is lifted to the
    world per frame: X(t) = cam_to_world(t) [z(t) K^-1 (x, y, 1)] with z = `coords_depth`, and
    labelled as our scenes are (`datagen.annotate.world_motion`): displacement[:, t] = |X(t) -
    X(t-1)| (t = 0: to t = 1), moving = displacement > `options.mobility_threshold` (0.01 units a
    frame by default, `datagen.foreign.ReadOptions`), tracks_world = X. The data has no objects,
    so `mobility_rule="object"` cannot apply: such scenes are labelled by the point rule, with one
    warning per folder of sequences.

What co-tracker's code does not say, and what is assumed here (its loader reads only `coords` and
`visibility`; the release's other keys are described only in co-tracker issues #152, #153, #158):
- `coords_depth` is the z-depth (distance to the camera plane) of each track point, in every frame
  (the dataset author in #153; Kubric's own depth maps are Euclidean range).
- `camera` is Kubric's camera record, as in its metadata.json and TFDS: `focal_length` in mm on a
  `sensor_width` of 32 mm (Kubric's default; a `sensor_width` in the record is used instead),
  horizontal fit, principal point at the image centre; `positions` and (w,x,y,z) `quaternions`
  in Blender's camera axes (x right, y up, looking along -z), as in `kubric_worker`. The release
  was rendered with `--randomize_focal_length` (co-tracker #130): a per-frame (T,) focal length
  is taken too. The frame rate is not recorded, so the threshold applies per frame of the release.
- `coords` are read as stored, pixel centres at integers (CoTracker's loader marks x < 0 or
  x > W-1 out of view, and our export writes that); tracks converted from TAP-Vid's raster
  coordinates would be half a pixel off.
- `depth` and `depths/` are not read: their convention (z or range) is not documented (#152, #153),
  and the tracks' own `coords_depth` is what lifting needs. `depth` stays None.
Fields neither layout has are None: depth, segmentation, flows, object_to_world, objects,
track_object (and in (i) intrinsics, cam_to_world, tracks_world, displacement). `query_frame` is
each track's first visible frame (CoTracker's default query; 0 for a track never visible).

The reader interface is `datagen.foreign`'s (KIND, EXPECTED, detect, units, read_units).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from c4d_core.errors import UserError
from c4d_core.geometry import intrinsics_from_lens, unproject
from c4d_core.pickles import read_data_pickle
from c4d_core.video import read_video
from datagen.annotate import world_motion
from datagen.foreign import ReadOptions, Unit
from datagen.foreign.kubric_worker import camera_from_kubric, detect_folders, folder_units
from datagen.scene import Scene

log = logging.getLogger(__name__)

KIND = "cotracker-kubric"
EXPECTED = ("CoTracker's Kubric folders: a folder of sequence folders SEQ (or one) holding "
            "SEQ/frames/*.png and SEQ/SEQ.npy (kubric_movi_f_120_frames_dense/movi_f, or the "
            "CoTracker3_Kubric release)")
KUBRIC_SENSOR_WIDTH = 32.0  # mm: Kubric's PerspectiveCamera default (reference kubric_movi.md 1.6)
RECORD = ("np.save of a dict with coords (N,T,2) and visibility (N,T), as CoTracker's Kubric data "
          "holds")
_warned: set[tuple[str, Path]] = set()  # (what, folder of sequences) already said once


# --- the layout -----------------------------------------------------------------------------------


def is_sequence_folder(path: Path) -> bool:
    """Whether `path` looks like one CoTracker Kubric sequence: `frames/` and `NAME.npy`."""
    return (path / "frames").is_dir() and (path / f"{path.name}.npy").is_file()


def detect(path: Path) -> bool:
    """Whether `path` is a CoTracker Kubric sequence folder or a folder of them."""
    return detect_folders(path, is_sequence_folder)


def units(path, split: str | None = None) -> list[Unit]:
    """One `Unit` per sequence folder of `path`, sorted by name (`folder_units`; CoTracker lists
    them unsorted, and takes the first 30 of that listing as validation: here a split names a
    sub-folder)."""
    return folder_units(path, split, KIND, is_sequence_folder, EXPECTED)


def read_units(unit: Unit, options: ReadOptions = ReadOptions()) -> Iterator[Scene]:
    """The scene of one sequence-folder unit (`read_sequence`)."""
    yield read_sequence(Path(unit.path), unit.index, options)


# --- decoding -------------------------------------------------------------------------------------


def _read_record(path: Path) -> dict[str, Any]:
    """The dict of a sequence's `.npy` file, through the restricted unpickler."""
    value = read_data_pickle(path, "CoTracker annotation", f"expected {RECORD}", npy=True)
    if isinstance(value, np.ndarray) and value.dtype == object and value.shape == ():
        value = value.item()
    if not isinstance(value, dict):
        raise UserError(f"{path} holds {type(value).__name__}, not a dict; expected {RECORD}")
    return value


def _array(record: dict, path: Path, key: str, shape: tuple[int | None, ...] | None,
           where: str = "") -> np.ndarray:
    """record[key] as a float64 array of `shape` (None: any shape; a None entry: any size); a
    UserError naming the file and the key (after `where`, e.g. "camera.") where it is missing or
    of another shape."""
    if not isinstance(record, dict) or key not in record:
        raise UserError(f"{path} has no {where}{key}; expected {RECORD}, plus coords_depth and "
                        "camera in the CoTracker3_Kubric release")
    try:
        value = np.asarray(record[key], np.float64)
    except (TypeError, ValueError):
        value = None
    if shape is None and value is not None:
        return value
    if value is None or value.ndim != len(shape) or any(
            want is not None and got != want for got, want in zip(value.shape, shape)):
        got = "not numbers" if value is None else f"of shape {value.shape}"
        want = "(" + ",".join("*" if n is None else str(n) for n in shape) + ")"
        raise UserError(f"{path}'s {where}{key} is {got}, expected {want}")
    return value


def _camera(record: dict, path: Path, num_frames: int, height: int,
            width: int) -> tuple[np.ndarray, np.ndarray]:
    """intrinsics (T,3,3) and OpenCV cam_to_world (T,4,4) of the release's `camera` (module
    docstring: Kubric's lens in mm and camera axes)."""
    camera = record["camera"]
    focal = _array(camera, path, "focal_length", None, where="camera.").ravel()  # mm
    if focal.size not in (1, num_frames) or not np.all(focal > 0):
        raise UserError(f"{path}'s camera.focal_length is {focal[:3]}..., expected one "
                        f"positive focal length in mm or one per frame ({num_frames})")
    sensor = (float(_array(camera, path, "sensor_width", (), where="camera."))
              if "sensor_width" in camera else KUBRIC_SENSOR_WIDTH)
    intrinsics = np.stack([intrinsics_from_lens(f, sensor, height, width)
                           for f in np.broadcast_to(focal, (num_frames,))])
    cam_to_world = camera_from_kubric(
        _array(camera, path, "positions", (num_frames, 3), where="camera."),
        _array(camera, path, "quaternions", (num_frames, 4), where="camera."))
    return intrinsics, cam_to_world


WARNINGS = {
    "tracking only": "CoTracker Kubric sequences without depth and camera (CoTracker's original "
                     "layout): tracks and occlusion only, no mobility labels (moving is None); "
                     "the CoTracker3_Kubric release, Kubric's own data or `c4d datagen` scenes "
                     "have them",
    "point rule": "CoTracker3_Kubric sequences have no objects, so mobility_rule=object cannot "
                  "apply: their moving labels are by the point rule (a track's world "
                  "displacement since the previous frame)",
}


def _say_once(what: str, folder: Path) -> None:
    """Log `WARNINGS[what]` once per folder of sequences (per process)."""
    if (what, folder.parent) not in _warned:
        _warned.add((what, folder.parent))
        log.warning("%s: %s", folder.parent, WARNINGS[what])


def read_sequence(folder: str | Path, index: int = 0,
                  options: ReadOptions = ReadOptions()) -> Scene:
    """The `Scene` of one CoTracker Kubric sequence folder (module docstring), `index` its place
    in its source's reading order."""
    folder = Path(folder)
    frames_folder, record_path = folder / "frames", folder / f"{folder.name}.npy"
    if not is_sequence_folder(folder):
        missing = "frames/" if not frames_folder.is_dir() else record_path.name
        raise UserError(f"{folder} is not a CoTracker Kubric sequence: {missing} is missing "
                        f"(expected {EXPECTED})")
    if not any(frames_folder.iterdir()):
        raise UserError(f"{frames_folder} holds no frames; expected the sequence's PNG frames")
    rgb = read_video(frames_folder)  # (T,H,W,3), name order; a bad frame is a UserError naming it
    num_frames, height, width = rgb.shape[:3]
    record = _read_record(record_path)
    coords = _array(record, record_path, "coords", (None, num_frames, 2))
    occluded = _array(record, record_path, "visibility", coords.shape[:2]) != 0  # occlusion flags
    query_frame = np.argmax(~occluded, axis=1).astype(np.int32)  # first visible (0: never)
    meta = {"generator": "kubric", "source_format": KIND, "preset": KIND, "split": None,
            "scene_index": index, "video_name": folder.name, "folder": str(folder),
            "resolution": [height, width], "num_frames": num_frames, "fps": None}
    intrinsics = cam_to_world = world = displacement = None
    moving = None
    if "coords_depth" in record and "camera" in record:  # the CoTracker3_Kubric release
        z = _array(record, record_path, "coords_depth", coords.shape[:2])
        intrinsics, cam_to_world = _camera(record, record_path, num_frames, height, width)
        world = unproject(coords, z, intrinsics, cam_to_world)  # (N,T,3): per frame t, K_t, pose_t
        displacement, moving = world_motion(world, options.mobility_threshold)
        if options.mobility_rule != "point":
            _say_once("point rule", folder)
        meta |= {"layout": "release", "mobility_threshold": options.mobility_threshold,
                 "mobility_rule": "point"}
    elif "moving" in record:  # `c4d export cotracker`: our own label
        moving = _array(record, record_path, "moving", coords.shape[:2]) != 0
        meta["layout"] = "c4d export"
    else:
        _say_once("tracking only", folder)
        meta["layout"] = "original"
    return Scene(
        rgb=rgb, depth=None, segmentation=None, flow_fwd=None, flow_bwd=None,
        intrinsics=None if intrinsics is None else intrinsics.astype(np.float32),
        cam_to_world=None if cam_to_world is None else cam_to_world.astype(np.float32),
        object_to_world=None, objects=None, tracks=coords.astype(np.float32), occluded=occluded,
        query_frame=query_frame, track_object=None,
        tracks_world=None if world is None else world.astype(np.float32),
        displacement=displacement, moving=moving, meta=meta)
