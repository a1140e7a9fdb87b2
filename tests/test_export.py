"""`c4d export kubric|cotracker|tapvid`: each export read back by a reader written here from the
format's documented facts (docs/FORMAT.md "Exports", ../shared/reference/kubric_movi.md 2.1-2.4,
cotracker3.md 2.3, tapvid.md 2.1-2.3), compared with the scenes it came from; plus the faults
of item 5 of issue 26: a killed export resumed, foreign folders, missing layers, unknown formats.

The datasets are real `c4d datagen` output: one small dataset with every optional layer on
(non-square frames, so an axis swap shows) and one without normals and object coordinates.
"""

from __future__ import annotations

import json
import os
import pickle
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from c4d.cli import main
from c4d_core.geometry import quat_to_matrix
from c4d_core.pickles import read_data_pickle
from datagen import read_scenes
from dynpt.tapvid_data import read_tapvid

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}",
       "OMP_NUM_THREADS": "1", "PYOPENGL_PLATFORM": "egl"}
SIZE = (48, 64)  # H, W
FRAMES = 8
DATAGEN = ["--preset", "movi-e", "--resolution", "48x64", "--frames", str(FRAMES), "--workers", "1",
           "tracks.num_points=32", "objects.num_static=[2,3]", "objects.num_tossed=[1,2]"]
KUBRIC_LAYERS = ("rgba", "depth", "segmentation", "forward_flow", "backward_flow", "normal",
                 "object_coordinates")  # the per-frame files of Kubric's worker (reference 2.1)
# (bit depth, PNG colour type) of each PNG layer: 8-bit RGBA, 8-bit palette, 16-bit RGB; Kubric's
# read_png takes only 8- and 16-bit files
PNG_KINDS = {"rgba": (8, 6), "segmentation": (8, 3), "forward_flow": (16, 2),
             "backward_flow": (16, 2), "normal": (16, 2), "object_coordinates": (16, 2)}
# The GSO categories of Kubric's builders (movi_e.py's `category` ClassLabel, ../shared/reference/
# kubric_movi.md 2.2), and the GSO asset our plain shapes are written as (docs/FORMAT.md): its
# manifest keys as movi_e.py's asset table lists them and its scale_factor in movi_f.py's table
GSO_CATEGORIES = {"Action Figures", "Bag", "Board Games", "Bottles and Cans and Cups", "Camera",
                  "Car Seat", "Consumer Goods", "Hat", "Headphones", "Keyboard", "Legos",
                  "Media Cases", "Mouse", "None", "Shoe", "Stuffed Toys", "Toys"}
SHAPE_GSO = ("Closetmaid_Premium_Fabric_Cube_Red", 12158, "None", "Closetmaid Prem")
SHAPE_SCALE_FACTOR = 0.32167


@pytest.fixture(scope="module")
def full(tmp_path_factory) -> Path:
    """4 scenes in 2 shards with every optional layer."""
    out = tmp_path_factory.mktemp("export") / "full"
    assert main(["datagen", *DATAGEN, "--num-scenes", "4", "--scenes-per-shard", "2", "--seed", "4",
                 "--out", str(out), "layers.normal=true", "layers.object_coordinates=true",
                 "layers.events=true"]) == 0
    return out


@pytest.fixture(scope="module")
def plain(tmp_path_factory) -> Path:
    """1 scene without normals and object coordinates (another seed: another dataset)."""
    out = tmp_path_factory.mktemp("export") / "plain"
    assert main(["datagen", *DATAGEN, "--num-scenes", "1", "--seed", "9", "--out", str(out),
                 "layers.normal=false", "layers.object_coordinates=false"]) == 0
    return out


@pytest.fixture(scope="module")
def blurred(tmp_path_factory) -> Path:
    """1 scene of the movi-f preset (written for Kubric's movi_f.py)."""
    out = tmp_path_factory.mktemp("blurred") / "movi-f"  # not among the export* datasets below
    assert main(["datagen", *DATAGEN, "--preset", "movi-f", "--num-scenes", "1", "--seed", "4",
                 "--out", str(out), "layers.normal=true", "layers.object_coordinates=true",
                 "layers.events=true"]) == 0
    return out


@pytest.fixture(scope="module")
def scenes(full) -> dict[str, object]:
    return {f"{s.meta['scene_index']:08d}": s for s in read_scenes(full)}


def export(fmt: str, data: Path | str, out: Path, capsys=None) -> tuple[int, str]:
    """(exit code, stderr) of `c4d export fmt data out`, in this process."""
    code = main(["export", fmt, str(data), str(out)])
    return code, capsys.readouterr().err.strip() if capsys else ""


def files_of(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


# --- Kubric's worker layout ----------------------------------------------------------------------


def rgb_png(path: Path) -> np.ndarray:
    """An 8- or 16-bit PNG's channels in RGB(A) order."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    return image[..., [2, 1, 0, 3][:image.shape[-1]]]


def kubric_scene(folder: Path) -> dict:
    """A Kubric scene folder read as movi_e.py's `load_scene_directory` and the TFDS decoders do:
    16-bit values v decoded as v / 65535 * (max - min) + min (flow ranges from data_ranges.json),
    normals as v / 65535 * 2 - 1, object coordinates as v / 65535; segmentation as palette
    indices; depth as the float TIFF."""
    meta = json.loads((folder / "metadata.json").read_text())
    ranges = json.loads((folder / "data_ranges.json").read_text())
    t = meta["metadata"]["num_frames"]

    def frames(layer, read):
        return np.stack([read(folder / f"{layer}_{i:05d}.{'tiff' if layer == 'depth' else 'png'}")
                         for i in range(t)])

    def palette_indices(path):
        image = Image.open(path)
        assert image.mode == "P"
        return np.array(image)

    def flow(name):
        encoded = frames(name, rgb_png)
        assert encoded.dtype == np.uint16 and not encoded[..., 2].any()  # R, G = drow, dcol; B = 0
        low, high = ranges[name]["min"], ranges[name]["max"]
        return encoded[..., :2] / 65535 * (high - low) + low, (high - low) / 65535

    return {"meta": meta, "events": json.loads((folder / "events.json").read_text()),
            "rgba": frames("rgba", rgb_png), "segmentation": frames("segmentation", palette_indices),
            "depth": frames("depth", lambda p: np.array(Image.open(p))),
            "forward_flow": flow("forward_flow"), "backward_flow": flow("backward_flow"),
            "normal": frames("normal", rgb_png), "object_coordinates": frames("object_coordinates", rgb_png)}


def kubric_project(point, position, quaternion, k_normalised):
    """Kubric's camera.project_point: world point -> normalised image (u, v), Blender camera."""
    world = np.eye(4)
    world[:3, :3], world[:3, 3] = quat_to_matrix(np.asarray(quaternion)), position
    projected = np.asarray(k_normalised) @ (np.linalg.inv(world) @ np.append(point, 1.0))[:3]
    return projected[:2] / projected[2]


def test_kubric_export_is_kubric_s_worker_layout_of_our_scenes(full, scenes, tmp_path):
    out = tmp_path / "kubric"
    assert export("kubric", full, out)[0] == 0
    # OUT: the marker of c4d_core.ownership and scenes/, the data path of Kubric's builders, which
    # read every entry there as a scene folder (is_complete_dir) and sort them as integers (test)
    assert sorted(p.name for p in out.iterdir()) == [".c4d-output.json", "scenes"]
    entries = list((out / "scenes").iterdir())
    assert all(p.is_dir() for p in entries) and sorted(p.name for p in entries) == sorted(scenes)
    assert sorted(int(p.name) for p in entries) == sorted(int(name) for name in scenes)
    h, w = SIZE
    for name, s in scenes.items():
        folder = out / "scenes" / name
        names = [p.name for p in folder.iterdir()]
        # movi_e.py's is_complete_dir: the three JSON files, and as many frames of each layer as rgba
        assert {"data_ranges.json", "metadata.json", "events.json"} <= set(names)
        assert {layer: sum(n.startswith(layer + "_") for n in names) for layer in KUBRIC_LAYERS} \
            == dict.fromkeys(KUBRIC_LAYERS, s.num_frames)
        for layer, kind in PNG_KINDS.items():
            for t in range(s.num_frames):
                header = (folder / f"{layer}_{t:05d}.png").read_bytes()[:26]  # signature + IHDR
                assert (header[24], header[25]) == kind, (layer, t)
        k = kubric_scene(folder)
        meta = k["meta"]
        assert meta["metadata"]["resolution"] == [w, h] and meta["metadata"]["num_frames"] == s.num_frames
        # what movi_e.py serialises: the background's name, a string; no movi-f keys
        assert meta["metadata"]["background"] == "procedural" and "height" not in meta["metadata"]
        assert meta["flags"]["tfds_builder"] == "movi_e.py"
        assert np.array_equal(k["rgba"][..., :3], s.rgb) and (k["rgba"][..., 3] == 255).all()

        # depth: Euclidean distance from the camera centre, from our z-depth and K
        fx, fy, cx, cy = (s.intrinsics[:, i, j][:, None, None] for i, j in ((0, 0), (1, 1), (0, 2), (1, 2)))
        v, u = np.mgrid[0:h, 0:w]
        x, y = (u - cx) / fx * s.depth, (v - cy) / fy * s.depth
        assert k["depth"].dtype == np.float32
        np.testing.assert_allclose(k["depth"], np.sqrt(x ** 2 + y ** 2 + s.depth ** 2), rtol=1e-6)

        # flow: (drow, dcol); backward flow is the motion from t-1 to t (minus ours)
        for layer, want in (("forward_flow", s.flow_fwd[..., ::-1]), ("backward_flow", -s.flow_bwd[..., ::-1])):
            decoded, step = k[layer]
            error = want - decoded  # truncated: the stored value is at most one step below
            assert error.min() >= -1e-4 and error.max() <= step + 1e-4, layer
        assert np.abs(k["normal"] / 65535 * 2 - 1 - s.normal).max() <= 2 / 65535 + 1e-6
        assert np.abs(k["object_coordinates"] / 65535 - s.object_coordinates).max() <= 1 / 65535 + 1e-6

        # segmentation: 0 background, then the objects seen, most visible pixels first
        seg, ours = k["segmentation"], s.segmentation
        counts = np.bincount(ours.ravel(), minlength=len(s.objects) + 1)[1:]
        order = [int(i) for i in np.argsort(-counts, kind="stable") if counts[i] > 0]
        assert meta["metadata"]["num_instances"] == len(order) == len(meta["instances"])
        assert np.array_equal(seg == 0, ours == 0)
        for j, obj in enumerate(order):
            assert np.array_equal(seg == j + 1, ours == obj + 1)

        # camera: Blender axes, normalised K; projecting our world tracks gives our tracks
        cam = meta["camera"]
        kn = np.array(cam["K"])
        assert np.allclose([kn[0, 0] * w, -kn[0, 2] * w - 0.5, -kn[1, 1] * h, -kn[1, 2] * h - 0.5],
                           [s.intrinsics[0, 0, 0], s.intrinsics[0, 0, 2], s.intrinsics[0, 1, 1], s.intrinsics[0, 1, 2]])
        assert np.allclose(cam["positions"], s.cam_to_world[:, :3, 3], atol=1e-5)
        assert np.allclose(quat_to_matrix(np.array(cam["quaternions"])),
                           s.cam_to_world[:, :3, :3] @ np.diag([1, -1, -1]), atol=1e-5)
        assert np.isclose(cam["field_of_view"], 2 * np.arctan(cam["sensor_width"] / 2 / cam["focal_length"]))
        seen = np.argwhere(~s.occluded)
        for n, t in seen[:: max(1, len(seen) // 50)]:
            uv = kubric_project(s.tracks_world[n, t], cam["positions"][t], cam["quaternions"][t], kn)
            assert np.allclose(uv * [w, h] - 0.5, s.tracks[n, t], atol=1e-3)

        # instances, in segmentation order
        for j, (obj, inst) in enumerate(zip(order, meta["instances"])):
            assert inst["c4d_asset_id"] == s.objects[obj]["asset_id"]
            assert inst["scale"] == s.objects[obj]["scale"]
            # movi_e.py's asset_id_from_metadata: the GSO stand-in by its manifest keys
            assert inst["category"] in GSO_CATEGORIES and isinstance(inst["nr_faces"], int)
            if inst["c4d_asset_id"].startswith(("random_urdf/", "primitive/")):
                assert (inst["asset_id"], inst["nr_faces"], inst["category"],
                        inst["description"][:15]) == SHAPE_GSO
            assert inst["visibility"] == [int((seg[t] == j + 1).sum()) for t in range(s.num_frames)]
            frames = [t for t in range(s.num_frames) if (seg[t] == j + 1).any()]
            assert inst["bbox_frames"] == frames
            for t, box in zip(frames, inst["bboxes"]):  # post_processing.compute_bboxes
                rows, cols = np.nonzero(seg[t] == j + 1)
                assert np.allclose(box, [rows.min() / h, cols.min() / w, (rows.max() + 1) / h,
                                         (cols.max() + 1) / w])
            assert np.allclose(inst["bboxes_3d"], s.instances["bbox_3d"][obj])
            assert np.allclose(inst["positions"], s.object_to_world[obj, :, :3, 3], atol=1e-6)
            assert np.allclose(quat_to_matrix(np.array(inst["quaternions"])),
                               s.object_to_world[obj, :, :3, :3], atol=1e-5)
            assert np.allclose(inst["velocities"], s.instances["velocity"][obj])
            assert inst["is_dynamic"] == bool(s.instances["is_dynamic"][obj])
            for t in range(s.num_frames):
                uv = kubric_project(inst["positions"][t], cam["positions"][t], cam["quaternions"][t], kn)
                assert np.allclose(inst["image_positions"][t], uv, atol=1e-4)
        # collisions: instances as segmentation ids - 1, -1 for the floor and unseen objects;
        # frames from 1 at the first rendered frame
        assert len(k["events"]["collisions"]) == len(s.events["frame"]) > 0
        for e, theirs in enumerate(k["events"]["collisions"]):
            assert theirs["instances"] == [order.index(i) if i in order else -1
                                           for i in s.events["instances"][e]]
            assert np.isclose(theirs["frame"], s.events["frame"][e] + 1)
            assert np.allclose(theirs["image_position"],
                               (s.events["image_position"][e] + 0.5) / [w, h], atol=1e-6)
            for key in ("force", "position", "contact_normal"):  # the float32 values, exactly
                assert np.array_equal(np.float32(theirs[key]), s.events[key][e]), key


def test_a_movi_f_scene_is_written_in_movi_f_py_s_conventions(blurred, tmp_path):
    """movi_f.py reads `height` / `width`, `motion_blur`, multiplies the flow ranges by 512 and
    an instance's scale by its asset's scale_factor, and takes the category from its own table."""
    out = tmp_path / "kubric"
    assert export("kubric", blurred, out)[0] == 0
    scene = next(iter(read_scenes(blurred)))
    meta = json.loads((out / "scenes" / "00000000" / "metadata.json").read_text())
    ranges = json.loads((out / "scenes" / "00000000" / "data_ranges.json").read_text())
    h, w = SIZE
    assert meta["flags"]["tfds_builder"] == "movi_f.py"
    assert (meta["metadata"]["height"], meta["metadata"]["width"]) == (h, w)
    assert meta["metadata"]["motion_blur"] == scene.meta["motion_blur"] > 0
    for name, flow in (("forward_flow", scene.flow_fwd), ("backward_flow", -scene.flow_bwd)):
        assert np.isclose(ranges[name]["min"] * 512, flow.min(), rtol=1e-6)
        assert np.isclose(ranges[name]["max"] * 512, flow.max(), rtol=1e-6)
    counts = np.bincount(scene.segmentation.ravel(), minlength=len(scene.objects) + 1)[1:]
    order = [int(i) for i in np.argsort(-counts, kind="stable") if counts[i] > 0]
    shapes = 0
    for obj, inst in zip(order, meta["instances"], strict=True):
        ours = scene.objects[obj]
        assert inst["c4d_asset_id"] == ours["asset_id"]
        if ours["asset_id"].startswith(("random_urdf/", "primitive/")):
            assert inst["asset_id"] == SHAPE_GSO[0]
            assert np.isclose(inst["scale"] * SHAPE_SCALE_FACTOR, ours["scale"], rtol=1e-12)
            shapes += 1
    assert shapes > 0


# --- CoTracker's Kubric training layout ----------------------------------------------------------


def test_cotracker_export_is_what_its_kubric_loader_reads(full, scenes, tmp_path):
    out = tmp_path / "cotracker"
    assert export("cotracker", full, out)[0] == 0
    sequences = [p.name for p in out.iterdir() if p.is_dir()]  # the loader lists the sub-folders
    assert sorted(sequences) == sorted(scenes)
    for name in sequences:
        s = scenes[name]
        frames = sorted((out / name / "frames").iterdir())
        assert np.array_equal(np.stack([rgb_png(p) for p in frames]), s.rgb)
        record = np.load(out / name / f"{name}.npy", allow_pickle=True).item()
        assert set(record) == {"coords", "visibility", "moving"}
        n, t = s.tracks.shape[:2]
        assert record["coords"].shape == (n, t, 2) and record["coords"].dtype == np.float32
        assert np.array_equal(record["coords"], s.tracks)
        # the loader takes np.logical_not(visibility) as the visibility: the file holds occlusion
        assert np.array_equal(np.logical_not(record["visibility"]), ~s.occluded)
        assert record["moving"].dtype == bool and np.array_equal(record["moving"], s.moving)


# --- TAP-Vid pickle ------------------------------------------------------------------------------


def test_tapvid_export_is_a_davis_style_pickle_the_evaluation_reads(full, scenes, tmp_path):
    out = tmp_path / "val.pkl"
    assert export("tapvid", full, out)[0] == 0
    data = read_data_pickle(out, "TAP-Vid pickle", "")
    assert isinstance(data, dict) and sorted(data) == sorted(scenes)
    h, w = SIZE
    for name, s in scenes.items():
        entry = data[name]
        assert entry["video"].dtype == np.uint8 and np.array_equal(entry["video"], s.rgb)
        points = entry["points"]
        assert points.dtype == np.float32 and points.shape == s.tracks.shape
        seen = points[~s.occluded]  # occluded points may lie outside the frame
        assert ((seen >= 0) & (seen <= 1)).all()
        assert np.abs(points * [w, h] - 0.5 - s.tracks).max() < 1e-4  # raster, centres at +0.5
        assert entry["occluded"].dtype == bool and np.array_equal(entry["occluded"], s.occluded)
        assert np.array_equal(entry["moving"], s.moving)
    # the project's own TAP-Vid reader (c4d eval --data) gets our tracks back, time-major
    for item in read_tapvid(out, size=SIZE):
        s = scenes[item["name"]]
        assert np.array_equal(item["video"], s.rgb)
        assert np.abs(item["tracks"] - np.swapaxes(s.tracks, 0, 1)).max() < 1e-4
        assert np.array_equal(item["occluded"], np.swapaxes(s.occluded, 0, 1))


# --- item 5: determinism, resumption and refusals ------------------------------------------------


def test_a_killed_export_resumes_into_the_same_bytes(full, tmp_path):
    reference = tmp_path / "reference"
    assert export("kubric", full, reference)[0] == 0
    out = tmp_path / "killed"
    proc = subprocess.Popen([sys.executable, "-m", "c4d", "export", "kubric", str(full), str(out)],
                            env=ENV, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    first = out / "scenes" / "00000000"
    end = time.monotonic() + 120
    while not first.is_dir() and proc.poll() is None and time.monotonic() < end:
        time.sleep(0.002)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    done = sorted(p.name for p in first.parent.iterdir() if not p.name.endswith(".partial"))
    assert first.is_dir() and done != sorted(p.name for p in (reference / "scenes").iterdir()), \
        f"the export was not killed between scenes: {done}"
    inode = first.stat().st_ino
    code = main(["export", "kubric", str(full), str(out)])
    assert code == 0 and first.stat().st_ino == inode  # the finished scene was kept, not redone
    assert files_of(out) == files_of(reference)  # the rest completed, byte for byte
    assert not [p for p in out.rglob("*.partial")]  # nothing but scenes where the builders read


def test_a_kubric_export_in_the_old_layout_or_with_other_entries_is_refused(full, tmp_path, capsys):
    """OUT holds the marker and scenes/ only: scene folders of an earlier export in OUT itself
    are refused with how to move them; any other entry beside scenes/ is refused, naming it."""
    out = tmp_path / "kubric"
    assert export("kubric", full, out)[0] == 0
    old = tmp_path / "old"
    shutil.copytree(out, old)
    for scene in (old / "scenes").iterdir():
        scene.rename(old / scene.name)
    (old / "scenes").rmdir()
    capsys.readouterr()
    code, err = export("kubric", full, old, capsys)
    assert code == 2 and len(err.splitlines()) == 1, err
    assert "00000000 of an earlier kubric export" in err and f"{old / 'scenes'}" in err, err
    (out / "notes").mkdir()
    code, err = export("kubric", full, out, capsys)
    assert code == 2 and len(err.splitlines()) == 1 and "notes, which no kubric export" in err, err


def test_an_export_refuses_foreign_folders_missing_layers_and_unknown_formats(full, plain, tmp_path, capsys):
    def refused(fmt, data, out, *expected):
        capsys.readouterr()
        code, err = export(fmt, data, out, capsys)
        assert code == 2 and err.startswith("c4d: error: ") and len(err.splitlines()) == 1, err
        for text in expected:
            assert text in err, err

    refused("mp4", full, tmp_path / "a", "unknown export format 'mp4'", "kubric, cotracker, tapvid")
    refused("kubric", plain, tmp_path / "a", "normal, object_coordinates", "layers.normal=true",
            "layers.object_coordinates=true")
    assert not (tmp_path / "a").exists()  # nothing left behind
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "notes.txt").write_text("mine")
    refused("cotracker", full, tmp_path / "b", "holds files that c4d did not write", "notes.txt")
    assert [p.name for p in (tmp_path / "b").iterdir()] == ["notes.txt"]
    assert export("cotracker", full, tmp_path / "c")[0] == 0
    refused("kubric", full, tmp_path / "c", "a cotracker export")
    refused("cotracker", plain, tmp_path / "c", "not a cotracker export of this dataset", "seed 9")
    before = {p: p.stat().st_mtime_ns for p in (tmp_path / "c").rglob("*")}
    assert export("cotracker", full, tmp_path / "c")[0] == 0  # the same again: nothing to do
    assert {p: p.stat().st_mtime_ns for p in (tmp_path / "c").rglob("*")} == before
    both = f"{full.parent.parent}/export*/*/train-*.tar"  # the shards of both datasets
    refused("cotracker", both, tmp_path / "e", "mixes datasets", "seed 9")
    assert not (tmp_path / "e").exists()  # refused before the first scene
    (tmp_path / "d.pkl").write_bytes(pickle.dumps({}))
    refused("tapvid", full, tmp_path / "d.pkl", "already exists")
    refused("tapvid", full, tmp_path / "c", "is a folder")
