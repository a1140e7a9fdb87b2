"""Long videos in windows (`c4d_pipeline.windows`): the Sim(3) join, the plan and its refusals,
windowed against whole-video poses, bounded requests to the sources, streamed outputs, `c4d run --window`."""

import json
import zipfile

import numpy as np
import pytest

from c4d.cli import main
from c4d_core import geometry
from c4d_core.config import load_config
from c4d_core.errors import UserError
from c4d_pipeline.eval_metrics import pose_metrics
from c4d_pipeline.flow import build_flow
from c4d_pipeline.ground_truth import GroundTruthPointmaps, oracle_tracks
from c4d_pipeline.outputs import PlyStream, _ply_bytes, read_reconstruction, write_npz_frames
from c4d_pipeline.pipeline import reconstruct
from c4d_pipeline.windows import (anchor_frames, join_similarity, plan_windows, pose_graph, reconstruct_windowed,
                                  similarity_poses)
from tests.synthetic_scenes import make_box_scene
from tests.test_c4d_run import make_inputs

FAST = ["graph.window=2", "optim.stage1_iters=80", "optim.stage2_iters=10", "pts.window=6", "pts.extend=1"]


def _graph(window=5, stride=2, start=1):
    return load_config("c4d", "default", overrides=[f"graph.window={window}", f"graph.stride={stride}",
                                                    f"graph.start={start}"]).graph


def test_join_recovers_a_known_similarity():
    scene = make_box_scene(6, 24, 32, num_tracks=0, seed=3)
    points = np.stack([geometry.unproject_depth_map(scene.depth[t], scene.intrinsics[t], scene.cam_to_world[t])
                       for t in range(3)])  # (3,H,W,3) world
    rot = geometry.quat_to_matrix(np.array([0.9, 0.2, -0.3, 0.25]) / np.linalg.norm([0.9, 0.2, -0.3, 0.25]))
    scale, trans = 0.37, np.array([1.5, -2.0, 0.3])
    moved = scale * points @ rot.T + trans
    rng = np.random.default_rng(0)
    noisy = moved + 0.002 * rng.standard_normal(moved.shape)
    conf, static = np.full(points.shape[:3], 5.0), np.ones(points.shape[:3], bool)
    static[:, :4] = False
    noisy[:, :4] += 3.0  # "moving" pixels far off: left out by the static mask
    s, r, t = join_similarity(points, noisy, conf, conf, static)
    assert s == pytest.approx(scale, rel=1e-3)
    np.testing.assert_allclose(r, rot, atol=1e-3)
    np.testing.assert_allclose(t, trans, atol=1e-2)
    # the cameras follow the world: their centres are mapped like points
    poses = similarity_poses(scene.cam_to_world[:3], scale, rot, trans)
    np.testing.assert_allclose(poses[:, :3, 3], scale * scene.cam_to_world[:3, :3, 3] @ rot.T + trans, atol=1e-6)
    np.testing.assert_allclose(poses[:, :3, :3], rot @ scene.cam_to_world[:3, :3, :3], atol=1e-6)


def test_plan_covers_the_video_and_every_graph_pair():
    graph = _graph()  # offsets 1..9
    plan = plan_windows(100, 30, 10, graph)
    assert [(w.start, w.stop) for w in plan] == [(0, 30), (18, 48), (35, 65), (53, 83), (70, 100)]
    owned = np.concatenate([np.arange(w.own_start, w.own_stop) for w in plan])
    np.testing.assert_array_equal(owned, np.arange(100))  # every frame written once, in order
    assert all(w.start <= w.own_start < w.own_stop <= w.stop for w in plan)
    for i in range(100):  # every pair of the whole-video graph lies inside some window
        for j in range(i + 1, min(i + 10, 100)):
            assert any(w.start <= i and j < w.stop for w in plan), (i, j)
    assert [(w.start, w.stop) for w in plan_windows(25, 30, 10, graph)] == [(0, 25)]


@pytest.mark.parametrize("frames, overlap, message", [
    (9, 5, "window.frames = 9 cannot hold the scene graph, whose longest pair spans 9 frames"),
    (30, 4, "window.overlap = 4 is shorter than the scene graph's longest pair (9 frames)"),
    (12, 12, "window.overlap = 12 must be smaller than window.frames = 12"),
])
def test_windows_that_cannot_hold_the_graph_are_refused(frames, overlap, message):
    with pytest.raises(UserError) as err:
        plan_windows(100, frames, overlap, _graph())
    assert message in str(err.value) and "\n" not in str(err.value)


def test_the_anchors_pairs_hold_the_drift_of_the_chain():
    """Windows whose measurements turn a little too much each (a drift that adds up along the
    chain) and an anchor whose few long pairs do not drift but are noisy: the pass with the anchor
    ends near the true path, the windows alone stay on the drifted one, and the anchor's noise
    does not undo the windows' neighbouring frames (weights 1 / a pair's offset in its reconstruction)."""
    rng = np.random.default_rng(0)
    count = 60
    truth = np.tile(np.eye(4), (count, 1, 1))
    truth[:, 0, 3] = np.arange(count) * 0.1  # a straight path along x

    def turn(angle):  # (4,4) rotation about z
        out = np.eye(4)
        out[:2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
        return out

    window = np.array([(i, j) for i in range(count) for j in (i + 1, i + 3) if j < count])
    drifted = [np.linalg.inv(truth[i]) @ truth[j] @ turn(0.004 * (j - i)) for i, j in window]  # 0.23 deg a frame
    keys = anchor_frames(count, 12)
    steps = np.array([(a, b) for a in range(len(keys)) for b in (a + 1, a + 2) if b < len(keys)])  # in keyframes
    anchor = keys[steps]
    noisy = []
    for i, j in anchor:
        rel = np.linalg.inv(truth[i]) @ truth[j] @ turn(rng.normal(0, 0.002))
        rel[:3, 3] += rng.normal(0, 0.005, 3)
        noisy.append(rel)

    def chained(pairs, relative):  # poses integrated along the neighbouring pairs
        step = {(int(i), int(j)): r for (i, j), r in zip(pairs, relative)}
        poses = [np.eye(4)]
        for t in range(1, count):
            poses.append(poses[-1] @ step[(t - 1, t)])
        return np.stack(poses)

    start = chained(window, drifted)
    weight_window = 1.0 / (window[:, 1] - window[:, 0])  # 1 / offset in frames
    weight_anchor = 1.0 / (steps[:, 1] - steps[:, 0])  # 1 / offset in keyframes
    alone = pose_graph(start, window, np.stack(drifted), weight_window, 1.0, 100)
    both = pose_graph(start, np.concatenate([window, anchor]), np.stack([*drifted, *noisy]),
                      np.concatenate([weight_window, weight_anchor]), 1.0, 100)
    error = {name: pose_metrics(poses, truth) for name, poses in (("alone", alone), ("both", both))}
    assert error["alone"]["ate"] > 0.05  # the drift of the chain: the path (5.9 long) bends by 13 degrees
    assert error["both"]["ate"] < 0.3 * error["alone"]["ate"], error  # 0.013 against 0.054
    assert error["both"]["rpe_trans"] < 0.002, error  # steps of 0.1: the anchor's noise (0.005) is not spread into them


def test_pose_graph_closes_a_seam():
    """Two windows measure the same chain of poses; the second one's poses are off by a jump.
    The pass leaves each window's own measurements met and spreads the jump over the seam."""
    truth = np.tile(np.eye(4), (12, 1, 1))
    truth[:, 0, 3] = np.arange(12) * 0.1
    jumped = truth.copy()
    jumped[6:, 1, 3] += 0.05  # the second window's frames as joined: shifted sideways
    pairs = np.array([(i, i + 1) for i in range(11)] + [(i, i + 2) for i in range(10)])
    relative = np.linalg.inv(truth[pairs[:, 0]]) @ truth[pairs[:, 1]]
    refined = pose_graph(jumped, pairs, relative, np.ones(len(pairs)), 1.0, 50)
    np.testing.assert_allclose(refined, truth, atol=1e-4)  # from a jump of 0.05
    np.testing.assert_array_equal(pose_graph(jumped, pairs, relative, np.ones(len(pairs)), 1.0, 0), jumped)


class _Recording:
    """A real pointmap source or flow estimator that records the pairs it is asked for."""

    def __init__(self, inner):
        self.inner, self.calls = inner, []

    def pointmaps(self, frames, edges):
        self.calls.append(np.asarray(edges))
        return self.inner.pointmaps(frames, edges)

    def flow(self, frames, pairs):
        self.calls.append(np.asarray(pairs))
        return self.inner.flow(frames, pairs)


@pytest.fixture(scope="module")
def windowed_and_whole(tmp_path_factory):
    """A 24-frame box scene reconstructed whole and in windows of 10 frames overlapping by 4."""
    scene = make_box_scene(24, 32, 40, num_tracks=128, seed=1)
    tracks = oracle_tracks(scene)
    whole = reconstruct(scene.rgb, GroundTruthPointmaps(scene), build_flow("gt", scene=scene), tracks,
                        load_config("c4d", "tiny", overrides=FAST))
    cfg = load_config("c4d", "tiny", overrides=[*FAST, "window.frames=10", "window.overlap=4"])
    source, flow = _Recording(GroundTruthPointmaps(scene)), _Recording(build_flow("gt", scene=scene))
    out = tmp_path_factory.mktemp("long") / "out"
    out.mkdir()
    windowed = reconstruct_windowed(scene.rgb, source, flow, tracks, cfg, out)
    return scene, whole, windowed, cfg, source, flow, out


def test_windowed_poses_agree_with_the_whole_video(windowed_and_whole):
    scene, whole, windowed, *_ = windowed_and_whole
    truth = scene.cam_to_world.astype(np.float64)
    ate_whole = pose_metrics(whole.cam_to_world.astype(np.float64), truth)["ate"]
    ate_windowed = pose_metrics(windowed.cam_to_world.astype(np.float64), truth)["ate"]
    path = np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1).sum()
    assert ate_windowed < 1.5 * ate_whole + 0.01 * path, (ate_windowed, ate_whole, path)
    between = pose_metrics(windowed.cam_to_world.astype(np.float64), whole.cam_to_world.astype(np.float64))
    assert between["ate"] < 0.05 * path and between["rpe_rot"] < 1.0, between


def test_sources_are_asked_only_for_pairs_of_the_anchor_or_inside_one_window(windowed_and_whole):
    scene, _, windowed, cfg, source, flow, _ = windowed_and_whole
    plan = plan_windows(24, 10, 4, cfg.graph)
    keys = anchor_frames(24, 10)
    np.testing.assert_array_equal(keys, [0, 3, 5, 8, 10, 13, 15, 18, 20, 23])  # first to last, evenly
    assert windowed.report["anchor"]["frames"] == keys.tolist()
    assert len(windowed.report["windows"]) == len(plan) == 4
    assert [w["joined_to"] for w in windowed.report["windows"]] == [  # every window holds keyframes
        ["anchor"], ["anchor", "previous"], ["anchor", "previous"], ["anchor", "previous"]]
    for recorder in (source, flow):
        assert len(recorder.calls) == 1 + len(plan)  # the anchor, then one request per window; none for the whole video
        assert np.isin(recorder.calls[0], keys).all() and np.ptp(recorder.calls[0]) > 10  # the anchor's pairs span windows
        for pairs, win in zip(recorder.calls[1:], plan):
            assert pairs.min() >= win.start and pairs.max() < win.stop, (pairs.min(), pairs.max(), win)


def test_without_the_anchor_the_windows_are_chained(windowed_and_whole, tmp_path):
    scene, whole, *_ = windowed_and_whole
    cfg = load_config("c4d", "tiny", overrides=[*FAST, "window.frames=10", "window.overlap=4", "window.anchor=false"])
    source = _Recording(GroundTruthPointmaps(scene))
    chained = reconstruct_windowed(scene.rgb, source, build_flow("gt", scene=scene), oracle_tracks(scene), cfg, tmp_path)
    assert "anchor" not in chained.report and len(source.calls) == 4  # the windows' requests only
    assert [w["joined_to"] for w in chained.report["windows"]] == [["reference"], *[["previous"]] * 3]
    truth = scene.cam_to_world.astype(np.float64)
    path = np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1).sum()
    ate = {name: pose_metrics(rec.cam_to_world.astype(np.float64), truth)["ate"]
           for name, rec in (("whole", whole), ("chain", chained))}
    assert ate["chain"] < 1.5 * ate["whole"] + 0.01 * path, ate


def test_streamed_outputs_are_a_reconstruction(windowed_and_whole):
    scene, _, windowed, _, _, _, out = windowed_and_whole
    rec = read_reconstruction(out)  # the strict reader of c4d eval-recon
    assert rec.points.shape == (24, 32, 40, 3) and rec.tracks_world.shape == (24, 128, 3)
    np.testing.assert_allclose(rec.cam_to_world, windowed.cam_to_world, atol=1e-6)
    for t in (0, 7, 23):  # world points = the refined pose applied to the written depth
        expected = geometry.unproject_depth_map(rec.depth[t], rec.intrinsics[t], windowed.cam_to_world[t])
        np.testing.assert_allclose(rec.points[t], expected, rtol=1e-4, atol=1e-4)
    assert (rec.confidence >= 1).all()
    tolerant = read_reconstruction(out, strict=False)
    assert tolerant.problems == [] and len(tolerant.ply_points) > 100
    assert not list(out.glob(".windows-*"))  # the scratch folder is gone


def test_stream_writers_write_what_the_whole_array_writers_write(tmp_path):
    rng = np.random.default_rng(0)
    points, colours = rng.standard_normal((5, 3)).astype(np.float32), rng.integers(0, 255, (5, 3), np.uint8)
    with PlyStream(tmp_path / "a.ply", tmp_path / "body") as ply:
        ply.add(points[:2], colours[:2])
        ply.add(points[2:], colours[2:])
    assert (tmp_path / "a.ply").read_bytes() == _ply_bytes(points, colours)
    arrays = {"points": rng.standard_normal((4, 3, 2, 3)), "confidence": rng.standard_normal((4, 3, 2))}
    write_npz_frames(tmp_path / "a.npz", 4, {name: (a.shape[1:], lambda a=a: iter(a)) for name, a in arrays.items()})
    with np.load(tmp_path / "a.npz") as data:
        for name, array in arrays.items():
            np.testing.assert_array_equal(data[name], array.astype(np.float32))
    assert zipfile.ZipFile(tmp_path / "a.npz").getinfo("points.npy").compress_type == zipfile.ZIP_DEFLATED


def test_c4d_run_in_windows(tmp_path, capsys):
    video, ckpt = make_inputs(tmp_path, frames=8)
    common = ["--pointmaps", str(ckpt), "--size", "64", "--preset", "tiny"]
    fast = ["graph.window=2", "optim.stage1_iters=4", "optim.stage2_iters=2", "pts.window=4", "pts.extend=1"]
    assert main(["run", str(video), *fast, "--out", str(tmp_path / "bad"), *common, "--window", "3"]) == 2
    err = capsys.readouterr().err.strip()
    assert "window.frames = 3 cannot hold the scene graph" in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "bad").exists()
    out = tmp_path / "out"
    assert main(["run", str(video), *fast, "--out", str(out), *common, "--window", "6",
                 "--window-overlap", "3"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert [w["frames"] for w in report["windows"]] == [[0, 6], [2, 8]]
    assert report["config"]["window"]["frames"] == 6
    assert read_reconstruction(out).points.shape == (8, 48, 64, 3)
