"""Validation of a shard set against the format (`c4d inspect SOURCE --check`), scene by scene.

- `iter_dataset`: every sample of a shard set (or every scene of other projects' Kubric data,
  `datagen.foreign`) as a `Sample` (its Scene, or why it cannot be read), streaming (memory
  stays at one scene); the dataset report reads through it too.
- `validate_scene`: every way one scene breaks the contract (wrong shape or dtype, against
  `datagen.codecs.ARRAY_FIELDS`; non-finite values, ids out of range, occluded at query, mobility
  label disagreeing with the displacement; of the optional layers: normals not of unit length,
  object coordinates outside [0,1] or not 0 on the background, boxes and visible pixels that
  disagree with the segmentation, events naming no object).
- `check_dataset`: decode and validate every sample, listing every problem (corrupt member,
  truncated shard, ...) with shard and scene key, without stopping at the first, and the shards
  the dataset file lists that are missing.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from c4d_core.errors import UserError
from datagen import foreign, shards
from datagen.annotate import segment_boxes
from datagen.codecs import (ARRAY_FIELDS, CHECKSUMS, QUANTISED, QUANTUM, REQUIRED_FIELDS,
                            event_records, instance_records, wrong_layout)
from datagen.scene import OPTIONAL_LAYERS, Scene

# |n| - 1 allowed in a stored normal: three components each within half a quantisation step.
NORMAL_TOLERANCE = 4 * (QUANTISED["normal"][1] - QUANTISED["normal"][0]) / QUANTUM

# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------


@dataclass
class Sample:
    """One sample of a shard set: where it is, and its Scene or the reason it could not be read."""

    shard: str
    key: str
    scene: Scene | None
    error: str | None = None
    verified: bool = True  # False: the sample carries no checksums (format 2 or older)


def iter_dataset(source, split: str | None = None, fields=None, full_first: int = 0) -> Iterator[Sample]:
    """Every sample of `source` (anything `datagen.read_scenes` accepts, or other projects'
    Kubric data, `datagen.foreign`), in reading order.

    `fields`: decode only these Scene fields (default all), except for the first `full_first`
    samples, which are decoded in full. A corrupt sample or a truncated shard yields a `Sample`
    with `error` set, and reading goes on with the next sample or shard.
    """
    if foreign.source_kind(source) != foreign.SHARDS:
        yield from _iter_foreign(source, split, fields, full_first)
        return
    count = 0
    for shard in shards.list_shards(source, split):
        try:
            for raw in shards.iter_samples(shard):
                wanted = None if count < full_first else fields
                count += 1
                verified = CHECKSUMS in raw
                try:
                    scene = shards.decode_scene(raw, wanted)
                except UserError as exc:
                    yield Sample(str(shard), raw["__key__"], None, str(exc), verified)
                else:
                    yield Sample(str(shard), raw["__key__"], scene, None, verified)
        except UserError as exc:  # the tar itself is truncated or corrupt
            yield Sample(str(shard), "?", None, str(exc))


def _iter_foreign(source, split: str | None, fields, full_first: int) -> Iterator[Sample]:
    """`iter_dataset` of other projects' Kubric data: one `Sample` per unit (its file or folder
    as the shard, the rest of its name as the key; tracks the data lacks drawn with seed 0 and
    our point mobility label); a damaged unit yields its error and reading goes on."""
    for count, unit in enumerate(foreign.source_units(source, split)):
        key = unit.name[len(unit.path):].strip() if unit.name.startswith(unit.path) else unit.name
        options = foreign.ReadOptions(fields=None if count < full_first or fields is None
                                      else tuple(fields))
        try:
            scene = foreign.read_unit(unit, options)
        except UserError as exc:
            yield Sample(unit.path, key or unit.name, None, str(exc))
        else:
            yield Sample(unit.path, key or unit.name, scene)


# --------------------------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------------------------


def _expected_shapes(scene: Scene) -> dict[str, tuple[int | None, ...]]:
    """field -> the shape the contract requires, given T, H, W, K and N of the scene; the dtype
    of each is `datagen.codecs.ARRAY_FIELDS`'s."""
    t, h, w = scene.rgb.shape[:3]
    k = len(scene.objects) if scene.objects is not None else None
    n = scene.tracks.shape[0] if isinstance(scene.tracks, np.ndarray) else None
    shapes = {
        "rgb": (t, h, w, 3),
        "depth": (t, h, w),
        "segmentation": (t, h, w),
        "flow_fwd": (t, h, w, 2),
        "flow_bwd": (t, h, w, 2),
        "intrinsics": (t, 3, 3),
        "cam_to_world": (t, 4, 4),
        "tracks": (n, t, 2),
        "normal": (t, h, w, 3),
        "object_coordinates": (t, h, w, 3),
    }
    if k is not None:
        shapes["object_to_world"] = (k, t, 4, 4)
    if n is not None:
        shapes |= {
            "occluded": (n, t),
            "query_frame": (n,),
            "track_object": (n,),
            "tracks_world": (n, t, 3),
            "displacement": (n, t),
            "moving": (n, t),
        }
    return shapes


def validate_scene(scene: Scene, cfg) -> list[str]:
    """Every way `scene` breaks the contract (INTERFACES.md), as short sentences; [] if none.

    `cfg`: the inspect config (`configs/inspect/default.yaml`), for its `check` tolerances.
    """
    required = REQUIRED_FIELDS
    if isinstance(scene.meta, dict) and scene.meta.get("generator") == "datagen":
        # every datagen preset produces every field but the optional layers, which its meta
        # lists as made (scenes written before the layers existed list none)
        layers = scene.meta.get("layers", {})
        required = tuple(name for name in Scene.field_names()
                         if name not in OPTIONAL_LAYERS or layers.get(name))
    missing = [name for name in required if getattr(scene, name) is None]
    if missing:
        return [f"required fields are missing (truncated sample?): {', '.join(missing)}"]
    if not isinstance(scene.rgb, np.ndarray) or scene.rgb.ndim != 4:
        return [f"rgb must be (T,H,W,3), got {getattr(scene.rgb, 'shape', type(scene.rgb))}"]

    problems = []
    wrong = set()  # the fields of the wrong dtype or shape
    for name, shape in _expected_shapes(scene).items():
        value = getattr(scene, name)
        got = None if value is None else wrong_layout(name, value, shape)
        if got is not None:
            problems.append(f"{name} is {got}, expected {ARRAY_FIELDS[name][0]} {shape}")
            wrong.add(name)
    ok = {name for name in Scene.field_names() if getattr(scene, name) is not None} - wrong

    for name in ok & {name for name, (dtype, _) in ARRAY_FIELDS.items() if dtype.kind == "f"}:
        bad = int((~np.isfinite(getattr(scene, name))).sum())
        if bad:
            problems.append(f"{name} has {bad} NaN or infinite values")
    num_frames, num_objects = scene.num_frames, len(scene.objects)
    if "depth" in ok and (scene.depth[np.isfinite(scene.depth)] <= 0).any():
        problems.append("depth has values <= 0")
    if "segmentation" in ok:
        low, high = int(scene.segmentation.min()), int(scene.segmentation.max())
        if low < 0 or high > num_objects:
            problems.append(f"segmentation ids span [{low}, {high}], outside [0, {num_objects}]")
    # Kubric renders a frame beyond each end, so its scenes' meta marks these flows valid
    fwd_valid, bwd_valid = scene.meta.get("flow_fwd_valid"), scene.meta.get("flow_bwd_valid")
    if "flow_fwd" in ok and not (fwd_valid and fwd_valid[-1]) and np.abs(scene.flow_fwd[-1]).max() > 0:
        problems.append("flow_fwd of the last frame is not zero (it has no next frame)")
    if "flow_bwd" in ok and not (bwd_valid and bwd_valid[0]) and np.abs(scene.flow_bwd[0]).max() > 0:
        problems.append("flow_bwd of the first frame is not zero (it has no previous frame)")
    if "cam_to_world" in ok and np.isfinite(scene.cam_to_world).all():
        rot = scene.cam_to_world[:, :3, :3].astype(np.float64)
        error = np.abs(np.swapaxes(rot, 1, 2) @ rot - np.eye(3)).max()
        if error > cfg.check.rotation_tolerance or np.abs(scene.cam_to_world[:, 3] - [0, 0, 0, 1]).max() > 0:
            problems.append(f"cam_to_world is not rigid (|R^T R - I| = {error:.2g})")
    if "intrinsics" in ok and (scene.intrinsics[:, [0, 1], [0, 1]] <= 0).any():
        problems.append("intrinsics have a focal length <= 0")
    if "track_object" in ok and scene.num_tracks:
        low, high = int(scene.track_object.min()), int(scene.track_object.max())
        if low < 0 or high > num_objects:
            problems.append(f"track_object spans [{low}, {high}], outside [0, {num_objects}]")
    if {"query_frame", "occluded"} <= ok and scene.num_tracks:
        queries = scene.query_frame
        if queries.min() < 0 or queries.max() >= num_frames:
            problems.append(f"query_frame spans [{queries.min()}, {queries.max()}], "
                            f"outside [0, {num_frames - 1}]")
        else:
            hidden = int(scene.occluded[np.arange(scene.num_tracks), queries].sum())
            if hidden:
                problems.append(f"{hidden} tracks are occluded at their query frame")
    threshold = float(scene.meta.get("mobility_threshold", cfg.check.mobility_threshold))
    if scene.meta.get("mobility_rule") == "object" and {"moving", "object_to_world", "track_object"} <= ok:
        # the paper appendix's rule (datagen.foreign.ReadOptions): the object's position change
        expected = foreign.object_moving(scene.object_to_world, threshold)[scene.track_object]
        disagree = int((scene.moving != expected).sum())
        if disagree:
            problems.append(f"moving disagrees with its object's position change > {threshold} "
                            f"at {disagree} points")
    elif {"moving", "displacement"} <= ok:
        disagree = int((scene.moving != (scene.displacement > threshold)).sum())
        if disagree:
            problems.append(f"moving disagrees with displacement > {threshold} at {disagree} points")
    if "displacement" in ok and (scene.displacement < 0).any():
        problems.append("displacement has negative values")
    return problems + _layer_problems(scene, ok)


def _layer_problems(scene: Scene, ok: set[str]) -> list[str]:
    """The problems of the optional layers (normal, object_coordinates, instances, events)."""
    problems = []
    background = scene.segmentation == 0 if "segmentation" in ok else None
    if "normal" in ok and np.isfinite(scene.normal).all():
        error = float(np.abs(np.linalg.norm(scene.normal, axis=-1) - 1.0).max())
        if error > NORMAL_TOLERANCE:
            problems.append(f"normal is not of unit length (| |n| - 1 | up to {error:.2g})")
    if "object_coordinates" in ok:
        coords = scene.object_coordinates
        if ((coords < 0) | (coords > 1)).any():
            problems.append("object_coordinates lie outside [0, 1]")
        if background is not None and coords[background].any():
            problems.append(f"object_coordinates are not 0 on {int(coords[background].any(-1).sum())}"
                            " background pixels")
    if scene.instances is not None:
        problems += _instance_problems(scene, "segmentation" in ok)
    if scene.events is not None:
        problems += _event_problems(scene)
    return problems


def _record_layout(records, values) -> str | None:
    """What is wrong with the keys, dtypes or shapes of a record field (`Scene.instances` or
    `Scene.events`), as the shard encoder (`records`: its `instance_records` or
    `event_records`) would reject it; None if nothing."""
    try:
        records(values)
    except ValueError as exc:
        return str(exc)
    return None


def _instance_problems(scene: Scene, with_segmentation: bool) -> list[str]:
    instances, t, k = scene.instances, scene.num_frames, len(scene.objects)
    layout = _record_layout(instance_records, instances)
    if layout:
        return [layout]
    if np.shape(instances["visible_pixels"]) != (k, t):
        return [f"instances cover {np.shape(instances['visible_pixels'])} (objects, frames), the "
                f"scene has {(k, t)}"]
    problems = []
    for key in ("bbox_3d", "velocity", "angular_velocity"):
        if not np.isfinite(instances[key]).all():
            problems.append(f"instances[{key!r}] has NaN or infinite values")
    if with_segmentation:  # both are exact functions of the segmentation
        visible, boxes = segment_boxes(scene.segmentation, k)
        if not np.array_equal(visible, instances["visible_pixels"]):
            problems.append("instances['visible_pixels'] disagree with the segmentation at "
                            f"{int((visible != instances['visible_pixels']).sum())} object-frames")
        if not np.array_equal(boxes, instances["bbox_2d"], equal_nan=True):
            problems.append("instances['bbox_2d'] disagree with the segmentation's extents")
    return problems


def _event_problems(scene: Scene) -> list[str]:
    events, k, t = scene.events, len(scene.objects), scene.num_frames
    layout = _record_layout(event_records, events)
    if layout:
        return [layout]
    problems = []
    instances = events["instances"]
    if ((instances < -1) | (instances >= k)).any() or (instances[:, 0] == instances[:, 1]).any():
        problems.append(f"events name instances outside [-1, {k - 1}] or a body with itself")
    if ((events["frame"] < -1) | (events["frame"] > t)).any():
        problems.append(f"events have frames outside the simulated [-1, {t}]")
    if not (events["force"] > 0).all():
        problems.append("events have a normal force <= 0")
    if len(events["frame"]) and np.abs(np.linalg.norm(events["contact_normal"], axis=-1) - 1).max() > 1e-3:
        problems.append("events have contact normals that are not unit vectors")
    return problems


@dataclass
class CheckResult:
    """Outcome of `check_dataset`: number of samples and shards read, every problem found and
    the shards missing."""

    num_samples: int
    problems: list[tuple[str, str, str]]  # (shard, scene key, problem)
    num_unverified: int = 0  # samples without checksums (shards of format 2 or older)
    num_shards: int = 0  # shards read (or found unreadable)
    missing: list[Path] = field(default_factory=list)  # shards the dataset file lists, absent

    @property
    def num_bad_samples(self) -> int:
        return len({(shard, key) for shard, key, _ in self.problems})


def check_dataset(source, cfg, split: str | None = None, progress: bool = True) -> CheckResult:
    """Decode and validate every sample of `source`; never stops at the first problem. The
    shards that the dataset file of a `source` folder lists but that are absent are counted
    apart (`CheckResult.missing`), not as problems of scenes."""
    problems: list[tuple[str, str, str]] = []
    if foreign.source_kind(source) != foreign.SHARDS:  # other projects' data: its files or folders
        listed, missing = sorted({unit.path for unit in foreign.source_units(source, split)}), []
    else:
        listed = shards.list_shards(source, split)
        folder = isinstance(source, (str, Path)) and Path(source).is_dir()
        missing = shards.missing_shards(listed) if folder else []
    count = unverified = 0
    for sample in tqdm(iter_dataset(source, split), desc="check", unit="scene", disable=not progress):
        count += 1
        unverified += not sample.verified
        if sample.error is not None:
            problems.append((sample.shard, sample.key, sample.error))
            continue
        problems += [(sample.shard, sample.key, p) for p in validate_scene(sample.scene, cfg)]
    return CheckResult(count, problems, unverified, len(listed), missing)
