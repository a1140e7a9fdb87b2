"""Folders in Kubric's worker layout read as Scenes (datagen/foreign/kubric_worker.py): our scenes
-> `c4d export kubric` -> the reader equal our scenes (rgb exact; segmentation, objects, instances
and events up to Kubric's instance order, docs/FORMAT.md "kubric"; depth and the 16-bit layers
within one step; cameras within 1e-5; TAP-Vid-Kubric tracks and their world mobility equal to
those drawn from our own scene); the read options; and bad input refused in one line naming the
file (a folder of another kind, a missing or corrupt file, a missing record).
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from c4d.cli import main
from c4d_core.errors import UserError
from datagen import read_scenes
from datagen.annotate import tapvid_kubric_tracks
from datagen.foreign import (ReadOptions, Unit, cotracker_kubric, kubric_worker, object_moving,
                             source_kind)

SIZE = (48, 64)  # H, W: not square, so an axis swap shows
FRAMES = 8


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> tuple[list, Path]:
    """2 of our scenes with every optional layer, and their `c4d export kubric` folder."""
    root = tmp_path_factory.mktemp("worker")
    data, out = root / "data", root / "kubric"
    assert main(["datagen", "--preset", "movi-e", "--resolution", "48x64", "--frames", str(FRAMES),
                 "--workers", "1", "tracks.num_points=32", "objects.num_static=[2,3]",
                 "objects.num_tossed=[1,2]", "--num-scenes", "2", "--seed", "4", "--out", str(data),
                 "layers.normal=true", "layers.object_coordinates=true", "layers.events=true"]) == 0
    assert main(["export", "kubric", str(data), str(out)]) == 0
    return list(read_scenes(data)), out


def read_all(path: Path, **options) -> list:
    return [next(kubric_worker.read_units(unit, ReadOptions(**options)))
            for unit in kubric_worker.units(path)]


def kubric_order(scene) -> np.ndarray:
    """Kubric's instance order (docs/FORMAT.md "kubric"): the objects seen in some frame, most
    visible pixels first, ties by index."""
    counts = np.bincount(scene.segmentation.ravel(), minlength=len(scene.objects) + 1)[1:]
    return np.array([k for k in np.argsort(-counts, kind="stable") if counts[k] > 0])


def in_kubric_order(scene, order: np.ndarray):
    """Our scene with its objects renumbered in Kubric's order (the unseen ones left out)."""
    relabel = np.zeros(len(scene.objects) + 1, np.int32)
    relabel[order + 1] = np.arange(1, len(order) + 1)
    return dataclasses.replace(scene, segmentation=relabel[scene.segmentation],
                               object_to_world=scene.object_to_world[order],
                               objects=[scene.objects[k] for k in order],
                               instances=None if scene.instances is None else
                               {key: value[order] for key, value in scene.instances.items()})


def test_detect_and_units(exported, tmp_path):
    """A source is the export's OUT (its scene folders in OUT/scenes/), OUT/scenes itself, one
    scene folder, or a folder of scene folders as Kubric's worker jobs leave them (no marker)."""
    _, out = exported
    job = Path(shutil.copytree(out / "scenes", tmp_path / "job"))  # Kubric's own job folder
    for source in (out, out / "scenes", job, out / "scenes" / "00000001"):
        assert kubric_worker.detect(source) and not cotracker_kubric.detect(source), source
    assert not kubric_worker.detect(out / "nothing")
    assert source_kind(out) == source_kind(out / "scenes") == source_kind(job) == "kubric-worker"
    for source in (out, out / "scenes", job):
        units = kubric_worker.units(source)
        assert [(u.kind, Path(u.path).name, u.index) for u in units] == \
            [("kubric-worker", "00000000", 0), ("kubric-worker", "00000001", 1)], source
    assert kubric_worker.scene_root(out) == out / "scenes" and kubric_worker.scene_root(job) == job
    assert [Path(u.path).name for u in kubric_worker.units(out / "scenes" / "00000001")] == \
        ["00000001"]


def test_our_scenes_through_the_kubric_export_read_back_equal(exported):
    ours, out = exported
    h, w = SIZE
    for s, r in zip(ours, read_all(out)):
        order = kubric_order(s)
        assert r.meta["video_name"] == f"{s.meta['scene_index']:08d}"
        assert np.array_equal(r.rgb, s.rgb)
        assert np.array_equal(r.segmentation, in_kubric_order(s, order).segmentation)
        # depth: Euclidean range in a float TIFF, back to z-depth
        assert r.depth.dtype == np.float32 and np.allclose(r.depth, s.depth, rtol=1e-5)
        # 16-bit layers: within one step of the range
        ranges = json.loads((Path(r.meta["folder"]) / "data_ranges.json").read_text())
        for ours_flow, theirs, name in ((s.flow_fwd, r.flow_fwd, "forward_flow"),
                                        (s.flow_bwd, r.flow_bwd, "backward_flow")):
            step = (ranges[name]["max"] - ranges[name]["min"]) / 65535
            assert theirs.shape == (FRAMES, h, w, 2)
            assert np.abs(theirs - ours_flow).max() <= step + 1e-4, name
        assert np.abs(r.normal - s.normal).max() <= 2 / 65535 + 1e-6
        assert np.abs(r.object_coordinates - s.object_coordinates).max() <= 1 / 65535 + 1e-6
        # cameras
        assert np.allclose(r.intrinsics, s.intrinsics, rtol=1e-6)
        assert np.abs(r.cam_to_world - s.cam_to_world).max() <= 1e-5
        assert np.abs(r.object_to_world - s.object_to_world[order]).max() <= 1e-5
        # objects, instances and events, in Kubric's order
        assert len(r.objects) == len(order)
        for j, k in enumerate(order):
            assert {key: r.objects[j][key] for key in s.objects[k]} == s.objects[k]
        for key in ("bbox_3d", "velocity", "angular_velocity", "visible_pixels", "is_dynamic"):
            assert np.allclose(r.instances[key], s.instances[key][order]), key
        assert np.allclose(r.instances["bbox_2d"], s.instances["bbox_2d"][order], equal_nan=True)
        assert np.allclose(r.instances["image_position"], s.instances["image_position"][order],
                           atol=1e-4, equal_nan=True)
        index = {int(k): j for j, k in enumerate(order)}
        assert np.array_equal(r.events["instances"],
                              [[index.get(i, -1) for i in pair] for pair in s.events["instances"]])
        assert np.allclose(r.events["frame"], s.events["frame"])
        assert np.allclose(r.events["image_position"], s.events["image_position"], atol=1e-4)
        for key in ("force", "position", "contact_normal"):
            assert np.array_equal(r.events[key], s.events[key]), key


def test_tracks_and_world_mobility_equal_those_drawn_from_our_scene(exported):
    ours, out = exported
    for index, (s, r) in enumerate(zip(ours, read_all(out, seed=5))):
        want = tapvid_kubric_tracks(in_kubric_order(s, kubric_order(s)), [5, index])
        assert r.tracks.shape == (256, FRAMES, 2) and r.meta["track_seed"] == [5, index]
        assert np.array_equal(r.query_frame, want.query_frame)
        assert np.array_equal(r.track_object, want.track_object)
        assert np.abs(r.tracks - want.tracks).max() < 1e-3
        assert np.abs(r.tracks_world - want.tracks_world).max() < 1e-4
        assert np.array_equal(r.occluded, want.occluded)
        assert np.array_equal(r.moving, want.moving) and r.moving.any() and not r.moving.all()
        assert np.allclose(r.displacement, want.displacement, atol=1e-5)


def test_read_options_fields_rule_and_seed(exported):
    _, out = exported
    unit = kubric_worker.units(out)[0]
    fewer = next(kubric_worker.read_units(unit, ReadOptions(fields=("rgb", "tracks", "moving"))))
    assert all(getattr(fewer, name) is None for name in kubric_worker.SKIPPABLE)
    assert fewer.depth is not None and fewer.moving is not None
    by_object = next(kubric_worker.read_units(unit, ReadOptions(mobility_rule="object")))
    moved = object_moving(by_object.object_to_world, 0.01)
    assert np.array_equal(by_object.moving, moved[by_object.track_object])
    again = next(kubric_worker.read_units(unit, ReadOptions(mobility_rule="object")))
    assert np.array_equal(again.tracks, by_object.tracks)  # deterministic by seed
    other = next(kubric_worker.read_units(unit, ReadOptions(seed=1)))
    assert not np.array_equal(other.tracks, by_object.tracks)


def test_a_movi_f_scene_written_for_movi_f_py_reads_back_in_our_units(tmp_path):
    """movi_f.py's conventions (flow ranges in 512-pixel frames, scale relative to the GSO mesh)
    are undone: flows and objects equal ours."""
    data, out = tmp_path / "data", tmp_path / "kubric"
    assert main(["datagen", "--preset", "movi-f", "--resolution", "32x48", "--frames", "6",
                 "--workers", "1", "tracks.num_points=16", "objects.num_static=[2,3]",
                 "objects.num_tossed=[1,1]", "--num-scenes", "1", "--seed", "2", "--out", str(data),
                 "layers.normal=true", "layers.object_coordinates=true", "layers.events=true"]) == 0
    assert main(["export", "kubric", str(data), str(out)]) == 0
    [s], [r] = list(read_scenes(data)), read_all(out)
    ranges = json.loads((out / "scenes" / "00000000" / "data_ranges.json").read_text())
    for ours_flow, theirs, name in ((s.flow_fwd, r.flow_fwd, "forward_flow"),
                                    (s.flow_bwd, r.flow_bwd, "backward_flow")):
        step = (ranges[name]["max"] - ranges[name]["min"]) * 512 / 65535
        assert np.abs(theirs - ours_flow).max() <= step + 1e-4, name
    order = kubric_order(s)
    for j, k in enumerate(order):
        assert r.objects[j]["asset_id"] == s.objects[k]["asset_id"]
        assert np.isclose(r.objects[j]["scale"], s.objects[k]["scale"], rtol=1e-9)
    assert r.meta["motion_blur"] == s.meta["motion_blur"]


# --- bad input ------------------------------------------------------------------------------------


@pytest.fixture
def scene_copy(exported, tmp_path) -> Path:
    _, out = exported
    return Path(shutil.copytree(out / "scenes" / "00000000", tmp_path / "00000000"))


def read(folder: Path):
    return next(kubric_worker.read_units(Unit(kubric_worker.KIND, str(folder), 0, str(folder))))


def one_line(exc: pytest.ExceptionInfo) -> str:
    message = str(exc.value)
    assert "\n" not in message
    return message


def test_a_folder_of_another_kind_is_refused_naming_what_was_expected(tmp_path):
    (tmp_path / "scene").mkdir()
    (tmp_path / "scene" / "rgb_00000.png").write_bytes(b"not Kubric's")
    assert not kubric_worker.detect(tmp_path)
    with pytest.raises(UserError) as exc:
        kubric_worker.units(tmp_path)
    assert str(tmp_path) in one_line(exc) and "rgba_00000.png" in str(exc.value) \
        and "metadata.json" in str(exc.value)


@pytest.mark.parametrize("name", ["depth_00003.tiff", "backward_flow_00007.png", "events.json",
                                  "data_ranges.json"])
def test_a_missing_file_is_named(scene_copy, name):
    (scene_copy / name).unlink()
    with pytest.raises(UserError) as exc:
        read(scene_copy)
    assert f"{name} is missing" in one_line(exc) and str(scene_copy) in str(exc.value)


@pytest.mark.parametrize("name", ["rgba_00002.png", "depth_00001.tiff", "segmentation_00004.png",
                                  "normal_00000.png", "metadata.json"])
def test_a_corrupt_file_is_named(scene_copy, name):
    path = scene_copy / name
    path.write_bytes(path.read_bytes()[:40])  # cut short
    with pytest.raises(UserError) as exc:
        read(scene_copy)
    assert str(path) in one_line(exc)


@pytest.mark.parametrize("edit, named", [
    (lambda m: m["camera"].pop("K"), "camera.K"),
    (lambda m: m["instances"][0].pop("quaternions"), "instances[0].quaternions"),
    (lambda m: m["camera"].update(positions=[[0.0, 0.0, 1.0]]), "camera.positions"),
    (lambda m: m.update(instances=m["instances"][:1]), "instances"),
])
def test_a_missing_or_wrong_record_is_named(scene_copy, edit, named):
    path = scene_copy / "metadata.json"
    meta = json.loads(path.read_text())
    edit(meta)
    path.write_text(json.dumps(meta))
    with pytest.raises(UserError) as exc:
        read(scene_copy)
    assert named in one_line(exc) and "metadata.json" in str(exc.value)
