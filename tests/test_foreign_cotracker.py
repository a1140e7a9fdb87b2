"""CoTracker's Kubric folders read as Scenes (datagen/foreign/cotracker_kubric.py): folders written
here from the format's facts (reference kubric_movi.md 4.1 and 8.5: `SEQ/frames/*.png` and
`SEQ/SEQ.npy`, `np.save` of a dict whose `visibility` holds the occlusion flag; the
CoTracker3_Kubric release adds `coords_depth`, `depth`, `camera` and `depths/`) read back equal;
our scenes through `c4d export cotracker` read back equal; and bad input refused in one line
(a folder of another kind, a missing file, a corrupt frame or pickle, a crafted pickle that would
run code).
"""

from __future__ import annotations

import logging
import os
import pickle
from pathlib import Path

import cv2
import numpy as np
import pytest

from c4d.cli import main
from c4d_core.errors import UserError
from c4d_core.geometry import matrix_to_quat
from datagen import read_scenes
from datagen.foreign import ReadOptions, Unit, cotracker_kubric, kubric_worker

H, W, T, N = 24, 32, 6, 12
FOCAL_MM, SENSOR_MM = 35.0, 32.0  # Kubric's lens (reference 1.6): fx = 35 / 32 * W


def write_sequence(root: Path, name: str, rgb: np.ndarray, record: dict,
                   depths: np.ndarray | None = None) -> Path:
    """One sequence folder as CoTracker's data holds it: frames/NNN.png (8-bit RGB) and NAME.npy
    (np.save of the dict, pickled), plus depths/NNN.npy where given (the release)."""
    folder = root / name
    (folder / "frames").mkdir(parents=True)
    for t, frame in enumerate(rgb):
        assert cv2.imwrite(str(folder / "frames" / f"{t:03d}.png"), frame[..., ::-1])
    np.save(folder / f"{name}.npy", record, allow_pickle=True)
    if depths is not None:
        (folder / "depths").mkdir()
        for t, depth in enumerate(depths):
            np.save(folder / "depths" / f"{t:03d}.npy", depth)
    return folder


def read_all(path: Path, **options) -> list:
    return [next(cotracker_kubric.read_units(unit, ReadOptions(**options)))
            for unit in cotracker_kubric.units(path)]


def tracking_record(rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    rgb = rng.integers(0, 256, (T, H, W, 3), dtype=np.uint8)
    coords = rng.uniform(-2, W + 2, (N, T, 2)).astype(np.float32)
    occluded = rng.random((N, T)) < 0.3
    return rgb, {"coords": coords, "visibility": occluded}


# --- (i) CoTracker's original layout: tracking only ----------------------------------------------


def test_original_layout_reads_back_its_frames_tracks_and_occlusion(tmp_path, caplog):
    rng = np.random.default_rng(0)
    written = {}
    for name in ("0001", "0000"):
        rgb, record = tracking_record(rng)
        write_sequence(tmp_path / "movi_f", name, rgb, record)
        written[name] = rgb, record
    root = tmp_path / "movi_f"
    assert cotracker_kubric.detect(root) and cotracker_kubric.detect(root / "0000")
    assert not kubric_worker.detect(root)
    units = cotracker_kubric.units(root)
    assert [Path(u.path).name for u in units] == ["0000", "0001"]  # sorted, unlike os.listdir
    assert [u.index for u in units] == [0, 1] and units[0].kind == "cotracker-kubric"
    with caplog.at_level(logging.WARNING):
        scenes = read_all(root)
    for unit, scene in zip(units, scenes):
        rgb, record = written[Path(unit.path).name]
        assert np.array_equal(scene.rgb, rgb)
        assert scene.tracks.dtype == np.float32 and np.array_equal(scene.tracks, record["coords"])
        # the file's `visibility` is the occlusion flag: CoTracker's loader negates it
        assert np.array_equal(scene.occluded, record["visibility"])
        visible = ~record["visibility"]
        assert np.array_equal(scene.query_frame, np.where(visible.any(1), visible.argmax(1), 0))
        assert scene.moving is None and scene.tracks_world is None and scene.cam_to_world is None
        assert scene.meta["layout"] == "original"
    # mobility is unavailable, and the reader says so once, naming the folder
    said = [r.getMessage() for r in caplog.records if "no mobility labels" in r.getMessage()]
    assert len(said) == 1 and str(root) in said[0]


# --- (ii) the CoTracker3_Kubric release: lifted to the world ------------------------------------


def kubric_camera(positions: np.ndarray) -> np.ndarray:
    """Kubric's camera quaternions (w,x,y,z) looking at the origin from `positions` (T,3), in
    Blender's camera axes (x right, y up, looking along -z), no roll (reference 1.6, 2.5)."""
    forward = -positions / np.linalg.norm(positions, axis=-1, keepdims=True)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right, axis=-1, keepdims=True)
    up = np.cross(right, forward)
    return matrix_to_quat(np.stack([right, up, -forward], axis=-1))


def release_scene(rng: np.random.Generator, focal_mm):
    """World points (N,T,3) (half static, a quarter moving 0.05 units a frame, a quarter 0.004),
    a Kubric camera on a line, and what the release stores of them: coords (x, y) with pixel
    centres at integers and coords_depth = z in the camera."""
    positions = np.linspace([9.0, -2.0, 4.0], [8.0, 1.0, 4.5], T)
    quaternions = kubric_camera(positions)
    start = rng.uniform(-2, 2, (N, 3))
    velocity = np.zeros((N, 3))
    velocity[N // 2: 3 * N // 4] = [0.05, 0.0, 0.0]
    velocity[3 * N // 4:] = [0.0, 0.004, 0.0]
    world = start[:, None] + np.arange(T)[None, :, None] * velocity[:, None]  # (N,T,3)
    forward = -positions / np.linalg.norm(positions, axis=-1, keepdims=True)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right, axis=-1, keepdims=True)
    down = np.cross(forward, right)
    rel = world - positions  # (N,T,3)
    x, y, z = (np.sum(rel * axis, -1) for axis in (right, down, forward))  # OpenCV camera frame
    f_px = np.broadcast_to(focal_mm, (T,)) / SENSOR_MM * W
    coords = np.stack([f_px * x / z + (W - 1) / 2, f_px * y / z + (H - 1) / 2], -1)
    moving = np.linalg.norm(velocity, axis=-1)[:, None].repeat(T, 1) > 0.01
    return world, positions, quaternions, coords, z, moving, f_px


@pytest.mark.parametrize("focal_mm", [FOCAL_MM, np.linspace(30.0, 40.0, T)])
def test_release_layout_is_lifted_to_the_world_and_labelled_by_world_mobility(tmp_path, focal_mm):
    rng = np.random.default_rng(1)
    world, positions, quaternions, coords, z, moving, f_px = release_scene(rng, focal_mm)
    rgb, record = tracking_record(rng)
    record |= {"coords": coords.astype(np.float32), "coords_depth": z.astype(np.float32),
               "depth": rng.uniform(5, 15, (N, T)).astype(np.float32),
               "camera": {"focal_length": focal_mm, "positions": positions,
                          "quaternions": quaternions}}
    write_sequence(tmp_path, "0576", rgb, record, depths=rng.uniform(5, 15, (T, H, W)))
    [scene] = read_all(tmp_path)
    assert np.array_equal(scene.rgb, rgb) and np.array_equal(scene.tracks, record["coords"])
    assert np.array_equal(scene.occluded, record["visibility"])
    assert np.allclose(scene.intrinsics[:, [0, 1], [0, 1]], f_px[:, None])
    assert np.allclose(scene.intrinsics[:, :2, 2], [(W - 1) / 2, (H - 1) / 2])
    assert np.allclose(scene.cam_to_world[:, :3, 3], positions, atol=1e-5)
    assert np.allclose(scene.tracks_world, world, atol=1e-4)
    assert scene.moving.dtype == bool and np.array_equal(scene.moving, moving)
    assert np.allclose(scene.displacement[moving], 0.05, atol=1e-4)
    assert scene.meta["layout"] == "release" and scene.meta["mobility_threshold"] == 0.01
    assert scene.depth is None and scene.track_object is None and scene.objects is None


def test_release_without_objects_labels_by_the_point_rule_and_says_so(tmp_path, caplog):
    rng = np.random.default_rng(2)
    world, positions, quaternions, coords, z, moving, _ = release_scene(rng, FOCAL_MM)
    rgb, record = tracking_record(rng)
    record |= {"coords": coords, "coords_depth": z,
               "camera": {"focal_length": FOCAL_MM, "positions": positions,
                          "quaternions": quaternions}}
    write_sequence(tmp_path, "a", rgb, record)
    write_sequence(tmp_path, "b", rgb, record)
    with caplog.at_level(logging.WARNING):
        scenes = read_all(tmp_path, mobility_rule="object")
    assert all(np.array_equal(s.moving, moving) for s in scenes)
    assert sum("mobility_rule=object cannot apply" in r.getMessage() for r in caplog.records) == 1


# --- our scenes through `c4d export cotracker` ----------------------------------------------------


def test_our_scenes_through_the_cotracker_export_read_back_equal(tmp_path):
    data, out = tmp_path / "data", tmp_path / "cotracker"
    assert main(["datagen", "--preset", "movi-e", "--resolution", "32x48", "--frames", "6",
                 "--workers", "1", "tracks.num_points=24", "objects.num_static=[2,3]",
                 "objects.num_tossed=[1,1]", "--num-scenes", "2", "--seed", "3",
                 "--out", str(data)]) == 0
    assert main(["export", "cotracker", str(data), str(out)]) == 0
    ours = list(read_scenes(data))
    theirs = read_all(out)
    assert len(theirs) == len(ours) == 2
    for s, r in zip(ours, theirs):
        assert r.meta["video_name"] == f"{s.meta['scene_index']:08d}"
        assert np.array_equal(r.rgb, s.rgb) and np.array_equal(r.tracks, s.tracks)
        assert np.array_equal(r.occluded, s.occluded) and np.array_equal(r.moving, s.moving)
        assert r.meta["layout"] == "c4d export"


# --- bad input ------------------------------------------------------------------------------------


def one_line(exc: pytest.ExceptionInfo) -> str:
    message = str(exc.value)
    assert "\n" not in message
    return message


@pytest.fixture
def sequence(tmp_path) -> Path:
    rgb, record = tracking_record(np.random.default_rng(3))
    return write_sequence(tmp_path / "root", "0007", rgb, record)


def unit_of(folder: Path) -> Unit:
    return Unit(cotracker_kubric.KIND, str(folder), 0, str(folder))


def read(folder: Path):
    return next(cotracker_kubric.read_units(unit_of(folder)))


def test_a_folder_of_another_kind_is_refused_naming_what_was_expected(tmp_path):
    (tmp_path / "seq").mkdir()
    (tmp_path / "seq" / "notes.txt").write_text("hello")
    assert not cotracker_kubric.detect(tmp_path)
    with pytest.raises(UserError) as exc:
        cotracker_kubric.units(tmp_path)
    assert str(tmp_path) in one_line(exc) and "SEQ/frames/*.png and SEQ/SEQ.npy" in str(exc.value)
    with pytest.raises(UserError, match="no sub-folder 'val'"):
        cotracker_kubric.units(tmp_path, split="val")


def test_a_missing_file_is_named(sequence):
    (sequence / "0007.npy").unlink()
    with pytest.raises(UserError) as exc:
        read(sequence)
    assert "0007.npy is missing" in one_line(exc)


def test_a_corrupt_frame_is_named(sequence):
    (sequence / "frames" / "002.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 40)
    with pytest.raises(UserError) as exc:
        read(sequence)
    assert "002.png" in one_line(exc)


def test_a_corrupt_pickle_is_named(sequence):
    path = sequence / "0007.npy"
    path.write_bytes(path.read_bytes()[:-200])  # cut short
    with pytest.raises(UserError) as exc:
        read(sequence)
    assert str(path) in one_line(exc) and "damaged" in str(exc.value)


@pytest.mark.parametrize("record, named", [
    ({"coords": np.zeros((N, T, 2))}, "visibility"),
    ({"coords": np.zeros((N, T + 1, 2)), "visibility": np.zeros((N, T + 1), bool)}, "coords"),
    ({"coords": np.zeros((N, T, 2)), "visibility": np.zeros((N, T), bool), "coords_depth":
      np.ones((N, T)), "camera": {"positions": np.zeros((T, 3))}}, "camera.focal_length"),
    ([1, 2, 3], "not a dict"),
])
def test_a_record_without_the_keys_and_shapes_is_named(sequence, record, named):
    np.save(sequence / "0007.npy", np.array(record, dtype=object) if isinstance(record, list)
            else record, allow_pickle=True)
    with pytest.raises(UserError) as exc:
        read(sequence)
    assert named in one_line(exc) and "0007.npy" in str(exc.value)


class _RunsCode:
    """Unpickled by a plain `pickle.load`, it would run a shell command."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def test_a_crafted_pickle_is_refused_without_running_code(sequence):
    marker = sequence / "ran"
    path = sequence / "0007.npy"
    with open(path, "wb") as fh:  # an .npy header of a 0-d object array, then the pickle
        np.lib.format.write_array_header_1_0(fh, {"descr": "|O", "fortran_order": False,
                                                  "shape": ()})
        pickle.dump({"coords": _RunsCode(marker)}, fh, protocol=3)
    with pytest.raises(UserError) as exc:
        read(sequence)
    assert "could run code" in one_line(exc) and "system" in str(exc.value)
    assert not marker.exists()
