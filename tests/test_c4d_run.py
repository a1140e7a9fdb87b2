"""`c4d run` end to end on a short generated video with tiny random-weight networks."""

import argparse
import json

import cv2
import numpy as np
import pytest
import torch

from c4d.cli import main
from c4d_core.config import load_config
from c4d_pipeline.video_input import dust3r_resize, load_video_input, plan_preprocessing
from datagen.generate import generate_scene
from dynpt.checkpoint import save_checkpoint
from dynpt.dust3r.net import Dust3rConfig, Dust3rNet
from dynpt.model import build_model
from c4d_core.video import write_video

TINY_NET = Dust3rConfig(enc_embed_dim=32, enc_depth=2, enc_num_heads=2, dec_embed_dim=32, dec_depth=2,
                        dec_num_heads=2, head_type="linear", img_size=512)
ARGS = ("AsymmetricCroCo3DStereo(pos_embed='RoPE100', img_size=(512, 512), head_type='linear', "
        "output_mode='pts3d', depth_mode=('exp', -inf, inf), conf_mode=('exp', 1, inf), enc_embed_dim=32, "
        "enc_depth=2, enc_num_heads=2, dec_embed_dim=32, dec_depth=2, dec_num_heads=2)")
FAST = ["graph.window=2", "optim.stage1_iters=4", "optim.stage2_iters=2", "pts.window=4", "pts.extend=1"]


def make_inputs(folder, frames=8, size=64):
    """A generated MOVi-E video (mp4) and a tiny DUSt3R-layout checkpoint with random weights."""
    cfg = load_config("datagen", "movi-e", overrides=[f"resolution=[{size},{size}]", f"frames={frames}",
                                                      "tracks.num_points=16"])
    video = write_video(folder / "video.mp4", generate_scene(cfg, 0).rgb, fps=12)
    ckpt = folder / "dust3r_tiny.pth"
    torch.save({"model": tiny_network().state_dict(), "args": argparse.Namespace(model=ARGS)}, ckpt)
    return video, ckpt


def tiny_network(seed=0) -> Dust3rNet:
    """Random weights, with head biases that put points in front of the camera, spread like a
    pinhole camera's rays within each 16x16 patch (a random network has no notion of where a
    patch is; without this its pointmaps imply no positive focal length)."""
    torch.manual_seed(seed)
    net = Dust3rNet(TINY_NET)
    v, u = torch.meshgrid(torch.arange(16.0), torch.arange(16.0), indexing="ij")
    with torch.no_grad():
        for head in (net.downstream_head1, net.downstream_head2):
            head.proj.weight.mul_(0.05)
            bias = head.proj.bias.view(4, 16, 16)  # channel-major blocks of p*p values: x, y, z, conf
            bias[0], bias[1], bias[2], bias[3] = 0.05 * (u - 7.5), 0.05 * (v - 7.5), 2.0, 0.0
    return net


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("c4d_run")
    video, ckpt = make_inputs(folder)
    torch.manual_seed(0)
    tracker = save_checkpoint(folder / "dynpt_tiny.pt",
                              build_model(load_config("dynpt/model", "tiny").model), step=0)
    return folder, video, ckpt, tracker


def test_preprocessing_follows_dust3r_sizes():
    for source, size, expected in [((480, 640), 512, (384, 512)), ((480, 854), 512, (288, 512)),
                                   ((436, 1024), 512, (208, 512)), ((375, 1242), 512, (144, 512)),
                                   ((512, 512), 512, (384, 512)), ((480, 640), 224, (224, 224)),
                                   ((64, 64), 64, (48, 64))]:
        assert plan_preprocessing(source, size).output_hw == expected, (source, size)
    frames = np.zeros((1, 40, 80, 3), np.uint8)
    frames[0, :, 40:] = 255  # right half white
    out, plan = dust3r_resize(frames, 64)
    assert out.shape == (1, 32, 64, 3) and plan.crop_xy == (0, 0)
    assert out[0, :, :30].max() < 30 and out[0, :, 34:].min() > 225
    # Intrinsics follow the resize: the principal point of the source centre lands on the output centre.
    K = plan.intrinsics(np.array([[100.0, 0, 39.5], [0, 100, 19.5], [0, 0, 1]]))
    np.testing.assert_allclose(K[:2, 2], [31.5, 15.5])
    np.testing.assert_allclose(K[0, 0], 80.0)


def test_run_writes_every_output_of_the_contract(inputs, tmp_path):
    folder, video, ckpt, tracker = inputs
    out = tmp_path / "out"
    code = main(["run", str(video), *FAST, "--out", str(out), "--pointmaps", str(ckpt), "--tracker", str(tracker),
                 "--size", "64", "--preset", "tiny", "--grid-size", "16"])
    assert code == 0
    T = 8
    for name in [f"frames/{T - 1:06d}.png", "depth/000000.npy", "depth/000000.png", "masks/000000.png",
                 "poses_tum.txt", "intrinsics.npy", "pointmaps.npz", "tracks_2d.npz", "tracks_3d.npz",
                 "scene.ply", "report.json", "config.yaml"]:
        assert (out / name).is_file(), name
    assert cv2.imread(str(out / "frames/000000.png")).shape == (48, 64, 3)
    assert np.load(out / "depth/000000.npy").shape == (48, 64)
    assert np.load(out / "intrinsics.npy").shape == (T, 3, 3)
    points = np.load(out / "pointmaps.npz")
    assert points["points"].shape == (T, 48, 64, 3) and (points["confidence"] >= 1).all()
    assert np.load(out / "tracks_3d.npz")["tracks_world"].shape[0] == T
    assert len((out / "poses_tum.txt").read_text().splitlines()) == T
    report = json.loads((out / "report.json").read_text())
    assert report["inputs"]["motion_masks"] == "dynpt+flow"
    assert report["inputs"]["frame_indices"] == list(range(T))
    assert report["inputs"]["pointmap_source"] == "Dust3rPointmaps"


def test_run_without_tracker_uses_flow_only_masks(inputs, tmp_path, caplog):
    folder, video, ckpt, _ = inputs
    out = tmp_path / "out"
    with caplog.at_level("WARNING"):
        code = main(["run", str(video), *FAST, "--out", str(out), "--pointmaps", str(ckpt), "--size", "64",
                     "--preset", "tiny", "--stride", "2"])
    assert code == 0
    assert "no --tracker given" in caplog.text
    report = json.loads((out / "report.json").read_text())
    assert report["inputs"]["motion_masks"] == "flow-only" and report["inputs"]["frame_indices"] == [0, 2, 4, 6]
    assert not (out / "tracks_3d.npz").exists() or np.load(out / "tracks_3d.npz")["tracks_world"].size == 0


def test_bad_inputs_fail_fast_with_one_line(inputs, tmp_path, capsys):
    folder, video, ckpt, _ = inputs
    corrupt = tmp_path / "corrupt.mp4"
    corrupt.write_bytes(np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    truncated = tmp_path / "truncated.mp4"
    truncated.write_bytes(video.read_bytes()[: video.stat().st_size // 3])
    cases = [
        (["run", str(video), "--out", str(tmp_path / "o"), "--pointmaps", str(tmp_path / "none.pth")], "does not exist"),
        (["run", str(video), "--out", str(tmp_path / "o"), "--pointmaps", str(ckpt), "--tracker", "x.pt"], "tracker checkpoint"),
        (["run", str(video), "--out", str(tmp_path / "o"), "--pointmaps", str(folder)], "is a folder, not a file"),
        (["run", str(video), "--out", str(tmp_path / "o"), "--pointmaps", str(ckpt), "--tracker", str(folder)], "is a folder"),
        (["run", str(video), "--out", str(tmp_path / "o"), "--pointmaps", str(video)], "cannot read checkpoint"),
        (["run", str(corrupt), "--out", str(tmp_path / "o"), "--pointmaps", str(ckpt), "--size", "64"], "corrupt"),
        (["run", str(truncated), "--out", str(tmp_path / "o"), "--pointmaps", str(ckpt), "--size", "64"], "truncated"),
        (["run", str(video), "optim.nope=1", "--out", str(tmp_path / "o"), "--pointmaps", str(ckpt)], "unknown config key"),
        (["run", str(video), "--out", str(tmp_path / "o"), "--pointmaps", str(ckpt), "--flow", "raft:none.pth"], "RAFT weights"),
        (["run", str(video), "--out", str(tmp_path / "o"), "--pointmaps", str(ckpt), "--flow", f"raft:{folder}"], "is a folder, not a file"),
    ]
    for argv, message in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert message in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "o").exists()


def test_video_folder_input_with_frame_limit(inputs, tmp_path):
    folder, video, _, _ = inputs
    frames_dir = tmp_path / "frames"
    frames_dir.mkdir()
    for t, frame in enumerate(load_video_input(video, size=64).frames):
        cv2.imwrite(str(frames_dir / f"{t:03d}.png"), frame[..., ::-1])
    loaded = load_video_input(frames_dir, size=64, max_frames=3)
    assert loaded.frames.shape == (3, 48, 64, 3) and loaded.source_indices.tolist() == [0, 1, 2]


def test_poses_timestamps_are_source_frame_times(inputs, tmp_path):
    folder, video, ckpt, _ = inputs
    out = tmp_path / "out"
    assert main(["run", str(video), *FAST, "--out", str(out), "--pointmaps", str(ckpt), "--size", "64",
                 "--preset", "tiny", "--stride", "2"]) == 0
    stamps = np.loadtxt(out / "poses_tum.txt", ndmin=2)[:, 0]
    np.testing.assert_allclose(stamps, np.array([0, 2, 4, 6]) / 12, atol=1e-6)  # the video is 12 fps


def test_a_diverging_pointmap_network_is_one_line_naming_its_outputs(inputs, tmp_path, capsys):
    """A network whose points lie behind the camera (as a weakly trained one's often do) makes the
    optimisation non-finite: one line that names the pointmap statistics and what to try."""
    folder, video, _, tracker = inputs
    net = tiny_network()
    with torch.no_grad():
        for head in (net.downstream_head1, net.downstream_head2):
            head.proj.bias.view(4, 16, 16)[2] = -2.0  # z < 0 everywhere
    ckpt = tmp_path / "behind.pth"
    torch.save({"model": net.state_dict(), "args": argparse.Namespace(model=ARGS)}, ckpt)
    for extra in ([], ["--tracker", str(tracker)], ["--flow", "dis:fast", "--stride", "2"]):
        argv = ["run", str(video), *FAST, "--out", str(tmp_path / "o"), "--pointmaps", str(ckpt),
                "--size", "64", "--preset", "tiny", *extra]
        assert main(argv) == 2, extra
        err = capsys.readouterr().err
        errors = [l for l in err.splitlines() if "c4d: error" in l]  # besides progress bars
        assert len(errors) == 1 and "Traceback" not in err, err
        assert "pointmap network" in errors[0] and "behind the camera" in errors[0], err
        assert "Try a better-trained network" in errors[0]


def test_one_yaml_file_holds_a_whole_run(inputs, tmp_path, capsys):
    """Every flag is a config key: a YAML file alone sets checkpoints, size, grid and flow, and the
    output folder keeps the resolved config."""
    folder, video, ckpt, tracker = inputs
    run_yaml = tmp_path / "run.yaml"
    run_yaml.write_text(
        "_base_: c4d/tiny\n"  # a shipped preset by name
        f"pointmaps: {{checkpoint: {ckpt}, size: 64}}\ntracker: {{checkpoint: {tracker}, grid_size: 16}}\n"
        "graph: {window: 2}\noptim: {stage1_iters: 4, stage2_iters: 2}\npts: {window: 4, extend: 1}\n")
    out = tmp_path / "out"
    assert main(["run", str(video), "--out", str(out), "--preset", str(run_yaml)]) == 0
    kept = load_config("c4d", out / "config.yaml")
    assert kept.pointmaps.checkpoint == str(ckpt) and kept.tracker.grid_size == 16
    assert kept.optim.stage1_iters == 4 and kept.optim.stage2_iters == 2  # tiny's keys under the file's
    report = json.loads((out / "report.json").read_text())
    assert report["inputs"]["motion_masks"] == "dynpt+flow" and report["config"] == dict(kept)
    # `flow=` is read (it was dead before: only --flow counted), also from a --config file.
    bad_flow = tmp_path / "flow.yaml"
    bad_flow.write_text("flow: raft:none.pth\n")
    for argv in (["flow=raft:none.pth"], ["--config", str(bad_flow)]):
        assert main(["run", str(video), "--out", str(tmp_path / "o"), "--preset", str(run_yaml), *argv]) == 2
        assert "RAFT weights" in capsys.readouterr().err
    # A key set by its flag and by key=value at once is refused.
    assert main(["run", str(video), "--out", str(tmp_path / "o"), "--pointmaps", str(ckpt),
                 f"pointmaps.checkpoint={ckpt}"]) == 2
    assert "set both by a flag" in capsys.readouterr().err
    assert main(["run", str(video), "--out", str(tmp_path / "o")]) == 2
    assert "no pointmap checkpoint" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_out_of_gpu_memory_advises_a_real_setting(inputs, monkeypatch):
    """The advice names `c4d run`'s own flag and key (it said `--device`, which `c4d run` lacks)."""
    from c4d_core.errors import UserError
    from c4d_core.schema import RULES
    from c4d_pipeline.cli_run import add_arguments
    from c4d_pipeline.dust3r_pointmaps import Dust3rPointmaps

    _, video, ckpt, _ = inputs
    source = Dust3rPointmaps.from_checkpoint(ckpt, "cpu", batch_size=1)

    def out_of_memory(*_):
        raise torch.cuda.OutOfMemoryError("CUDA out of memory")

    monkeypatch.setattr(source, "_run", out_of_memory)
    frames = load_video_input(video, size=64, max_frames=2).frames
    with pytest.raises(UserError) as error:
        source.pointmaps(frames, np.array([[0, 1]]))
    message = str(error.value)
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    flags = {flag for action in parser._actions for flag in action.option_strings}
    assert "device=cpu" in message and "device" in RULES["c4d"]
    assert all(word in flags for word in message.replace("(", " ").split() if word.startswith("--"))


def test_too_few_frames_or_a_huge_size_are_refused_before_anything_is_written(inputs, tmp_path, capsys):
    """One frame left (`--stride 100` of 8, `--max-frames 1`), a graph that cannot connect the
    frames, or `--size 100000` (a numpy ArrayMemoryError traceback): one line and no OUT (the
    one-frame case was refused only after OUT/config.yaml was written)."""
    folder, video, ckpt, _ = inputs
    out = tmp_path / "out"
    base = ["run", str(video), "--out", str(out), "--pointmaps", str(ckpt), "--preset", "tiny"]
    for extra, message in [(["--size", "64", "--stride", "100"], "gives 1 frame(s) at video.stride=100"),
                           (["--size", "64", "--max-frames", "1"], "`video.max_frames` = 1 is out of range"),
                           (["--size", "64", "--max-frames", "2", "graph.start=2"], "does not connect all 2 frames"),
                           (["--size", "100000"], "`pointmaps.size` = 100000 is out of range")]:
        assert main([*base, *extra]) == 2, extra
        err = capsys.readouterr().err
        errors = [line for line in err.splitlines() if "c4d: error" in line]
        assert len(errors) == 1 and message in errors[0] and "Traceback" not in err, err
        assert not out.exists(), extra
