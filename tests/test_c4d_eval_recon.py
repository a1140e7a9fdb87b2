"""`c4d eval-recon` end to end on a hand-written reconstruction directory of a generated scene."""

import json

import cv2
import numpy as np
import pytest

from c4d.cli import main
from c4d_pipeline.motion_mask import ground_truth_motion_masks
from c4d_pipeline.synthetic import make_box_scene
from datagen.geometry import matrix_to_quat
from datagen.shards import ShardWriter, encode_scene, scene_key

USED = [0, 2, 3, 5]  # the reconstruction skips frames 1 and 4


@pytest.fixture(scope="module")
def shard(tmp_path_factory):
    scenes = [make_box_scene(num_frames=6, height=24, width=32, num_tracks=16, seed=s) for s in (0, 1)]
    path = tmp_path_factory.mktemp("shards") / "test-000000.tar"
    with ShardWriter(path) as writer:
        for index, scene in enumerate(scenes):
            writer.write(encode_scene(scene, scene_key("test", index)))
    return path, scenes


def write_reconstruction(out, scene, depth_scale=3.0, report=True, hw=None):
    """A perfect reconstruction up to a similarity (rotation, shift, scale 1/depth_scale... of the
    world) and a depth scale, of frames USED, optionally at another resolution."""
    (out / "depth").mkdir(parents=True)
    (out / "masks").mkdir()
    rot = cv2.Rodrigues(np.array([0.3, -0.2, 0.9]))[0]
    lines = []
    for n, t in enumerate(USED):
        pose = scene.cam_to_world[t].astype(np.float64)
        centre = depth_scale * rot @ pose[:3, 3] + [1.0, 2.0, 3.0]
        qw, qx, qy, qz = matrix_to_quat(rot @ pose[:3, :3])
        lines.append(f"{t} {centre[0]} {centre[1]} {centre[2]} {qx} {qy} {qz} {qw}")
        depth = depth_scale * scene.depth[t]
        mask = ground_truth_motion_masks(scene)[t].astype(np.uint8) * 255
        if hw:
            depth = cv2.resize(depth, (hw[1], hw[0]), interpolation=cv2.INTER_NEAREST)
            mask = cv2.resize(mask, (hw[1], hw[0]), interpolation=cv2.INTER_NEAREST)
        np.save(out / "depth" / f"{n:06d}.npy", depth.astype(np.float32))
        cv2.imwrite(str(out / "masks" / f"{n:06d}.png"), mask)
    (out / "poses_tum.txt").write_text("\n".join(lines) + "\n")
    np.save(out / "intrinsics.npy", scene.intrinsics[USED])
    if report:
        (out / "report.json").write_text(json.dumps({"inputs": {"frame_indices": USED}}))


def test_a_perfect_reconstruction_scores_perfectly(shard, tmp_path, capsys):
    path, scenes = shard
    write_reconstruction(tmp_path / "out", scenes[1])
    code = main(["eval-recon", "--pred", str(tmp_path / "out"), "--gt", str(path), "--scene-index", "1",
                 "--out", str(tmp_path / "metrics.json")])
    assert code == 0
    result = json.loads((tmp_path / "metrics.json").read_text())
    assert result["frame_indices"] == USED and result["frame_indices_from"] == "report.json"
    assert result["pose"]["ate"] < 1e-5 and result["pose"]["rpe_trans"] < 1e-5 and result["pose"]["rpe_rot"] < 1e-2
    assert result["pose"]["sim3_scale"] == pytest.approx(1 / 3.0, rel=1e-5)
    for mode in ("scale", "scale_shift"):
        assert result["depth"][mode]["abs_rel"] < 1e-5 and result["depth"][mode]["delta_1_25"] == 1.0
    assert result["mask"]["iou"] == 1.0 and result["mask"]["gt_dynamic_fraction"] > 0
    assert "ATE" in capsys.readouterr().out


def test_a_lower_resolution_reconstruction_is_compared_at_the_scenes_resolution(shard, tmp_path):
    path, scenes = shard
    write_reconstruction(tmp_path / "out", scenes[1], report=False, hw=(12, 16))
    assert main(["eval-recon", "--pred", str(tmp_path / "out"), "--gt", str(path), "--scene-index", "1"]) == 0
    result = json.loads((tmp_path / "out" / "eval_recon.json").read_text())  # default output path
    assert result["frame_indices"] == USED and result["frame_indices_from"] == "poses_tum.txt timestamps"
    assert result["resolution"] == {"reconstruction": [12, 16], "ground_truth": [24, 32]}
    assert result["pose"]["ate"] < 1e-5
    assert 0 < result["depth"]["scale"]["abs_rel"] < 0.1  # detail lost at half size, nothing more
    assert 0.5 < result["mask"]["iou"] < 1.0


def test_bad_inputs_are_one_line_errors(shard, tmp_path, capsys):
    path, scenes = shard
    assert main(["eval-recon", "--pred", str(tmp_path), "--gt", str(path)]) == 2
    assert "no poses_tum.txt" in capsys.readouterr().err
    write_reconstruction(tmp_path / "out", scenes[0])
    assert main(["eval-recon", "--pred", str(tmp_path / "out"), "--gt", str(path), "--scene-index", "5"]) == 2
    assert "fewer than 6 scenes" in capsys.readouterr().err
    (tmp_path / "out" / "depth" / "000003.npy").unlink()
    assert main(["eval-recon", "--pred", str(tmp_path / "out"), "--gt", str(path)]) == 2
    assert "4 poses but 3 depth" in capsys.readouterr().err
