"""The fault suite, silent wrong results (issue 44 item 3): inputs that used to give a wrong or
empty output without a word now end in one line naming the real cause, or, where the input is
tolerable, in a one-line warning and the correct output.

- `c4d datagen` rerun with another seed or config after the dataset file was deleted: refused
  (the shards' scenes carry their seed and config digest), the old shards untouched;
- `c4d export tapvid` of tracks with NaN: those points left out, a scene without any skipped,
  each with a warning naming the scene; nothing usable: refused;
- `c4d view` of a scene with infinite depth: those points dropped with a warning counting them,
  the page holds the finite ones; none finite: refused; `--min-confidence nan`: refused;
- `c4d run --pointmaps RUN/last.pt` (a `c4d pretrain-pointmaps` training state): refused, naming
  the run's `pointmap_net.pth`;
- a copied demo or training folder continues from its own files; `c4d train --resume --config X`
  where X contradicts the saved config: refused;
- `c4d track --size 64 --max-size 32`: refused;
- options of `c4d view` / `c4d inspect` that do nothing for the input or output: refused;
- a key given twice in a YAML config: refused with the key and its line;
- `OMP_NUM_THREADS=abc`, `LOCAL_WORLD_SIZE=x`: one warning each, no OpenMP complaint.
"""

from __future__ import annotations

import dataclasses
import json
import pickle
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from c4d.cli import main
from c4d.view import scene_data
from c4d_core.config import load_config
from datagen.shards import ShardWriter, encode_scene, scene_key
from tests.dynpt_testdata import synthetic_scene, synthetic_shards
from tests.synthetic_scenes import make_box_scene
from tests.test_faults import (ENV, ROOT, TINY_DATAGEN, TRAIN, assert_one_line_error, inputs,  # noqa: F401
                               sha)
from tests.test_faults_training import POINTMAPS
from tests.test_inspect_recon import write_reconstruction
from tests.test_view import _decode

pytestmark = pytest.mark.faults


def write_shard(folder: Path, scenes: list) -> Path:
    """`scenes` as the shard `folder/train-000000.tar`, keys train-00000000, ...; returns folder."""
    folder.mkdir(parents=True, exist_ok=True)
    with ShardWriter(folder / "train-000000.tar") as writer:
        for index, scene in enumerate(scenes):
            writer.write(encode_scene(scene, scene_key("train", index)))
    return folder


# --- 1. datagen: shards of another generation -----------------------------------------------------


def test_datagen_rerun_after_the_dataset_file_was_deleted_refuses_other_settings(tmp_path, capsys):
    out = tmp_path / "data"
    tiny = [a for a in TINY_DATAGEN if a not in ("--seed", "5")]

    def datagen(*extra: str) -> int:
        return main(["datagen", "--num-scenes", "2", "--scenes-per-shard", "1", "--out", str(out),
                     "--workers", "1", *tiny, *extra])

    assert datagen("--seed", "5") == 0
    shards = {p.name: sha(p) for p in out.glob("*.tar")}
    (out / "dataset-train.json").unlink()
    assert_one_line_error(datagen("--seed", "6"), capsys.readouterr().err, "train-000000.tar",
                          "generated with seed 5 (this run: seed 6)", "dataset-train.json is missing",
                          "new --out")
    assert_one_line_error(datagen("--seed", "5", "camera.focal_mm=50"), capsys.readouterr().err,
                          "with another config (config_digest")
    assert {p.name: sha(p) for p in out.glob("*.tar")} == shards
    assert datagen("--seed", "5") == 0  # the shards' own settings: resumed, nothing regenerated
    assert json.loads((out / "dataset-train.json").read_text())["seed"] == 5
    assert {p.name: sha(p) for p in out.glob("*.tar")} == shards


# --- 2. export tapvid: tracks without a finite position -------------------------------------------


def nan_tracks(index: int, rows) -> object:
    """Synthetic scene `index` (20 tracks of 10 frames) with the track rows `rows` set to NaN."""
    scene = synthetic_scene(index)
    tracks = scene.tracks.copy()
    tracks[rows] = np.nan
    return dataclasses.replace(scene, tracks=tracks)


def test_tapvid_export_leaves_out_nan_tracks_and_refuses_when_none_is_left(tmp_path, capsys, caplog):
    data = write_shard(tmp_path / "data", [nan_tracks(0, slice(None)), nan_tracks(1, [3, 7]),
                                           nan_tracks(2, [])])
    out = tmp_path / "val.pkl"
    assert main(["export", "tapvid", str(data), str(out)]) == 0
    videos = pickle.loads(out.read_bytes())
    assert sorted(videos) == ["00000001", "00000002"]
    assert videos["00000001"]["points"].shape == (18, 10, 2)
    assert videos["00000001"]["occluded"].shape == videos["00000001"]["moving"].shape == (18, 10)
    assert all(np.isfinite(v["points"]).all() for v in videos.values())
    assert "scene 00000000 has 20 of 20 tracks with non-finite" in caplog.text
    assert "the scene is skipped" in caplog.text
    assert "scene 00000001 has 2 of 20 tracks with non-finite (NaN/inf) coordinates, left out; " \
           "18 kept" in caplog.text
    empty = write_shard(tmp_path / "empty", [nan_tracks(i, slice(None)) for i in range(2)])
    code = main(["export", "tapvid", str(empty), str(tmp_path / "empty.pkl")])
    assert_one_line_error(code, capsys.readouterr().err, "no scene has a track with finite coordinates")
    assert not (tmp_path / "empty.pkl").exists()


# --- 3, 8, 9. view and inspect --------------------------------------------------------------------


@pytest.fixture(scope="module")
def box():
    return make_box_scene(num_frames=4, height=48, width=64, num_tracks=16, seed=3)


@pytest.fixture(scope="module")
def box_data(tmp_path_factory, box) -> Path:
    return write_shard(tmp_path_factory.mktemp("box") / "data", [box])


@pytest.fixture(scope="module")
def recon(tmp_path_factory, box) -> Path:
    return write_reconstruction(box, tmp_path_factory.mktemp("box-recon") / "recon")


def test_view_of_infinite_depth_draws_the_finite_points_or_refuses(tmp_path, capsys, caplog, box):
    depth = box.depth.copy()
    depth[:, :16] = np.inf  # the top third of every frame
    data = write_shard(tmp_path / "inf", [dataclasses.replace(box, depth=depth)])
    page = tmp_path / "view.html"
    assert main(["view", str(data), "--save", str(page)]) == 0
    header, _ = _decode(page.read_text())
    drawn = sum(header["points"]["static"]) + sum(header["points"]["dynamic"])
    finite = (depth > 0) & np.isfinite(depth)
    expected = sum(len(scene_data.frame_selection(keep, scene_data.DEFAULT_STRIDE,
                                                  scene_data.DEFAULT_MAX_POINTS)) for keep in finite)
    assert drawn == expected > 0
    assert (f"{np.isinf(depth).sum()} of {(depth > 0).sum()} points have an infinite or NaN "
            "position and are not drawn") in caplog.text
    depth[:] = np.inf
    data = write_shard(tmp_path / "all-inf", [dataclasses.replace(box, depth=depth)])
    code = main(["view", str(data), "--save", str(tmp_path / "none.html")])
    assert_one_line_error(code, capsys.readouterr().err,
                          f"none of its {depth.size} points has a finite position")
    assert not (tmp_path / "none.html").exists()


def test_view_refuses_a_non_finite_or_unreachable_min_confidence(tmp_path, capsys, recon):
    page = tmp_path / "view.html"
    for value in ("nan", "inf"):
        code = main(["view", str(recon), "--min-confidence", value, "--save", str(page)])
        assert_one_line_error(code, capsys.readouterr().err,
                              f"--min-confidence must be a finite number, got {value}")
    code = main(["view", str(recon), "--min-confidence", "5", "--save", str(page)])
    assert_one_line_error(code, capsys.readouterr().err, "has confidence >= 5 (the highest is 1)",
                          "give a lower --min-confidence")
    assert not page.exists()


UNUSED = [  # (command, source, arguments, what the line says)
    ("view", "recon", ["--scene", "0"], "--scene is only for shard sets, and"),
    ("view", "data", ["--min-confidence", "2"], "--min-confidence is only for reconstructions"),
    ("view", "recon", ["--scene-index", "0"], "--scene-index is only for --gt DATA"),
    ("view", "recon", ["--frame", "1"], "--frame is only for --screenshot FILE.png"),
    ("view", "recon", ["--size", "640x400"], "--size is only for --screenshot FILE.png"),
    ("view", "recon", ["--port", "0"], "--port is only for serving the page"),
    ("view", "recon", ["--no-browser"], "--no-browser is only for serving the page"),
    ("inspect", "data", ["--gt", "{data}"], "--gt is only for reconstructions"),
    ("inspect", "data", ["--compare", "GA={recon}"], "--compare is only for reconstructions"),
    ("inspect", "recon", ["--scene", "0"], "--scene is only for shard sets"),
    ("inspect", "recon", ["--split", "train"], "--split is only for shard sets"),
    ("inspect", "recon", ["--num-samples", "1"], "--num-samples is only for shard sets"),
    ("inspect", "recon", ["--scene-index", "0"], "--scene-index is only for --gt DATA"),
    ("inspect", "data", ["--check", "--scene", "0"], "--scene is only for a report (--check"),
    ("inspect", "recon", ["--check", "--gt", "{data}"], "--gt is only for a report (--out DIR)"),
]


@pytest.mark.parametrize("name, source, extra, line", UNUSED,
                         ids=[f"{c[0]}-{c[1]}{c[2][0]}" for c in UNUSED])
def test_an_option_that_does_nothing_here_is_one_line(tmp_path, capsys, box_data, recon, name,
                                                      source, extra, line):
    paths = {"data": str(box_data), "recon": str(recon)}
    extra = [a.format(**paths) for a in extra]
    out = tmp_path / ("view.html" if name == "view" else "report")
    target = [] if "--check" in extra else ["--save" if name == "view" else "--out", str(out)]
    code = main([name, paths[source], *extra, *target])
    assert_one_line_error(code, capsys.readouterr().err, line, "drop it")
    assert not out.exists()


# --- 4. a pointmap training state as the network ---------------------------------------------------


def test_run_refuses_a_pointmap_training_state_and_names_the_network_file(tmp_path, capsys, inputs):
    scenes = [dataclasses.replace(synthetic_scene(i), depth=np.full((10, 32, 32), 2.0 + i, np.float32))
              for i in range(2)]
    shards = write_shard(tmp_path / "depth", scenes)
    run = tmp_path / "pretrain"
    pretrain = ["pretrain-pointmaps", *POINTMAPS, f"data.sources=[{shards}]", f"train.out_dir={run}",
                "train.steps=2"]
    assert main([*pretrain, "train.stop_after=1"]) == 0
    recon = ["run", str(inputs["video"]), "--pointmaps", str(run / "last.pt"), "--out",
             str(tmp_path / "recon"), "--size", "32"]
    assert_one_line_error(main(recon), capsys.readouterr().err,
                          f"{run / 'last.pt'} is a training state of `c4d pretrain-pointmaps`",
                          "has not finished", "--resume")
    assert main([*pretrain, "--resume"]) == 0
    assert_one_line_error(main(recon), capsys.readouterr().err,
                          f"pass {run / 'pointmap_net.pth'}, the network that run wrote")
    assert not (tmp_path / "recon").exists()


# --- 5, 6. moved folders, --resume --config --------------------------------------------------------


def test_a_copied_demo_folder_reads_its_own_step_records(tmp_path, monkeypatch):
    from c4d.demo import Demo

    cfg = load_config("demo", "quick")
    monkeypatch.chdir(tmp_path)
    original = Demo(cfg, Path("demo_out"))  # relative to the working directory, as users give it

    def train(folder: Path) -> dict:
        checkpoint = folder / "checkpoints" / "step_00000001.pt"
        checkpoint.parent.mkdir()
        checkpoint.write_bytes(b"weights")
        return {"checkpoint": original.stored(checkpoint)}

    assert original.run_step("train", train)["checkpoint"] == "train/checkpoints/step_00000001.pt"
    shutil.copytree("demo_out", "copy")
    copy = Demo(cfg, tmp_path / "copy")
    record = copy.run_step("train", lambda folder: pytest.fail("a finished step ran again"))
    own = tmp_path / "copy" / "train" / "checkpoints" / "step_00000001.pt"
    assert copy.located(record["checkpoint"]) == own
    # records of older runs: relative to the directory the demo ran in, or absolute
    for old in ("demo_out/train/checkpoints/step_00000001.pt",
                str(tmp_path / "demo_out" / "train" / "checkpoints" / "step_00000001.pt")):
        assert copy.located(old) == own


def test_a_copied_training_run_resumes_in_itself_and_a_contradicting_config_is_refused(tmp_path, capsys):
    first, copy = tmp_path / "first", tmp_path / "copy"
    assert main(["train", *TRAIN, f"data.sources=[{synthetic_shards(12, 3)}]",
                 f"train.out_dir={first}", "train.steps=4", "train.ckpt_every=2",
                 "train.stop_after=2"]) == 0
    shutil.copytree(first, copy)
    elsewhere = tmp_path / "copy.yaml"  # a config naming the copy; the saved one names `first`
    elsewhere.write_text(f"train:\n  out_dir: {copy}\n")
    assert main(["train", "--config", str(elsewhere), "--resume", "train.stop_after=0"]) == 0
    assert sorted(p.name for p in (copy / "checkpoints").glob("step_*")) == [
        "step_00000002.pt", "step_00000004.pt"]
    assert sorted(p.name for p in (first / "checkpoints").glob("step_*")) == ["step_00000002.pt"]
    other = tmp_path / "lr.yaml"
    other.write_text("train:\n  lr: 0.5\n")
    code = main(["train", "--config", str(other), "--resume", f"train.out_dir={first}"])
    assert_one_line_error(code, capsys.readouterr().err, f"--config {other} contradicts in train.lr",
                          "drop --config")


# --- 7. track ------------------------------------------------------------------------------------


def test_track_refuses_a_size_above_its_max_size(tmp_path, capsys, inputs):
    out = tmp_path / "tracks"
    code = main(["track", str(inputs["video"]), "--ckpt", str(inputs["ckpt"]), "--out", str(out),
                 "--size", "64", "--max-size", "32"])
    assert_one_line_error(code, capsys.readouterr().err, "--size 64 is larger than --max-size 32",
                          "give one of them")
    assert not out.exists()


# --- 10, 11. config files and thread variables -----------------------------------------------------


def test_a_key_given_twice_in_a_yaml_config_is_one_line(tmp_path, capsys):
    config = tmp_path / "twice.yaml"
    config.write_text("train:\n  lr: 0.001\n  steps: 3\n  lr: 0.002\n")
    code = main(["config", "show", "dynpt/tiny-cpu", "--config", str(config)])
    assert_one_line_error(code, capsys.readouterr().err, config.name, "at line 4",
                          "the key 'lr' is given twice in one mapping (also on line 2); keep one")
    code = main(["train", "--config", str(config), f"train.out_dir={tmp_path / 'run'}"])
    assert_one_line_error(code, capsys.readouterr().err, "the key 'lr' is given twice")
    assert not (tmp_path / "run").exists()
    code = main(["config", "show", "dynpt/tiny-cpu", "train.lr_scale={cnn: 1, cnn: 0}"])
    assert_one_line_error(code, capsys.readouterr().err, "the key 'cnn' is given twice")


@pytest.mark.parametrize("value", ["abc", "0"])
def test_thread_variables_that_are_not_counts_are_one_warning_each(tmp_path, inputs, value):
    env = {**ENV, "OMP_NUM_THREADS": value, "LOCAL_WORLD_SIZE": "x"}
    run = subprocess.run([sys.executable, "-m", "c4d", "track", str(inputs["video"]), "--ckpt",
                          str(inputs["ckpt"]), "--out", str(tmp_path / "t")],
                         env=env, cwd=ROOT, capture_output=True, text=True, timeout=240)
    assert run.returncode == 0, run.stderr[-2000:]
    warned = [line for line in run.stderr.splitlines() if "is not a positive integer" in line]
    assert warned == [f"OMP_NUM_THREADS={value!r} is not a positive integer; ignored, using "
                      "threads from the usable cores (--threads N chooses them)",
                      "LOCAL_WORLD_SIZE='x' is not a positive integer; ignored, using 1 process "
                      "on this machine"], run.stderr[-2000:]
    assert "libgomp" not in run.stderr and "Traceback" not in run.stderr
    assert (tmp_path / "t" / "tracks.npz").is_file()
