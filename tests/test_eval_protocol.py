"""The paper's D-ACC protocol (`c4d eval --protocol c4d-paper`): tracks drawn afresh as
TAP-Vid-Kubric draws them, queried at their drawn points, scored at 256x256."""

import json
from types import SimpleNamespace

import numpy as np
import pytest
from omegaconf import OmegaConf

from c4d.cli import main
from c4d_core import geometry
from c4d_core.config import load_config
from datagen.annotate import allocate_points, tapvid_kubric_tracks
from datagen.shards import ShardWriter, encode_scene, scene_key
from dynpt.checkpoint import save_checkpoint
from dynpt.evaluate import PAPER_RESOLUTION, evaluate_items, load_source, paper_item
from dynpt.model import build_model
from tests.synthetic_scenes import make_box_scene


@pytest.fixture(scope="module")
def box_scenes():
    return [make_box_scene(num_frames=24, height=48, width=64, num_tracks=8, seed=s) for s in (0, 1)]


@pytest.fixture(scope="module")
def box_shards(tmp_path_factory, box_scenes):
    out = tmp_path_factory.mktemp("boxes")
    with ShardWriter(out / "val-000000.tar") as writer:
        for i, scene in enumerate(box_scenes):
            scene.meta["scene_index"] = i
            writer.write(encode_scene(scene, scene_key("val", i)))
    return out


def test_kubric_allocation_caps_at_a_tenth_rounded_and_passes_the_rest_on():
    # smallest first: 7 -> min(round(100/3)=33, round(0.7)=1); 40 -> min(round(99/2)=50, 4);
    # the background takes the rest, capped at round(0.1 * 5000) = 500.
    counts = np.array([5000, 7, 40])
    assert allocate_points(counts, 100, 0.1, exact_kubric=True).tolist() == [95, 1, 4]
    assert allocate_points(np.array([3, 4]), 100, 0.1, exact_kubric=True).tolist() == [0, 0]


def test_tapvid_kubric_tracks_are_exact_seeded_and_follow_the_objects(box_scenes):
    scene = box_scenes[0]
    drawn = tapvid_kubric_tracks(scene, [0, 3], 256)
    again = tapvid_kubric_tracks(scene, [0, 3], 256)
    other = tapvid_kubric_tracks(scene, [1, 3], 256)
    np.testing.assert_array_equal(drawn.tracks, again.tracks)
    assert not np.array_equal(drawn.tracks, other.tracks)
    n = np.arange(256)
    q = drawn.query_frame
    assert drawn.tracks.shape == (256, 24, 2) and (q % 4 == q[0] % 4).all()  # one stride-4 phase
    assert not drawn.occluded[n, q].any()  # visible where drawn
    xy = drawn.tracks[n, q]  # the drawn pixel itself: integer, on its segment
    np.testing.assert_allclose(xy, np.round(xy), atol=1e-3)
    seg = scene.segmentation[q, np.round(xy[:, 1]).astype(int), np.round(xy[:, 0]).astype(int)]
    np.testing.assert_array_equal(seg, drawn.track_object)
    # Every object is drawn, the backdrop no more than its share; only the sliding box moves.
    assert set(np.unique(drawn.track_object)) == {0, 1, 2, 3}
    assert drawn.moving[drawn.track_object != 3].sum() == 0
    assert drawn.moving[drawn.track_object == 3].mean() > 0.9
    # A visible track point projects where the geometry says: re-project its world point.
    uv, _ = geometry.project(drawn.tracks_world, scene.intrinsics[None], scene.cam_to_world[None])
    np.testing.assert_allclose(uv, drawn.tracks, atol=1e-3)
    with pytest.raises(ValueError, match="depth"):
        tapvid_kubric_tracks(SimpleNamespace(depth=None, segmentation=1, object_to_world=1), 0)


class OracleTracker:
    """The ground truth of the items, in order, with the true mobility as its probability."""

    def __init__(self, items):
        self.items = iter(items)

    def track(self, video, queries):
        item = next(self.items)
        return SimpleNamespace(tracks=item["tracks"], visible=~item["occluded"],
                               moving=item["moving"].astype(np.float32))


def test_paper_items_at_256_and_an_oracle_scores_one(box_scenes):
    cfg = OmegaConf.create({"seed": 0, "protocol": "c4d-paper"})
    items = [paper_item(s, i, cfg) for i, s in enumerate(box_scenes)]
    item = items[0]
    assert item["video"].shape == (24, *PAPER_RESOLUTION, 3) and item["tracks"].shape == (24, 256, 2)
    drawn = tapvid_kubric_tracks(box_scenes[0], [0, 0], 256)  # scaled by 256/64 and 256/48
    scale = np.array([256 / 64, 256 / 48])
    np.testing.assert_allclose(item["tracks"], ((drawn.tracks + 0.5) * scale - 0.5).transpose(1, 0, 2),
                               atol=1e-3)
    result = evaluate_items(OracleTracker(items), items, "sampled")["summary"]
    assert result["average_jaccard"] == pytest.approx(1.0) and result["d_acc"] == 1.0
    assert result["moving_ap"] == pytest.approx(1.0) and result["d_acc_balanced"] == 1.0
    from dynpt.baselines import ZeroMotionBaseline

    baseline = evaluate_items(ZeroMotionBaseline(), items, "sampled")["summary"]
    moving = np.mean([it["moving"][np.arange(24)[:, None] != it["query_frame"]].mean() for it in items])
    assert baseline["moving_ap"] == pytest.approx(moving, abs=0.02)  # a constant ranks nothing
    assert baseline["d_acc_static"] == 1.0 and baseline["d_acc_moving"] == 0.0


def test_eval_cli_protocol_reports_and_refuses(tmp_path, box_shards, capsys):
    ckpt = tmp_path / "tiny.pt"
    save_checkpoint(ckpt, build_model(load_config("dynpt", "tiny-cpu").model), step=0)
    out = tmp_path / "paper"
    assert main(["eval", "--ckpt", str(ckpt), "--data", str(box_shards), "--protocol", "c4d-paper",
                 "--out", str(out), "--config", "tiny-cpu"]) == 0
    report = json.loads((out / "eval.json").read_text())
    assert report["info"]["protocol"] == "c4d-paper" and report["info"]["resolution"] == [256, 256]
    assert report["info"]["num_tracks"] == 256 and report["summary"]["num_videos"] == 2
    assert all(r["num_queries"] == 256 for r in report["per_video"])
    for key in ("d_acc", "d_acc_moving", "d_acc_static", "d_acc_balanced", "moving_ap"):
        assert 0 <= report["summary"][key] <= 1 and 0 <= report["zero_motion"][key] <= 1
    assert report["d_acc_difference_interval"] is not None
    printed = capsys.readouterr().out
    assert "the c4d-paper protocol: 24 frames at 256x256, 256 TAP-Vid-Kubric tracks" in printed
    assert "AP moving" in printed
    # Refused, one line each, nothing written: a contradicting setting, a short video, TAP-Vid.
    refused = tmp_path / "refused"
    assert main(["eval", "--ckpt", str(ckpt), "--data", str(box_shards), "--protocol", "c4d-paper",
                 "--out", str(refused), "eval.num_tracks=64"]) == 2
    assert "eval.num_tracks=64 contradicts --protocol c4d-paper" in capsys.readouterr().err
    assert main(["eval", "--ckpt", str(ckpt), "--data", str(box_shards), "--protocol", "c4d-paper",
                 "--mode", "first", "--out", str(refused)]) == 2
    assert "leave --mode out" in capsys.readouterr().err
    short = tmp_path / "short"
    short.mkdir()
    with ShardWriter(short / "val-000000.tar") as writer:
        writer.write(encode_scene(make_box_scene(num_frames=12, height=24, width=32), scene_key("val", 0)))
    assert main(["eval", "--ckpt", str(ckpt), "--data", str(short), "--protocol", "c4d-paper",
                 "--out", str(refused)]) == 2
    err = capsys.readouterr().err
    assert "has 12 frames; the c4d-paper protocol scores 24-frame videos" in err
    assert len(err.strip().splitlines()) == 1 and not refused.exists()


def test_protocol_refuses_a_tapvid_benchmark(tmp_path):
    (tmp_path / "tapvid_davis.pkl").write_bytes(b"")
    cfg = OmegaConf.create({"protocol": "c4d-paper", "resolution": [256, 256]})
    with pytest.raises(Exception, match="the c4d-paper protocol draws its tracks"):
        load_source(str(tmp_path / "tapvid_davis.pkl"), cfg)
