"""Known intrinsics (`c4d run --intrinsics`, `intrinsics.known` / `intrinsics.mode`): better poses
where the pointmaps misjudge the field of view, kept exactly in fixed mode, following the frames'
resize and crop, and one line for each bad input."""

import argparse

import numpy as np
import pytest
import torch

from c4d.cli import main
from c4d_core.config import load_config
from c4d_core.geometry import rescale_pixels
from c4d_core.video import write_video
from c4d_pipeline import optimize as opt
from c4d_pipeline.eval_metrics import pose_metrics
from c4d_pipeline.flow import build_flow
from c4d_pipeline.ground_truth import GroundTruthPointmaps, ground_truth_motion_masks
from c4d_pipeline.scene_graph import strided_window_pairs
from c4d_pipeline.video_input import VideoInput, network_intrinsics, plan_preprocessing
from tests.synthetic_scenes import make_box_scene
from tests.test_c4d_run import ARGS, FAST, tiny_network

T, H, W = 8, 24, 32
# fx != fy and a principal point off the centre (15.5, 11.5)
TRUE_K = np.array([[30.0, 0, 14.0], [0, 27.0, 12.5], [0, 0, 1]])


def _rows(k: np.ndarray) -> np.ndarray:
    """(...,3,3) -> (...,4) fx, fy, cx, cy."""
    return np.stack([k[..., 0, 0], k[..., 1, 1], k[..., 0, 2], k[..., 1, 2]], -1)


def test_known_intrinsics_fixed_give_better_poses_and_are_kept_exactly():
    scene = make_box_scene(num_frames=T, height=H, width=W, num_tracks=16, seed=1, intrinsics=TRUE_K)
    edges = strided_window_pairs(T, window=3, stride=2)
    flows = build_flow("gt", scene=scene).flow(scene.rgb, [tuple(e) for e in edges])
    pw = GroundTruthPointmaps(scene).pointmaps(scene.rgb, edges)
    pw.pts_i[..., :2] *= 1.3  # a network that misjudges the field of view by 30 %
    pw.pts_j[..., :2] *= 1.3
    known = np.tile(_rows(TRUE_K), (T, 1)).astype(np.float32)  # (T,4)
    static = ~ground_truth_motion_masks(scene)
    for coarse in ([], ["optim.coarse_factor=2", "optim.coarse_iters=30"]):  # full size; coarse-to-fine
        cfg = load_config("c4d", "tiny", overrides=["graph.window=3", *coarse])
        estimated = opt.optimise(pw, T, cfg, flows=flows, static_masks=static)
        fixed = opt.optimise(pw, T, cfg, flows=flows, static_masks=static, intrinsics=known)
        ate_estimated = pose_metrics(estimated.cam_to_world, scene.cam_to_world)["ate"]
        ate_fixed = pose_metrics(fixed.cam_to_world, scene.cam_to_world)["ate"]
        print(f"{coarse}: ATE estimated intrinsics {ate_estimated:.4f}, known (fixed) {ate_fixed:.4f}")
        assert ate_fixed < 0.8 * ate_estimated
        np.testing.assert_allclose(_rows(fixed.intrinsics), known, rtol=1e-5)
        assert abs(estimated.intrinsics[0, 0, 0] / TRUE_K[0, 0] - 1) > 0.1  # what the pointmaps imply


def test_network_intrinsics_follow_the_resize_and_crop_and_the_source_frames():
    plan = plan_preprocessing((300, 400), 224)  # resize 300x400 -> 224x299, centre crop 224x224
    assert plan.resized_hw == (224, 299) and plan.crop_xy == (37, 0)
    rows = np.array([[500.0 + n, 480.0, 210.0, 140.0] for n in range(5)])  # one per source frame
    video = VideoInput(np.zeros((3, 224, 224, 3), np.uint8), np.array([0, 2, 4]), plan, None)
    got = network_intrinsics(rows, video, read_whole=True)
    s = np.array([299 / 400, 224 / 300])
    np.testing.assert_allclose(got[:, :2], rows[[0, 2, 4], :2] * s, rtol=1e-6)
    np.testing.assert_allclose(got[:, 2:], rescale_pixels(rows[[0, 2, 4], 2:], s) - [37, 0], rtol=1e-6)
    np.testing.assert_allclose(network_intrinsics(rows[:1], video, read_whole=True), got[[0, 0, 0]])


@pytest.fixture(scope="module")
def run_inputs(tmp_path_factory):
    """A 96x96 box-scene video (resized to 64x64, then cropped to 64x48 at --size 64) and a tiny
    random DUSt3R-layout checkpoint."""
    folder = tmp_path_factory.mktemp("c4d_intrinsics")
    video = write_video(folder / "video.mp4", make_box_scene(num_frames=6, height=96, width=96).rgb, fps=12)
    ckpt = folder / "dust3r_tiny.pth"
    torch.save({"model": tiny_network().state_dict(), "args": argparse.Namespace(model=ARGS)}, ckpt)
    return folder, video, ckpt


def _run(video, ckpt, out, *extra) -> int:
    return main(["run", str(video), *FAST, "--out", str(out), "--pointmaps", str(ckpt), "--size", "64",
                 "--preset", "tiny", *extra])


def test_run_writes_the_given_intrinsics_scaled_to_the_network_frames(run_inputs, tmp_path):
    folder, video, ckpt = run_inputs
    rows = np.array([[80.0 + n, 70.0, 45.0, 50.0] for n in range(6)])  # per source frame, 96x96 px
    table = tmp_path / "k.txt"
    np.savetxt(table, rows)
    assert _run(video, ckpt, tmp_path / "fixed", "--intrinsics", str(table), "--stride", "2") == 0
    # 96 -> 64: scale 2/3, then the 4:3 crop drops 8 rows at the top
    expected = np.stack([rows[:, 0] * 2 / 3, rows[:, 1] * 2 / 3, (rows[:, 2] + 0.5) * 2 / 3 - 0.5,
                         (rows[:, 3] + 0.5) * 2 / 3 - 0.5 - 8], -1)[[0, 2, 4]]
    np.testing.assert_allclose(_rows(np.load(tmp_path / "fixed/intrinsics.npy")), expected, rtol=1e-5)

    assert _run(video, ckpt, tmp_path / "init", "intrinsics.known=80,70,45,50", "--intrinsics-mode",
                "init") == 0
    got = _rows(np.load(tmp_path / "init/intrinsics.npy"))  # (6,4)
    start = np.array([80 * 2 / 3, 70 * 2 / 3, 45.5 * 2 / 3 - 0.5, 50.5 * 2 / 3 - 8.5])
    assert not np.allclose(got[:, 0], start[0], rtol=1e-4)  # the focal was optimised from there
    np.testing.assert_allclose(got[:, 1] / got[:, 0], 70 / 80, rtol=1e-5)  # fy/fx and the
    np.testing.assert_allclose(got[:, 2:], np.broadcast_to(start[2:], (6, 2)), rtol=1e-5)  # centre kept


@pytest.mark.parametrize("given, message", [
    ("1,2,3", "1x3 values; give 4 numbers a row"),
    ("0,70,45,50", "row 0 is 0 70 45 50; every value must be finite and the focal lengths fx, fy > 0"),
    ("80,-70,45,50", "focal lengths fx, fy > 0"),
    ("80,nan,45,50", "every value must be finite"),
    ("80,70,inf,50", "every value must be finite"),
    ("eighty", "not a file, nor numbers fx,fy,cx,cy"),
    ("three_columns.txt", "6x3 values; give 4 numbers a row"),
    ("five_rows.npy", "has 5 rows, but the video has 6 source frames"),
    ("words.txt", "could not convert"),
])
def test_bad_intrinsics_are_refused_with_one_line_before_anything_is_written(run_inputs, tmp_path, capsys,
                                                                             given, message):
    folder, video, ckpt = run_inputs
    np.savetxt(tmp_path / "three_columns.txt", np.ones((6, 3)))
    np.save(tmp_path / "five_rows.npy", np.ones((5, 4)))
    (tmp_path / "words.txt").write_text("fx fy cx cy\n")
    path = tmp_path / given
    assert _run(video, ckpt, tmp_path / "o", "--intrinsics", str(path) if path.exists() else given) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "o").exists()


def test_the_mode_is_a_checked_config_key(run_inputs, tmp_path, capsys):
    folder, video, ckpt = run_inputs
    assert _run(video, ckpt, tmp_path / "o", "intrinsics.known=80,70,45,50", "intrinsics.mode=free") == 2
    err = capsys.readouterr().err.strip()
    assert "intrinsics.mode" in err and len(err.splitlines()) == 1, err
