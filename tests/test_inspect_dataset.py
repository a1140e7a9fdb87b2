"""`c4d inspect` on shard sets: statistics, pictures, detail mode and `--check`."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from c4d.cli import main
from c4d.inspect import dataset_check, dataset_report
from c4d_core.config import load_config
from c4d_core.video import read_video
from tests.synthetic_scenes import make_box_scene
from datagen import shards

T, H, W, N = 8, 48, 64, 48
CFG = load_config("inspect", "default")


def _scene(seed: int):
    return make_box_scene(num_frames=T, height=H, width=W, num_tracks=N, seed=seed)


def _write_shard(path: Path, scenes: dict[str, object]) -> Path:
    with shards.ShardWriter(path) as writer:
        for key, scene in scenes.items():
            writer.write(shards.encode_scene(scene, key))
    return path


@pytest.fixture(scope="module")
def shard_dir(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("shards")
    _write_shard(folder / "train-000000.tar", {"train-00000000": _scene(0), "train-00000001": _scene(1)})
    _write_shard(folder / "train-000001.tar", {"train-00000002": _scene(2)})
    return folder


def _not_blank(image: np.ndarray) -> bool:
    return image.std() > 5 and len(np.unique(image.reshape(-1, image.shape[-1]), axis=0)) > 10


def test_report_counts_plots_and_sample_pictures(shard_dir, tmp_path):
    out = tmp_path / "report"
    assert main(["inspect", str(shard_dir), "--out", str(out), "--num-samples", "2", "--no-progress"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["counts"] == {"scenes": 3, "frames": 3 * T, "objects": 9, "tracks": 3 * N, "unreadable": 0}
    stats = summary["statistics"]
    assert stats["visible_fraction_per_track"]["count"] == 3 * N
    assert stats["moving_fraction_per_frame"]["count"] == 3 * T
    assert 0 < stats["moving_fraction_per_track"]["mean"] < 1
    assert stats["camera_speed"]["min"] > 0

    plot = np.asarray(Image.open(out / "distributions.png").convert("RGB"))
    assert plot.shape == (600, 1600, 3) and _not_blank(plot)
    assert sorted(p.name for p in (out / "scenes").iterdir()) == ["train-00000000", "train-00000001"]
    sheet = np.asarray(Image.open(out / "scenes/train-00000000/sheet.png"))
    panel_h, panel_w = 4 * H, 4 * W  # 48-pixel scenes are shown 4x larger
    keys = 26  # the colour-key strip under the panels (tracks, depth bar, flow wheel)
    assert sheet.shape == (4 * panel_h + 3 * 2 + keys, 4 * panel_w + 3 * 2, 3) and _not_blank(sheet)
    video = read_video(out / "scenes/train-00000000/video.webm")
    assert video.shape == (T, panel_h + keys, 4 * panel_w + 3 * 2, 3) and _not_blank(video[0])
    page = (out / "index.html").read_text()
    assert "distributions.png" in page and "scenes/train-00000001/video.webm" in page


def test_tracks_are_drawn_by_mobility_in_the_sample_video(shard_dir):
    scene = next(iter(dataset_check.iter_dataset(shard_dir))).scene
    panels, labels = dataset_report.scene_panels(scene, CFG)
    assert labels == ["rgb + tracks", "depth", "segmentation", "flow_fwd"]
    n, t = np.argwhere(scene.moving & ~scene.occluded)[0]  # a visible moving point
    x, y = np.round((scene.tracks[n, t] + 0.5) * 4 - 0.5).astype(int)
    np.testing.assert_array_equal(panels[0][t, y, x], (255, 50, 40))


def test_scene_detail_mode(shard_dir, tmp_path):
    out = tmp_path / "scene"
    assert main(["inspect", str(shard_dir), "--out", str(out), "--scene", "2"]) == 0
    for name in ("index.html", "sheet.png", "all_frames.png", "tracks.png", "video.webm"):
        assert (out / name).is_file(), name
    assert "train-00000002" in (out / "index.html").read_text()
    every = np.asarray(Image.open(out / "all_frames.png"))
    assert every.shape[0] == T * 4 * H + (T - 1) * 2 + 26  # + the colour keys
    assert main(["inspect", str(shard_dir), "--out", str(out), "--scene", "3"]) == 2


def test_validate_scene_finds_each_kind_of_problem():
    scene = _scene(0)
    assert dataset_check.validate_scene(scene, CFG) == []
    bad = dataclasses.replace(
        scene,
        depth=scene.depth[:, :, :-1],
        segmentation=np.where(scene.segmentation == 1, 7, scene.segmentation).astype(np.int32),
        tracks=np.where(np.arange(N)[:, None, None] == 0, np.nan, scene.tracks).astype(np.float32),
        moving=~scene.moving,
        occluded=scene.occluded.copy(),
    )
    bad.occluded[0, bad.query_frame[0]] = True
    problems = " | ".join(dataset_check.validate_scene(bad, CFG))
    for expected in ("depth is float32 (8, 48, 63), expected float32 (8, 48, 64)",
                     "segmentation ids span [0, 7], outside [0, 3]",
                     "tracks has 16 NaN",
                     "1 tracks are occluded at their query frame",
                     f"moving disagrees with displacement > 0.01 at {N * T} points"):
        assert expected in problems


def test_check_reports_every_bad_scene_and_shard_without_stopping(shard_dir, tmp_path):
    folder = tmp_path / "mixed"
    folder.mkdir()
    for shard in shard_dir.iterdir():
        (folder / shard.name).write_bytes(shard.read_bytes())
    good = _scene(3)
    wrong_depth = dataclasses.replace(good, depth=good.depth[:, :-2])
    occluded = good.occluded.copy()
    occluded[5, good.query_frame[5]] = True
    no_depth = dataclasses.replace(good, depth=None, meta={**good.meta, "generator": "datagen"})
    _write_shard(folder / "train-000002.tar", {"train-00000010": wrong_depth,
                                               "train-00000011": dataclasses.replace(good, occluded=occluded),
                                               "train-00000012": good,
                                               "train-00000013": no_depth})
    truncated = (folder / "train-000000.tar").read_bytes()
    (folder / "train-000000.tar").write_bytes(truncated[: int(len(truncated) * 0.7)])

    result = dataset_check.check_dataset(folder, CFG, progress=False)
    by_key = {}
    for shard, key, problem in result.problems:
        by_key.setdefault(key, []).append((Path(shard).name, problem))
    assert by_key["train-00000010"][0][0] == "train-000002.tar"
    assert "depth is float32 (8, 46, 64)" in by_key["train-00000010"][0][1]
    assert "1 tracks are occluded at their query frame" in by_key["train-00000011"][0][1]
    assert "required fields are missing (truncated sample?): depth" in by_key["train-00000013"][0][1]
    truncation = [p for key, items in by_key.items() for name, p in items if name == "train-000000.tar"]
    assert truncation and "truncated" in truncation[0]
    assert "train-00000012" not in by_key and "train-00000002" not in by_key
    assert result.num_samples >= 6  # shard 0's readable scene, shard 1, and all of shard 2

    out = tmp_path / "check"
    assert main(["inspect", str(folder), "--check", "--out", str(out), "--no-progress"]) == 1
    written = json.loads((out / "check.json").read_text())
    assert {p["key"] for p in written["problems"]} >= {"train-00000010", "train-00000011"}
    assert main(["inspect", str(shard_dir), "--check", "--no-progress"]) == 0


def test_user_mistakes_are_one_line_errors(tmp_path, capsys):
    assert main(["inspect", str(tmp_path / "nothing"), "--out", str(tmp_path / "o")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["inspect", str(tmp_path), "--check"]) == 2
    assert "no shards" in capsys.readouterr().err
    assert main(["inspect", str(tmp_path), "sampels=2", "--check"]) == 2
    assert "sampels" in capsys.readouterr().err


def test_real_datagen_shards_pass_the_check_and_report(tmp_path):
    shard_dir = tmp_path / "movi"
    assert main(["datagen", "--preset", "movi-e", "--num-scenes", "1", "--out", str(shard_dir),
                 "--resolution", "32", "--frames", "4"]) == 0
    assert main(["inspect", str(shard_dir), "--check", "--no-progress"]) == 0
    out = tmp_path / "report"
    assert main(["inspect", str(shard_dir), "--out", str(out), "--num-samples", "1", "--no-progress"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["presets"] == {"movi-e": 1} and summary["counts"]["frames"] == 4
    blur = summary["statistics"]["blur_shutter"]
    assert blur["count"] == 1 and blur["max"] == 0.0, "movi-e is sharp"
    assert summary["statistics"]["objects_per_scene"]["min"] >= 10


def test_optional_layers_are_drawn_and_checked(tmp_path):
    """A real scene with every optional layer: the sheet shows normals and object coordinates
    and the 2-D boxes on the RGB; `--check` passes it and names each layer broken on purpose."""
    shard_dir = tmp_path / "layers"
    assert main(["datagen", "--preset", "movi-e", "--num-scenes", "1", "--out", str(shard_dir),
                 "--resolution", "48", "--frames", "4", "layers.normal=true",
                 "layers.object_coordinates=true", "layers.events=true"]) == 0
    assert main(["inspect", str(shard_dir), "--check", "--no-progress"]) == 0
    scene = next(iter(dataset_check.iter_dataset(shard_dir))).scene
    panels, labels = dataset_report.scene_panels(scene, CFG)
    assert labels == ["rgb + tracks + boxes", "depth", "segmentation", "flow_fwd", "normal",
                      "object_coordinates"]
    factor = 4  # 48-pixel scenes are shown 4x larger
    background = np.repeat(np.repeat(scene.segmentation == 0, factor, 1), factor, 2)  # (T,H',W')
    assert not panels[5][background].any()  # object coordinates: black on the backdrop
    floor = background & (np.abs(np.repeat(np.repeat(scene.normal[..., 2], factor, 1), factor, 2)
                                 - 1) < 1e-4)
    assert floor.sum() > 100 and (panels[4][floor] == (128, 128, 255)).all()  # +z: light blue
    # An object's box outline in its segmentation colour, on a frame where it is visible.
    k, t = np.argwhere(scene.instances["visible_pixels"] > 20)[0]
    ymin, xmin, ymax, xmax = scene.instances["bbox_2d"][k, t]
    colour = dataset_report.draw.segment_palette(len(scene.objects) + 1)[k + 1]
    top = panels[0][t, int(round(ymin * 4 * 48)), int(round(xmin * 4 * 48)):int(round(xmax * 4 * 48))]
    assert (top == colour).all(-1).mean() > 0.5  # tracks may be drawn over parts of it

    bad_instances = {**scene.instances, "bbox_2d": scene.instances["bbox_2d"] + 0.01,
                     "visible_pixels": scene.instances["visible_pixels"] + 1}
    coordinates = scene.object_coordinates.copy()
    coordinates[scene.segmentation == 0] = 0.5
    events = {**scene.events, "instances": scene.events["instances"].copy()}
    events["instances"][0] = [99, -1]
    bad = dataclasses.replace(scene, normal=scene.normal * 1.01, object_coordinates=coordinates,
                              instances=bad_instances, events=events)
    problems = " | ".join(dataset_check.validate_scene(bad, CFG))
    for expected in ("normal is not of unit length", "object_coordinates are not 0 on",
                     "instances['visible_pixels'] disagree with the segmentation",
                     "instances['bbox_2d'] disagree", "events name instances outside"):
        assert expected in problems, expected
    listed = dataclasses.replace(scene, events=[{"frame": 0.0}])  # a list of dicts, not arrays
    assert dataset_check.validate_scene(listed, CFG) == ["events must be a dict of arrays, got list"]
    short = dataclasses.replace(scene, events={**scene.events, "force": scene.events["force"][1:]})
    assert "events['force'] must be float32" in " | ".join(dataset_check.validate_scene(short, CFG))
    missing = dataclasses.replace(scene, events=None)
    assert "required fields are missing (truncated sample?): events" in \
        dataset_check.validate_scene(missing, CFG)[0]
