"""Output files: every file of the contract's table written by `reconstruct` and read back exactly."""

import json

import numpy as np
import pytest

from c4d_core.config import load_config
from c4d_core.errors import UserError
from c4d_pipeline.flow import build_flow
from c4d_pipeline.ground_truth import GroundTruthPointmaps, oracle_tracks
from c4d_pipeline.outputs import (Reconstruction, ply_points, read_ply, read_reconstruction, read_tum,
                                  tum_lines, write_reconstruction)
from c4d_core import geometry
from c4d_pipeline.pipeline import Reused, lift_tracks, reconstruct
from tests.synthetic_scenes import make_box_scene



def random_reconstruction(rng, t=3, h=8, w=10, n=5) -> Reconstruction:
    quat = geometry.quat_normalize(rng.normal(size=(t, 4)))
    poses = geometry.make_pose(geometry.quat_to_matrix(quat), rng.normal(size=(t, 3))).astype(np.float32)
    return Reconstruction(
        frames=rng.integers(0, 256, (t, h, w, 3), dtype=np.uint8),
        depth=rng.uniform(0.5, 5, (t, h, w)).astype(np.float32),
        masks=rng.random((t, h, w)) > 0.7,
        cam_to_world=poses,
        intrinsics=np.tile(np.array([[9.0, 0, 4.5], [0, 9.0, 3.5], [0, 0, 1]], np.float32), (t, 1, 1)),
        points=rng.normal(size=(t, h, w, 3)).astype(np.float32),
        confidence=rng.uniform(1, 9, (t, h, w)).astype(np.float32),
        tracks_2d={"tracks": rng.uniform(0, 7, (t, n, 2)).astype(np.float32), "visible": rng.random((t, n)) > 0.2,
                   "moving": rng.random((t, n)).astype(np.float32), "queries": rng.uniform(0, 7, (n, 3)).astype(np.float32)},
        tracks_world=rng.normal(size=(t, n, 3)).astype(np.float32),
        tracks_valid=rng.random((t, n)) > 0.5,
        report={"seconds": {"stage1": 1.5}, "losses": {"stage1": {"ga": [0.3, 0.2]}}},
    )


def test_round_trip_of_every_file(tmp_path):
    rec = random_reconstruction(np.random.default_rng(0))
    out = write_reconstruction(rec, tmp_path / "out", ply_pixel_stride=1, ply_static_frame_stride=1)
    back = read_reconstruction(out)
    for name in ("frames", "depth", "masks", "intrinsics", "points", "confidence", "tracks_world", "tracks_valid"):
        np.testing.assert_array_equal(getattr(back, name), getattr(rec, name), err_msg=name)
    np.testing.assert_allclose(back.cam_to_world, rec.cam_to_world, atol=1e-6)
    for key, value in rec.tracks_2d.items():
        np.testing.assert_array_equal(back.tracks_2d[key], value)
    assert back.report == rec.report
    assert sorted(p.name for p in (out / "depth").iterdir()) == [
        f"{t:06d}.{ext}" for t in range(3) for ext in ("npy", "png")]
    points, colours = read_ply(out / "scene.ply")  # read by trimesh: the written values, exactly
    assert len(points) == rec.masks.size  # strides 1: every pixel (static of all frames + dynamic)
    written_points, written_colours = ply_points(rec, 1, 1)
    np.testing.assert_array_equal(points, written_points)
    np.testing.assert_array_equal(colours, written_colours)
    assert not list(out.rglob("*.tmp*"))  # atomic writes leave no temporaries


def test_tum_lines_are_standard_order():
    pose = geometry.make_pose(geometry.quat_to_matrix(np.array([0.0, 1.0, 0.0, 0.0])), np.array([1.0, 2.0, 3.0]))
    line = tum_lines(pose[None]).split()
    assert [float(v) for v in line] == [0.0, 1.0, 2.0, 3.0, 1.0, 0.0, 0.0, 0.0]  # t tx ty tz qx qy qz qw


def test_reading_a_non_reconstruction_is_a_user_error(tmp_path):
    with pytest.raises(UserError, match="poses_tum"):
        read_reconstruction(tmp_path)
    out = write_reconstruction(random_reconstruction(np.random.default_rng(1)), tmp_path / "out")
    (out / "masks" / "000001.png").write_bytes(b"not a png")
    with pytest.raises(UserError, match="masks/ cannot be read"):
        read_reconstruction(out)
    assert "masks/ cannot be read" in read_reconstruction(out, strict=False).problems[0]
    (tmp_path / "poses_tum.txt").write_text("0 1 2 3\n")
    with pytest.raises(UserError, match="8 numbers"):
        read_tum(tmp_path / "poses_tum.txt")


def test_lift_tracks_samples_the_pointmaps():
    points = np.zeros((1, 4, 5, 3), np.float32)
    points[0, :, :, 0] = np.arange(5)[None]  # x coordinate = column
    tracks = np.array([[[1.5, 2.0], [9.0, 1.0], [np.nan, 0.0]]], np.float32)
    world, valid = lift_tracks(points, tracks, np.ones((1, 3), bool))
    assert world[0, 0, 0] == pytest.approx(1.5)
    assert valid.tolist() == [[True, False, False]]


def test_reconstruct_writes_the_contract_table(tmp_path):
    scene = make_box_scene(num_frames=6, height=16, width=24, num_tracks=48, seed=5)
    cfg = load_config("c4d", "tiny", overrides=["graph.window=2", "optim.stage1_iters=10",
                                                "optim.stage2_iters=5", "pts.window=3", "pts.extend=1"])
    rec = reconstruct(scene.rgb, GroundTruthPointmaps(scene), build_flow("gt", scene=scene),
                      oracle_tracks(scene), cfg, tmp_path / "run")
    names = {p.relative_to(tmp_path / "run").as_posix() for p in (tmp_path / "run").rglob("*") if p.is_file()}
    for name in ("frames/000005.png", "depth/000000.npy", "depth/000000.png", "masks/000000.png",
                 "poses_tum.txt", "intrinsics.npy", "pointmaps.npz", "tracks_2d.npz", "tracks_3d.npz",
                 "scene.ply", "report.json"):
        assert name in names
    report = json.loads((tmp_path / "run" / "report.json").read_text())
    assert report["inputs"]["motion_masks"] == "dynpt+flow"
    assert {"pointmaps", "flow", "motion_masks", "optimise_stage1", "optimise_stage2"} <= set(report["seconds"])
    assert rec.masks.any() and rec.tracks_world.shape == (6, 48, 3)
    with pytest.raises(UserError, match="frames"):
        reconstruct(scene.rgb, GroundTruthPointmaps(scene), build_flow("gt", scene=scene),
                    oracle_tracks(make_box_scene(num_frames=5, height=16, width=24)), cfg)
    class NanSource(GroundTruthPointmaps):
        def pointmaps(self, frames, edges):
            pw = super().pointmaps(frames, edges)
            pw.pts_j[0, :3] = np.nan
            return pw

    no_tracker = reconstruct(scene.rgb, NanSource(scene), build_flow("gt", scene=scene), None, cfg)
    assert np.isfinite(no_tracker.points).all()
    assert no_tracker.report["inputs"]["motion_masks"] == "flow-only" and no_tracker.tracks_world is None


def test_inputs_reused_across_runs_are_computed_once_and_give_the_same_reconstruction(tmp_path):
    """`Reused` (C4D and GA only in `c4d demo`): the wrapped source and estimator run once for
    two reconstructions, each of which equals one from fresh inputs; callers get copies."""
    scene = make_box_scene(num_frames=6, height=16, width=24, num_tracks=48, seed=5)
    calls = {"pointmaps": 0, "flow": 0}

    class Counted(GroundTruthPointmaps):
        def pointmaps(self, frames, edges):
            calls["pointmaps"] += 1
            return super().pointmaps(frames, edges)

    flow = build_flow("gt", scene=scene)

    class CountedFlow:
        def flow(self, frames, pairs):
            calls["flow"] += 1
            return flow.flow(frames, pairs)

    pointmaps, flows = Reused(Counted(scene)), Reused(CountedFlow())
    for weights in ([], ["weights.cma=0", "weights.cts=0", "weights.pts=0"]):  # C4D, GA only
        cfg = load_config("c4d", "tiny", overrides=["graph.window=2", "optim.stage1_iters=10",
                                                    "optim.stage2_iters=5", "pts.window=3",
                                                    "pts.extend=1", *weights])
        reused = reconstruct(scene.rgb, pointmaps, flows, oracle_tracks(scene), cfg)
        fresh = reconstruct(scene.rgb, GroundTruthPointmaps(scene), flow, oracle_tracks(scene), cfg)
        np.testing.assert_array_equal(reused.cam_to_world, fresh.cam_to_world)
        np.testing.assert_array_equal(reused.depth, fresh.depth)
        assert reused.report["inputs"]["pointmap_source"] == "Counted"
    assert calls == {"pointmaps": 1, "flow": 1}
    edges = np.array([[0, 1], [1, 0]])
    first = pointmaps.pointmaps(scene.rgb, edges)  # other pairs: computed again
    first.pts_i[:] = np.nan  # a caller's change does not reach the next caller
    assert np.isfinite(pointmaps.pointmaps(scene.rgb, edges).pts_i).all() and calls["pointmaps"] == 2
