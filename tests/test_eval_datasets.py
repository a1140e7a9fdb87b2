"""Benchmark readers on tiny fake trees laid out like the public downloads."""

import cv2
import numpy as np
import pytest

from c4d_core.errors import UserError
from c4d_pipeline.eval_datasets import (SINTEL_TAG, associate, load_eval_dataset, read_sintel_camera,
                                        read_sintel_depth)


def write_rgb(path, value=0, hw=(6, 8)):
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.full((*hw, 3), value, np.uint8))


def write_depth_png(path, raw):
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.asarray(raw, np.uint16))


def test_sintel_binary_files_and_poses(tmp_path):
    root = tmp_path / "sintel"
    for t in range(3):
        write_rgb(root / "training/final/alley_2" / f"frame_{t + 1:04d}.png", t)
        K = np.array([[100.0, 0, 4], [0, 100, 3], [0, 0, 1]])
        world_to_cam = np.hstack([np.eye(3), [[-t], [0.0], [0.0]]])  # camera centre at x = t
        (root / "training/camdata_left/alley_2").mkdir(parents=True, exist_ok=True)
        with open(root / "training/camdata_left/alley_2" / f"frame_{t + 1:04d}.cam", "wb") as f:
            np.array([SINTEL_TAG], np.float32).tofile(f)
            np.concatenate([K.ravel(), world_to_cam.ravel()]).astype(np.float64).tofile(f)
        (root / "training/depth/alley_2").mkdir(parents=True, exist_ok=True)
        with open(root / "training/depth/alley_2" / f"frame_{t + 1:04d}.dpt", "wb") as f:
            np.array([SINTEL_TAG], np.float32).tofile(f)
            np.array([8, 6], np.int32).tofile(f)
            np.full(48, 30.0 * (t + 1), np.float32).tofile(f)  # 30, 60, 90 (beyond the cap of 70)
    (seq,) = load_eval_dataset("sintel", root)
    assert seq.name == "alley_2" and seq.num_frames == 3
    np.testing.assert_allclose(seq.cam_to_world[:, 0, 3], [-1, 0, 1])  # centres x = 0,1,2, mean-centred
    np.testing.assert_allclose(seq.intrinsics[0, 0, 0], 100.0)
    depth = seq.depths()
    assert depth.shape == (3, 6, 8) and depth[0, 0, 0] == 30 and depth[1, 0, 0] == 60 and depth[2].max() == 0
    assert seq.frames().shape == (3, 6, 8, 3)
    bad = tmp_path / "bad.dpt"
    bad.write_bytes(np.array([1.0], np.float32).tobytes())
    with pytest.raises(UserError, match="not a Sintel"):
        read_sintel_depth(bad)
    with pytest.raises(UserError, match="not a Sintel"):
        read_sintel_camera(bad)


def test_tum_association_stride_and_count(tmp_path):
    seq = tmp_path / "tum" / "rgbd_dataset_freiburg3_walking_xyz"
    stamps = 100.0 + 0.033 * np.arange(10)
    rgb_lines, gt_lines = ["# color images"], ["# ground truth trajectory"]
    for t, s in enumerate(stamps):
        write_rgb(seq / "rgb" / f"{s:.6f}.png", t)
        rgb_lines.append(f"{s:.6f} rgb/{s:.6f}.png")
        gt_lines.append(f"{s + 0.005:.4f} {t} 0 0 0 0 0 1")  # identity rotation, x = t
    gt_lines.append("200.0 99 0 0 0 0 0 1")  # unmatched pose
    (seq / "rgb.txt").write_text("\n".join(rgb_lines))
    (seq / "groundtruth.txt").write_text("\n".join(gt_lines))
    (seq_data,) = load_eval_dataset("tum", tmp_path / "tum")
    assert [p.name for p in seq_data.image_paths] == [f"{stamps[t]:.6f}.png" for t in (0, 3, 6, 9)]
    np.testing.assert_allclose(seq_data.cam_to_world[:, 0, 3], [0, 3, 6, 9])
    np.testing.assert_allclose(seq_data.cam_to_world[:, :3, :3], np.broadcast_to(np.eye(3), (4, 3, 3)))
    assert associate(np.array([0.0, 1.0]), np.array([1.01, 0.5, 0.015])) == [(0, 2), (1, 0)]


def test_scannet_first_frames_at_stride_three(tmp_path):
    scene = tmp_path / "scannet" / "scene0707_00"
    for i in range(8):
        write_rgb(scene / "color" / f"{i}.jpg", i)
        write_depth_png(scene / "depth" / f"{i}.png", np.full((6, 8), 1500 + i))
        pose = np.eye(4)
        pose[2, 3] = i
        (scene / "pose").mkdir(exist_ok=True)
        np.savetxt(scene / "pose" / f"{i}.txt", pose)
    (seq,) = load_eval_dataset("scannet", tmp_path / "scannet")
    assert [p.name for p in seq.image_paths] == ["0.jpg", "3.jpg", "6.jpg"]
    np.testing.assert_allclose(seq.cam_to_world[:, 2, 3], [0, 3, 6])
    np.testing.assert_allclose(seq.depths()[:, 0, 0], [1.5, 1.503, 1.506], rtol=1e-6)


def test_bonn_frame_window_and_kitti_depth_scale(tmp_path):
    seq = tmp_path / "bonn" / "rgbd_bonn_balloon2"
    for t in range(35):
        write_rgb(seq / "rgb" / f"{1000 + t:.6f}.png", t)
        write_depth_png(seq / "depth" / f"{1000 + t:.6f}.png", np.full((6, 8), 5000 * (t - 29)))
    (bonn,) = load_eval_dataset("bonn", tmp_path / "bonn")
    assert bonn.num_frames == 5 and bonn.image_paths[0].name == "1030.000000.png"
    np.testing.assert_allclose(bonn.depths()[:, 0, 0], [1, 2, 3, 4, 5])
    base = tmp_path / "kitti" / "depth_selection" / "val_selection_cropped"
    for t in range(3):
        write_rgb(base / "image_gathered" / "2011_09_26_drive_0002_sync_02" / f"{t:010d}.png", t)
        write_depth_png(base / "groundtruth_depth_gathered" / "2011_09_26_drive_0002_sync_02" / f"{t:010d}.png",
                        [[0, 256 * 80, 512]])
    (kitti,) = load_eval_dataset("kitti", tmp_path / "kitti")
    np.testing.assert_allclose(kitti.depths()[0], [[0, 80, 2]])  # no cap for KITTI


def test_wrong_layouts_name_the_expected_one(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(UserError, match="training/final"):
        load_eval_dataset("sintel", tmp_path / "empty")
    with pytest.raises(UserError, match="rgb.txt"):
        load_eval_dataset("tum", tmp_path / "empty")
    with pytest.raises(UserError, match="val_selection_cropped"):
        load_eval_dataset("kitti", tmp_path / "empty")
    with pytest.raises(UserError, match="unknown dataset"):
        load_eval_dataset("davis", tmp_path)
    write_rgb(tmp_path / "scannet" / "scene0001_00" / "color" / "0.jpg")
    with pytest.raises(UserError, match="pose"):
        load_eval_dataset("scannet", tmp_path / "scannet")
    with pytest.raises(UserError, match="not in the dataset"):
        load_eval_dataset("scannet", tmp_path / "scannet", sequences=["scene0707_00"])
