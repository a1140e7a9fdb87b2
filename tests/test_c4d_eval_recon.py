"""`c4d eval-recon` end to end on reconstruction directories of a generated scene."""

import json

import cv2
import numpy as np
import pytest

from c4d.cli import main
from c4d_pipeline.ground_truth import ground_truth_motion_masks
from c4d_pipeline.outputs import Reconstruction, write_reconstruction
from tests.synthetic_scenes import make_box_scene
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


def reconstruction(scene, frames=USED, depth_scale=3.0, hw=None, report=True):
    """The scene's truth for `frames` up to a similarity of the world (scale `depth_scale`)."""
    rot = cv2.Rodrigues(np.array([0.3, -0.2, 0.9]))[0]
    world = np.eye(4)
    world[:3, :3], world[:3, 3] = depth_scale * rot, [1.0, 2.0, 3.0]
    poses = world @ scene.cam_to_world[frames].astype(np.float64)
    poses[:, :3, :3] /= depth_scale  # a camera pose stays a rotation; only its centre is scaled
    depth = depth_scale * scene.depth[frames]
    masks = ground_truth_motion_masks(scene)[frames]
    if hw:
        depth = np.stack([cv2.resize(d, (hw[1], hw[0]), interpolation=cv2.INTER_NEAREST) for d in depth])
        masks = np.stack([cv2.resize(m.astype(np.uint8), (hw[1], hw[0]), interpolation=cv2.INTER_NEAREST) > 0 for m in masks])
    t, h, w = depth.shape
    rgb = np.stack([cv2.resize(f, (w, h), interpolation=cv2.INTER_AREA) for f in scene.rgb[frames]])
    return Reconstruction(
        frames=rgb, depth=depth.astype(np.float32), masks=masks,
        cam_to_world=poses.astype(np.float32), intrinsics=scene.intrinsics[frames],
        points=np.zeros((t, h, w, 3), np.float32), confidence=np.ones((t, h, w), np.float32),
        report={"inputs": {"frame_indices": list(frames)}} if report else {},
    )


def test_a_perfect_reconstruction_scores_perfectly(shard, tmp_path, capsys):
    path, scenes = shard
    out = write_reconstruction(reconstruction(scenes[1]), tmp_path / "out")
    code = main(["eval-recon", "--pred", str(out), "--gt", str(path), "--scene-index", "1", "--out", str(tmp_path / "m.json")])
    assert code == 0
    result = json.loads((tmp_path / "m.json").read_text())
    assert result["frame_indices"] == USED and result["frame_indices_from"] == "report.json"
    assert result["pose"]["ate"] < 1e-5 and result["pose"]["rpe_trans"] < 1e-5 and result["pose"]["rpe_rot"] < 1e-2
    assert result["pose"]["sim3_scale"] == pytest.approx(1 / 3.0, rel=1e-5)
    for mode in ("scale", "scale_shift"):
        assert result["depth"][mode]["abs_rel"] < 1e-5 and result["depth"][mode]["delta_1_25"] == 1.0
    assert result["mask"]["iou"] == 1.0 and result["mask"]["gt_dynamic_fraction"] > 0
    assert "ATE" in capsys.readouterr().out


def test_a_lower_resolution_reconstruction_is_compared_at_the_scenes_resolution(shard, tmp_path):
    path, scenes = shard
    out = write_reconstruction(reconstruction(scenes[0], frames=list(range(6)), hw=(12, 16), report=False), tmp_path / "out")
    assert main(["eval-recon", "--pred", str(out), "--gt", str(path)]) == 0
    result = json.loads((out / "eval_recon.json").read_text())  # default output path
    assert result["frame_indices"] == list(range(6)) and result["frame_indices_from"] == "all frames"
    assert result["resolution"] == {"reconstruction": [12, 16], "ground_truth": [24, 32]}
    assert result["pose"]["ate"] < 1e-5
    assert 0 < result["depth"]["scale"]["abs_rel"] < 0.1  # detail lost at half size, nothing more
    assert 0.5 < result["mask"]["iou"] < 1.0


def test_bad_inputs_are_one_line_errors(shard, tmp_path, capsys):
    path, scenes = shard
    assert main(["eval-recon", "--pred", str(tmp_path), "--gt", str(path)]) == 2
    assert "no poses_tum.txt" in capsys.readouterr().err
    out = write_reconstruction(reconstruction(scenes[0], report=False), tmp_path / "subset")
    assert main(["eval-recon", "--pred", str(out), "--gt", str(path)]) == 2
    assert "does not say which were used" in capsys.readouterr().err
    out = write_reconstruction(reconstruction(scenes[0]), tmp_path / "out")
    assert main(["eval-recon", "--pred", str(out), "--gt", str(path), "--scene-index", "5"]) == 2
    assert "fewer than 6 scenes" in capsys.readouterr().err
    other = write_reconstruction(reconstruction(scenes[1]), tmp_path / "other")
    assert main(["eval-recon", "--pred", str(other), "--gt", str(path)]) == 2
    assert "reconstructs another video" in capsys.readouterr().err
    wrong = reconstruction(scenes[0])
    wrong.report["inputs"]["source_hw"] = [64, 64]
    assert main(["eval-recon", "--pred", str(write_reconstruction(wrong, tmp_path / "w")),
                 "--gt", str(path)]) == 2
    assert "from a 64x64 video" in capsys.readouterr().err
    squeezed = write_reconstruction(reconstruction(scenes[0], frames=list(range(6)), hw=(33, 17),
                                                   report=False), tmp_path / "squeezed")
    assert main(["eval-recon", "--pred", str(squeezed), "--gt", str(path)]) == 2
    assert "aspect ratios differ" in capsys.readouterr().err
    (out / "depth" / "000003.npy").unlink()
    assert main(["eval-recon", "--pred", str(out), "--gt", str(path)]) == 2
    assert "4 poses, 3 depth maps" in capsys.readouterr().err


def write_sintel_sequence(root, name, scene, order=None):
    """`scene` (its frames in `order`, default all in order) in MPI Sintel's training layout:
    final/ frames, depth/ .dpt, camdata_left/ .cam."""
    from c4d_core.geometry import invert_pose
    from c4d_pipeline.eval_datasets import SINTEL_TAG

    for folder in ("final", "depth", "camdata_left"):
        (root / "training" / folder / name).mkdir(parents=True)
    h, w = scene.image_size
    for i, t in enumerate(range(scene.num_frames) if order is None else order):
        stem = f"frame_{i + 1:04d}"
        cv2.imwrite(str(root / "training/final" / name / f"{stem}.png"), scene.rgb[t][..., ::-1])
        with open(root / "training/depth" / name / f"{stem}.dpt", "wb") as f:
            np.array([SINTEL_TAG], np.float32).tofile(f)
            np.array([w, h], np.int32).tofile(f)
            scene.depth[t].astype(np.float32).tofile(f)
        world_to_cam = invert_pose(scene.cam_to_world[t].astype(np.float64))[:3]
        with open(root / "training/camdata_left" / name / f"{stem}.cam", "wb") as f:
            np.array([SINTEL_TAG], np.float32).tofile(f)
            np.concatenate([scene.intrinsics[t].ravel(), world_to_cam.ravel()]).astype(np.float64).tofile(f)


def test_a_benchmark_sequence_on_disk_is_scored_with_dataset_and_root(shard, tmp_path, capsys):
    _, scenes = shard
    root = tmp_path / "sintel"
    write_sintel_sequence(root, "alley_2", scenes[1], order=range(5, -1, -1))  # the same frames reversed
    write_sintel_sequence(root, "market_2", scenes[1])
    out = write_reconstruction(reconstruction(scenes[1], frames=list(range(6)), report=False), tmp_path / "out")
    assert main(["eval-recon", "--pred", str(out), "--dataset", "sintel", "--root", str(root),
                 "--sequence", "market_2"]) == 0
    result = json.loads((out / "eval_recon.json").read_text())
    assert result["dataset"] == "sintel" and result["sequence"] == "market_2"
    assert result["frame_indices"] == list(range(6)) and "mask" not in result  # a benchmark has no masks
    assert result["pose"]["ate"] < 1e-5 and result["pose"]["rpe_rot"] < 1e-2
    assert result["depth"]["scale"]["abs_rel"] < 1e-5
    assert "ATE" in capsys.readouterr().out
    # The other sequence is not this reconstruction: its depth scores far worse.
    assert main(["eval-recon", "--pred", str(out), "--dataset", "sintel", "--root", str(root),
                 "--sequence", "alley_2", "--out", str(tmp_path / "other.json")]) == 0
    other = json.loads((tmp_path / "other.json").read_text())
    assert other["depth"]["scale"]["abs_rel"] > 0.02, other["depth"]
    capsys.readouterr()
    for args, message in [(["--sequence", "cave_2"], "not in the dataset"),
                          ([], "has 2 sequences (alley_2, market_2); pick one with --sequence")]:
        assert main(["eval-recon", "--pred", str(out), "--dataset", "sintel", "--root", str(root), *args]) == 2
        assert message in capsys.readouterr().err
    assert main(["eval-recon", "--pred", str(out), "--dataset", "sintel"]) == 2
    assert "needs --root" in capsys.readouterr().err
