"""Evaluation: TAP-Vid pickles and query modes, the eval CLI's JSON and Markdown."""

import json
import pickle
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from omegaconf import OmegaConf

from c4d.cli import main
from c4d_core.config import load_config
from dynpt.checkpoint import save_checkpoint
from dynpt.evaluate import TRACK_KINDS, evaluate_items, load_source, track_kinds
from dynpt.model import build_model
from dynpt.tapvid_data import queries_first, queries_strided, read_tapvid
from tests.dynpt_testdata import synthetic_shards


def _tapvid_entry(seed, T=11, N=6, size=(48, 40)):
    rng = np.random.default_rng(seed)
    occluded = rng.random((N, T)) < 0.3
    occluded[-1] = True  # never visible: dropped in 'first' mode
    return {"video": rng.integers(0, 255, (T, *size, 3), dtype=np.uint8),
            "points": rng.random((N, T, 2)).astype(np.float32), "occluded": occluded}


@pytest.fixture(scope="module")
def davis_pickle(tmp_path_factory):
    path = tmp_path_factory.mktemp("tapvid") / "tapvid_davis.pkl"
    path.write_bytes(pickle.dumps({"bear": _tapvid_entry(0), "cows": _tapvid_entry(1)}))
    return path


def test_query_modes_follow_the_benchmark():
    occ = np.array([[1, 0, 0], [0, 1, 0], [1, 1, 1], [0, 0, 0], [1, 1, 0], [0, 0, 0]], bool)  # (T=6,N=3)
    tracks = np.arange(36, dtype=np.float32).reshape(6, 3, 2)
    q, idx = queries_first(occ, tracks)
    assert idx.tolist() == [0, 1, 2] and q[:, 0].tolist() == [1, 0, 0]
    np.testing.assert_array_equal(q[0, 1:], tracks[1, 0, ::-1])  # (t, y, x)
    q, idx = queries_strided(occ, tracks, stride=5)
    assert q[:, 0].tolist() == [0, 0, 5, 5, 5] and idx.tolist() == [1, 2, 0, 1, 2]


def test_tapvid_pickle_resized_to_256_and_points_scaled(davis_pickle):
    items = list(read_tapvid(davis_pickle))
    assert [i["name"] for i in items] == ["bear", "cows"]
    raw = _tapvid_entry(0)
    assert items[0]["video"].shape == (11, 256, 256, 3)
    np.testing.assert_allclose(items[0]["tracks"], raw["points"].transpose(1, 0, 2) * 256 - 0.5,
                               rtol=1e-6)
    # Kinetics: a list of entries whose video is JPEG bytes.
    entry = _tapvid_entry(2)
    entry["video"] = np.array([cv2.imencode(".jpg", f)[1].tobytes() for f in entry["video"]],
                              dtype=object)
    kinetics = davis_pickle.parent / "kinetics"
    kinetics.mkdir()
    (kinetics / "0000_of_0010.pkl").write_bytes(pickle.dumps([entry]))
    (item,) = read_tapvid(kinetics)
    assert item["name"] == "0000_of_0010/0000" and item["video"].shape == (11, 256, 256, 3)


class OracleTracker:
    """Returns the ground truth of one item: checks the plumbing, coordinates and metrics."""

    def __init__(self, item):
        self.item = item

    def track(self, video, queries):
        # Recover each query's track from its (t, x, y) on the ground truth.
        t = queries[:, 0].astype(int)
        gt = self.item["tracks"]  # (T,N,2)
        index = [int(np.argmin(np.abs(gt[ti] - q[1:]).sum(-1))) for ti, q in zip(t, queries)]
        moving = np.zeros(gt[:, index, 0].shape, np.float32)
        return SimpleNamespace(tracks=gt[:, index], visible=~self.item["occluded"][:, index],
                               moving=moving)


@pytest.mark.parametrize("mode", ["first", "strided"])
def test_perfect_tracker_scores_one(davis_pickle, mode):
    cfg = OmegaConf.create({"resolution": [256, 256]})
    items, kind = load_source(str(davis_pickle), cfg)
    assert kind == "tapvid"
    result = evaluate_items(OracleTracker(items[0]), items[:1], mode)
    s = result["summary"]
    assert s["average_jaccard"] == pytest.approx(1.0) and s["occlusion_accuracy"] == 1.0
    assert "d_acc" not in s  # no mobility labels in TAP-Vid


def test_eval_cli_writes_json_and_markdown(tmp_path, davis_pickle, capsys):
    ckpt = tmp_path / "tiny.pt"
    save_checkpoint(ckpt, build_model(load_config("dynpt", "tiny-cpu").model), step=0)
    shards = synthetic_shards(12, 3)
    out = tmp_path / "eval-shards"
    assert main(["eval", "--ckpt", str(ckpt), "--data", str(shards), "--out", str(out),
                 "--config", "tiny-cpu", "eval.resolution=[32,32]", "eval.num_tracks=8",
                 "eval.num_scenes=2"]) == 0
    report = json.loads((out / "eval.json").read_text())
    assert report["summary"]["num_videos"] == 2 and len(report["per_video"]) == 2
    s = report["summary"]
    assert 0 <= s["d_acc"] <= 1 and 0 <= s["average_jaccard"] <= 1
    # Synthetic scenes: half the points move, so D-ACC splits the two halves.
    assert s["d_acc"] == pytest.approx(0.5 * (s["d_acc_moving"] + s["d_acc_static"]), abs=0.15)
    baseline = report["zero_motion"]  # the reference row: all static, no motion
    assert baseline["d_acc_moving"] == 0 and baseline["d_acc_static"] == 1
    low, high = report["d_acc_difference_interval"]  # over the 2 videos, resampled
    assert low <= s["d_acc"] - baseline["d_acc"] + 1e-9 and s["d_acc"] - baseline["d_acc"] <= high + 1e-9
    table = (out / "eval.md").read_text()
    assert table.startswith("| source | tracker | videos | skipped | D-ACC")
    assert table in capsys.readouterr().out
    assert "| checkpoint | 2 | 0 |" in table and "| zero motion, all static | 2 | 0 |" in table
    assert "D-ACC minus all-static:" in table and "95 % interval over the videos" in table
    # the same tracks, their mobility fused with their epipolar geometry (dynpt/track_mobility.py)
    fused = tmp_path / "eval-epipolar"
    assert main(["eval", "--ckpt", str(ckpt), "--data", str(shards), "--out", str(fused),
                 "--config", "tiny-cpu", "eval.resolution=[32,32]", "eval.num_tracks=8",
                 "eval.num_scenes=2", "eval.mobility=epipolar", "eval.epipolar.head_weight=0"]) == 0
    fused_report = json.loads((fused / "eval.json").read_text())
    assert fused_report["info"]["mobility"] == "epipolar"
    assert fused_report["info"]["epipolar"]["head_weight"] == 0
    assert fused_report["summary"]["average_jaccard"] == s["average_jaccard"]
    assert "eval.mobility=epipolar" in (fused / "eval.md").read_text()
    # the tracks refined by Lucas-Kanade (dynpt/refine.py) before the fusion reads them
    refined = tmp_path / "eval-refined"
    assert main(["eval", "--ckpt", str(ckpt), "--data", str(shards), "--out", str(refined),
                 "--config", "tiny-cpu", "eval.resolution=[32,32]", "eval.num_tracks=8",
                 "eval.num_scenes=2", "eval.refine=lk", "eval.mobility=epipolar"]) == 0
    refined_report = json.loads((refined / "eval.json").read_text())
    assert refined_report["info"]["refine"] == "lk" and refined_report["info"]["lk"]["window"] == 11
    assert refined_report["summary"]["occlusion_accuracy"] == s["occlusion_accuracy"]  # same visibility
    assert "eval.refine=lk" in (refined / "eval.md").read_text()
    out2 = tmp_path / "eval-davis"
    assert main(["eval", "--ckpt", str(ckpt), "--data", str(davis_pickle), "--mode", "strided",
                 "--out", str(out2), "--config", "tiny-cpu", "eval.resolution=[64,64]"]) == 0
    summary = json.loads((out2 / "eval.json").read_text())["summary"]
    assert summary["num_videos"] == 2 and "d_acc" not in summary
    assert main(["eval", "--ckpt", str(tmp_path / "missing.pt"), "--data", str(shards)]) == 2


def test_zero_motion_baseline_scores_all_static_and_half_balanced():
    from dynpt.baselines import ZeroMotionBaseline

    eval_cfg = load_config("dynpt", "tiny-cpu", overrides=[
        "eval.resolution=[32,32]", "eval.num_tracks=8", "eval.num_scenes=2"]).eval
    items, kind = load_source(str(synthetic_shards(12, 3)), eval_cfg)
    s = evaluate_items(ZeroMotionBaseline(), items, "first")["summary"]
    assert kind == "shards"
    assert s["d_acc_static"] == 1.0 and s["d_acc_moving"] == 0.0 and s["d_acc_balanced"] == 0.5
    assert 0 < s["d_acc"] < 1


def test_track_kinds_from_the_scene_objects():
    scene = SimpleNamespace(track_object=np.array([0, 1, 2, 0, 2], np.int32),
                            objects=[{"tossed": False}, {"tossed": True}])
    kinds = track_kinds(scene)
    assert [TRACK_KINDS[k] for k in kinds] == ["background", "resting object", "tossed object",
                                               "background", "tossed object"]
    assert track_kinds(SimpleNamespace(track_object=scene.track_object, objects=None)) is None


def test_eval_uses_the_checkpoints_own_eval_settings():
    """`c4d eval` without --config evaluates as the checkpoint was validated during training."""
    from dynpt.cli_eval import eval_config

    saved = {"extra": {"train_config": {"eval": {"resolution": [48, 48], "num_tracks": 64,
                                                 "num_scenes": 8, "seed": 0}}}}
    cfg = eval_config(saved, None, ["eval.num_scenes=2"])
    assert list(cfg.resolution) == [48, 48] and cfg.num_tracks == 64 and cfg.num_scenes == 2
    assert list(eval_config(saved, "paper-gpu", []).resolution) == [256, 256]
    assert list(eval_config({"extra": {}}, None, []).resolution) == [256, 256]  # nothing saved
    # but not its number of scenes (the validation's during training), nor a preset's: all videos
    assert [eval_config(saved, config, []).num_scenes for config in (None, "paper-gpu")] == [0, 0]


def test_eval_scores_every_video_unless_asked_and_says_how_many_and_where(tmp_path, davis_pickle,
                                                                          capsys):
    """The checkpoint's eval.num_scenes (8: its validation during training) does not cut `c4d
    eval`: all 12 videos are scored, and the output says so and where it wrote (next to the
    checkpoint by default); eval.num_scenes=5 on the command line scores the first 5 "of 12"
    (counted in shards without a dataset file: the scenes are read past); on a TAP-Vid pickle
    it is refused before anything is written."""
    from dynpt.cli_eval import source_scenes
    from tests.dynpt_testdata import generated_shards

    ckpt = tmp_path / "run" / "last.pt"
    saved = {"eval": {"resolution": [32, 32], "num_tracks": 8, "num_scenes": 8, "seed": 0}}
    save_checkpoint(ckpt, build_model(load_config("dynpt", "tiny-cpu").model), step=0,
                    extra={"train_config": saved})
    shards = synthetic_shards(12, 3)
    assert main(["eval", "--ckpt", str(ckpt), "--data", str(shards)]) == 0
    printed = capsys.readouterr().out
    beside = tmp_path / "run" / f"eval-{shards.name}-first"
    assert f"scored 12 of 12 videos of {shards}\n" in printed
    assert (f"wrote {beside / 'eval.json'} and {beside / 'eval.md'} (next to the checkpoint; "
            "--out DIR writes elsewhere)") in printed
    assert json.loads((beside / "eval.json").read_text())["summary"]["num_videos"] == 12
    chosen = tmp_path / "chosen"
    assert main(["eval", "--ckpt", str(ckpt), "--data", str(shards), "--out", str(chosen),
                 "eval.num_scenes=5"]) == 0
    printed = capsys.readouterr().out
    assert (f"scored 5 of 12 videos of {shards} (the first 5, as eval.num_scenes=5 asked; "
            "without it every video is scored)\n") in printed
    assert f"wrote {chosen / 'eval.json'} and {chosen / 'eval.md'}\n" in printed
    report = json.loads((chosen / "eval.json").read_text())
    assert report["summary"]["num_videos"] == 5 and report["info"]["videos_in_data"] == 12
    assert source_scenes(str(generated_shards())) == 4  # from the dataset file `c4d datagen` wrote
    refused = tmp_path / "davis"
    assert main(["eval", "--ckpt", str(ckpt), "--data", str(davis_pickle), "--out", str(refused),
                 "eval.num_scenes=1"]) == 2
    assert "eval.num_scenes=1 is for datagen shards" in capsys.readouterr().err
    assert not refused.exists()


def test_eval_mode_is_the_key_eval_query_mode(tmp_path, davis_pickle, capsys):
    """`eval.query_mode=strided` is what `--mode strided` does (it still printed "first
    queries"); both at once are refused; without either, the checkpoint's own mode is used."""
    ckpt = tmp_path / "tiny.pt"
    model = build_model(load_config("dynpt", "tiny-cpu").model)
    saved = {"eval": {"resolution": [32, 32], "num_tracks": 8, "num_scenes": 2, "seed": 0, "query_mode": "strided"}}
    save_checkpoint(ckpt, model, step=0, extra={"train_config": saved})
    for argv in (["eval.query_mode=strided", "--config", "tiny-cpu"], []):  # the key; the checkpoint's
        out = tmp_path / f"eval{len(argv)}"
        assert main(["eval", "--ckpt", str(ckpt), "--data", str(davis_pickle), "--out", str(out), *argv]) == 0
        assert "(strided queries" in capsys.readouterr().out
        assert json.loads((out / "eval.json").read_text())["info"]["mode"] == "strided"
    assert main(["eval", "--ckpt", str(ckpt), "--data", str(davis_pickle), "--mode", "first",
                 "eval.query_mode=strided"]) == 2
    assert "`eval.query_mode` is set both by a flag" in capsys.readouterr().err


def test_too_small_network_size_names_that_size_and_what_sets_it():
    """The check is on the network's size: a 64x64 video into a model whose resolution is 12x10
    (an old checkpoint; the schema now refuses it) names 12x10 and model.resolution, not 64x64."""
    from c4d_core.errors import UserError
    from dynpt.inference import Tracker

    tracker = Tracker(build_model(load_config("dynpt", "tiny-cpu").model), "cpu")
    tracker.model.config["resolution"] = (10, 12)  # (H, W)
    video = np.zeros((3, 64, 64, 3), np.uint8)
    with pytest.raises(UserError, match=r"network size 12x10 pixels \(the checkpoint's model.resolution\)"):
        tracker.track(video)
    tracker.model.config["resolution"] = None  # the frames' own size: what sets it is named
    with pytest.raises(UserError, match="40x5 pixels .*--size/--max-size of c4d track.*eval.resolution"):
        tracker.track(np.zeros((3, 5, 40, 3), np.uint8))
