"""The fault suite, unclear messages: each names the real cause, never an innocent input.

Cases (issue 44, item 3): a truncated dataset file (not its good shards as foreign); a pickle, an
image or random bytes given as a shard set, a video or a checkpoint (named for what they are, not
called corrupt); frames smaller than one patch of the pointmap network; key=value overrides put
before the video; a non-positive `--max-depth` (and one beyond every depth); a demo record naming
a file no longer in its folder; a float TAP-Vid video; a browser that exits at once; a refused
but intact CoTracker3 file; a reconstruction of a scene written as an .mp4 (scored, the codec's
loss not taken for another scene, while another scene is still refused).
"""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import cv2
import numpy as np
import pytest

from c4d.cli import main
from c4d_core.config import load_config
from c4d_core.errors import UserError
from c4d_core.video import write_image, write_video
from c4d_pipeline.outputs import read_reconstruction
from datagen.shards import read_scenes
from tests.dynpt_testdata import generated_shards
from tests.test_faults import (TINY_DATAGEN, TRAIN, assert_one_line_error, command,  # noqa: F401
                               inputs)  # (module fixture)

pytestmark = pytest.mark.faults


def test_a_damaged_dataset_file_is_named_not_its_shards(tmp_path, capsys):
    out = tmp_path / "data"
    datagen = ["datagen", "--num-scenes", "2", "--scenes-per-shard", "1", "--out", str(out),
               "--workers", "1", *TINY_DATAGEN]
    assert main(datagen) == 0
    record = out / "dataset-train.json"
    whole = record.read_bytes()
    record.write_bytes(whole[:len(whole) // 2])
    for argv in (["inspect", str(out), "--check", "--no-progress"],
                 ["train", *TRAIN, f"data.sources=[{out}]", f"train.out_dir={tmp_path / 'run'}",
                  "train.steps=3"]):
        line = assert_one_line_error(main(argv), capsys.readouterr().err, str(record), "damaged",
                                     "not valid JSON", "rerun the same `c4d datagen` command")
        assert "train-000000.tar" not in line and "move it out" not in line
    # the advice holds: without it, the same command rewrites the file and keeps the shards
    shards = {p.name: p.stat().st_mtime_ns for p in out.glob("*.tar")}
    record.unlink()
    assert main(datagen) == 0
    assert record.read_bytes() == whole
    assert {p.name: p.stat().st_mtime_ns for p in out.glob("*.tar")} == shards


def test_a_file_of_another_kind_is_named_for_what_it_is(tmp_path, capsys, inputs):
    pickled = tmp_path / "points.pkl"
    pickled.write_bytes(pickle.dumps({"points": np.zeros((2, 3))}))
    noise = tmp_path / "noise"
    noise.write_bytes(np.random.default_rng(0).integers(0, 256, 4000, np.uint8).tobytes())
    image = write_image(tmp_path / "frame.png", np.zeros((8, 8, 3), np.uint8))

    line = assert_one_line_error(main(["export", "kubric", str(pickled), str(tmp_path / "k")]),
                                 capsys.readouterr().err, str(pickled), "is not a shard",
                                 "it is a Python pickle", "give a `c4d datagen` folder")
    assert "corrupt" not in line and "delete" not in line
    for source, kind in ((pickled, "a Python pickle"), (noise, "a file of no format c4d knows"),
                         (inputs["video"], "an AVI video")):
        line = assert_one_line_error(main(["view", str(source), "--save", str(tmp_path / "v.html")]),
                                     capsys.readouterr().err, str(source), "neither a reconstruction",
                                     f"it is {kind}", "`c4d run`", "`c4d datagen`")
        assert "corrupt" not in line and "delete" not in line
    # the same for a video and a checkpoint: what the file is, not "corrupt or truncated"
    code = main(command("run", tmp_path / "recon", {**inputs, "video": pickled}))
    assert_one_line_error(code, capsys.readouterr().err, "is not a video: it is a Python pickle")
    code = main(["track", str(inputs["video"]), "--ckpt", str(image), "--out", str(tmp_path / "t")])
    line = assert_one_line_error(code, capsys.readouterr().err, "it is a PNG image, not a PyTorch file")
    assert "truncated" not in line


def test_frames_smaller_than_a_patch_are_refused_by_run(tmp_path, capsys, inputs):
    frames = tmp_path / "dots"
    frames.mkdir()
    for t in range(3):
        write_image(frames / f"{t:03d}.png", np.full((1, 1, 3), 80 * t, np.uint8))
    out = tmp_path / "recon"
    line = assert_one_line_error(main(command("run", out, {**inputs, "video": frames})),
                                 capsys.readouterr().err, "1x1 pixels", "16-pixel patch",
                                 "at least 16x16")
    assert "diverged" not in line and not (out / "report.json").exists()


def test_overrides_before_the_video_are_named_as_such(tmp_path, capsys, inputs):
    _, video, *rest = command("run", tmp_path / "recon", inputs)
    line = assert_one_line_error(main(["run", "device=cpu", video, *rest]), capsys.readouterr().err,
                                 "the override 'device=cpu' stands before VIDEO", repr(video),
                                 "give VIDEO first and the overrides after it")
    assert "does not exist" not in line and "not of the form key=value" not in line
    line = assert_one_line_error(main(["run", "device=cpu", *rest]), capsys.readouterr().err,
                                 "VIDEO is missing: 'device=cpu' in its place is a key=value override")
    assert "does not exist" not in line
    code = main(["inspect", "samples=1", str(inputs["shards"]), "--check", "--no-progress"])
    assert_one_line_error(code, capsys.readouterr().err, "'samples=1' stands before SOURCE")


@pytest.fixture(scope="module")
def mp4_reconstruction(tmp_path_factory, inputs):
    """Scene 1 of a generated dataset written as an .mp4 (MPEG-4 part 2, lossy), its first 4 frames
    reconstructed at the pointmap network's size 512: (the reconstruction folder, the shard set,
    the scene)."""
    shards = generated_shards()
    scene = list(read_scenes(shards))[1]
    folder = tmp_path_factory.mktemp("mp4-recon")
    video = write_video(folder / "scene1.mp4", scene.rgb, 12)
    out = folder / "recon"
    assert main(["run", str(video), "--pointmaps", str(inputs["net"]), "--out", str(out),
                 "--size", "512", "video.max_frames=4", "graph.window=2", "optim.stage1_iters=2",
                 "optim.stage2_iters=1", "pts.window=4", "pts.extend=1"]) == 0
    return out, shards, scene


def test_an_mp4_of_the_scene_is_scored_and_another_scene_still_refused(tmp_path, capsys,
                                                                       mp4_reconstruction):
    out, shards, scene = mp4_reconstruction
    # the former measure, the mean difference to the scene's frames resized and cropped as the
    # reconstruction's input was, is over its limit of 8 (of 255): the codec's loss and resampling
    recon = read_reconstruction(out)
    used = recon.report["inputs"]
    (x, y), (rh, rw), h, w = used["crop_xy"], used["resized_hw"], *recon.frames.shape[1:3]
    truth = np.stack([cv2.resize(f, (rw, rh), interpolation=cv2.INTER_AREA)
                      for f in scene.rgb[used["frame_indices"]]])
    assert np.abs(truth[:, y:y + h, x:x + w].astype(np.float32) - recon.frames).mean() > 8
    metrics = tmp_path / "m.json"
    assert main(["eval-recon", "--pred", str(out), "--gt", str(shards), "--scene-index", "1",
                 "--out", str(metrics)]) == 0
    assert json.loads(metrics.read_text())["scene_index"] == 1
    for other in ("0", "2"):
        assert_one_line_error(main(["eval-recon", "--pred", str(out), "--gt", str(shards),
                                    "--scene-index", other, "--out", str(metrics)]),
                              capsys.readouterr().err, f"scene {other}", "correlation",
                              "reconstructs another video")


def test_a_max_depth_that_keeps_no_depth_is_named(mp4_reconstruction, tmp_path, capsys):
    out, shards, _ = mp4_reconstruction
    score = ["eval-recon", "--pred", str(out), "--gt", str(shards), "--scene-index", "1",
             "--out", str(tmp_path / "m.json")]
    for value in ("0", "-1"):
        line = assert_one_line_error(main([*score, f"--max-depth={value}"]), capsys.readouterr().err,
                                     "--max-depth must be a positive depth", f"got {value}")
        assert "depth maps" not in line
    line = assert_one_line_error(main([*score, "--max-depth=0.5"]), capsys.readouterr().err,
                                 "--max-depth 0.5 leaves fewer than 2 depth pixels",
                                 "the ground truth's depth is")
    assert "depth maps" not in line and not (tmp_path / "m.json").exists()


def test_a_demo_record_naming_a_file_gone_from_its_folder_says_so(tmp_path):
    from c4d.demo import Demo

    demo = Demo(load_config("demo", "quick"), tmp_path / "demo")
    with pytest.raises(UserError) as info:
        demo.located("train/checkpoints/step_00000040.pt")
    message = str(info.value)
    assert "train/checkpoints/step_00000040.pt" in message and "moved or deleted" in message
    assert "redo that step" in message and "pass the path" not in message


def test_a_float_tapvid_video_is_read_as_tapnet_reads_it_or_named(tmp_path, capsys, caplog, inputs):
    rng = np.random.default_rng(0)
    video = rng.integers(0, 256, (6, 32, 32, 3)).astype(np.uint8)
    entry = {"points": rng.random((5, 6, 2)).astype(np.float32), "occluded": np.zeros((5, 6), bool)}
    summaries = {}
    for name, frames in (("uint8", video), ("float64", video.astype(np.float64))):
        data = tmp_path / f"{name}.pkl"
        data.write_bytes(pickle.dumps({"bear": {**entry, "video": frames}}))
        assert main(["eval", "--ckpt", str(inputs["ckpt"]), "--data", str(data), "--out",
                     str(tmp_path / name), "--config", "tiny-cpu", "eval.resolution=[32,32]"]) == 0
        summaries[name] = json.loads((tmp_path / name / "eval.json").read_text())["summary"]
    assert summaries["float64"] == summaries["uint8"]  # 0..255 values, as tapnet's reader takes them
    assert "TAP-Vid video 'bear' is float64, not uint8" in caplog.text
    data = tmp_path / "unit.pkl"
    data.write_bytes(pickle.dumps({"bear": {**entry, "video": video / 255.0}}))
    line = assert_one_line_error(main(["eval", "--ckpt", str(inputs["ckpt"]), "--data", str(data),
                                       "--out", str(tmp_path / "unit"), "--config", "tiny-cpu",
                                       "eval.resolution=[32,32]"]), capsys.readouterr().err,
                                 "'bear' is float64 in [0, 1]", "uint8")
    assert "undecodable" not in line


def test_a_browser_that_exits_at_once_is_named_with_its_exit_code(tmp_path, capsys, monkeypatch,
                                                                  mp4_reconstruction):
    from c4d.view.browser import Browser

    browser = tmp_path / "chromium"
    browser.write_text("#!/bin/sh\necho 'some start-up noise' >&2\n"
                       "echo 'chromium: error while loading shared libraries: libnss3.so' >&2\n"
                       "exit 127\n")
    browser.chmod(0o755)
    monkeypatch.setenv("C4D_BROWSER", str(browser))
    code = main(["view", str(mp4_reconstruction[0]), "--screenshot", str(tmp_path / "view.png")])
    line = assert_one_line_error(code, capsys.readouterr().err, f"the browser {browser} exited",
                                 "exit code 127", "libnss3.so", "C4D_BROWSER")
    assert "Broken pipe" not in line and "noise" not in line
    with Browser() as started:  # a command written after it has gone: the same line, no EPIPE
        started._process.wait()
        with pytest.raises(UserError, match="exited before answering Target.createTarget "
                                            r"\(exit code 127; its last line"):
            started.send("Target.createTarget", {"url": "about:blank"})


def test_a_refused_cotracker3_file_gets_the_hint_of_its_refusal(tmp_path, capsys, inputs):
    track = ["track", str(inputs["video"]), "--out", str(tmp_path / "t"), "--ckpt"]
    code = main([*track, f"cotracker3:{inputs['net']}"])  # intact: a DUSt3R file, with its args
    line = assert_one_line_error(code, capsys.readouterr().err, "(argparse.Namespace)",
                                 "a CoTracker3 checkpoint holds tensors alone", "scaled_offline.pth")
    assert "truncated" not in line
    pickled = tmp_path / "state.pkl"  # intact: a plain pickle
    pickled.write_bytes(pickle.dumps({"fnet.conv1.weight": np.zeros(3)}))
    err = (main([*track, f"cotracker3:{pickled}"]), capsys.readouterr().err)
    line = assert_one_line_error(*err, "it is a Python pickle, not a PyTorch file", "tensors alone")
    assert "truncated" not in line and "UserWarning" not in err[1]
    cut = tmp_path / "cut.pth"  # damaged: the hint stays
    cut.write_bytes(Path(inputs["net"]).read_bytes()[:3000])
    assert_one_line_error(main([*track, f"cotracker3:{cut}"]), capsys.readouterr().err,
                          "not a PyTorch file, or truncated (3000 bytes)", "truncated or damaged")
