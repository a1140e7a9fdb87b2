"""The fault suite, training and checkpoint files: what a crash leaves behind is repaired, a damaged
checkpoint is set aside, and every unreadable checkpoint or folder given as one is one line.

- temporaries of a killed checkpoint write (`.step_XXXXXXXX.tmp<pid>.pt`) are deleted by the
  next run, fresh or resumed;
- a truncated newest checkpoint is renamed `*.pt.bad` on --resume, so that pruning keeps the good
  ones; `last.pt` is the last resort;
- `c4d pretrain-pointmaps` repairs its log like `c4d train` and refuses a damaged `last.pt` in one
  line;
- the reason a checkpoint cannot be read names what is wrong (Python objects; not a PyTorch file
  or truncated, with its size), never PyTorch's weights_only advice;
- a folder given as any checkpoint is named as a folder.
"""

from __future__ import annotations

import dataclasses
import io
import json
import logging
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from c4d.cli import main
from c4d_core.config import load_config
from c4d_core.errors import UserError
from c4d_core.video import write_image
from datagen.shards import ShardWriter, encode_scene, scene_key
from dynpt.checkpoint import FORMAT, save_checkpoint
from dynpt.model import build_model
from tests.dynpt_testdata import synthetic_scene, synthetic_shards
from tests.test_faults import ENV, ROOT, TRAIN, assert_one_line_error, log_lines, wait_for

pytestmark = pytest.mark.faults


def train_args(out: Path, *extra: str) -> list[str]:
    return ["train", *TRAIN, f"data.sources=[{synthetic_shards(12, 3)}]", f"train.out_dir={out}",
            *extra]


def cut_short(path: Path, size: int = 5000) -> None:
    """Replace `path` by a new file holding its first `size` bytes (a hard link to it, such as
    `last.pt`, keeps the whole file)."""
    data = path.read_bytes()
    path.unlink()
    path.write_bytes(data[:size])


# --- c4d train: temporaries and damaged checkpoints ---------------------------------------------


def test_temporaries_of_a_killed_checkpoint_write_are_removed_by_the_next_run(tmp_path, caplog):
    out = tmp_path / "run"
    ckpts = out / "checkpoints"
    ckpts.mkdir(parents=True)
    left = [ckpts / ".step_00000002.tmp999999.pt", ckpts / ".last.pt.tmp"]
    for path in left:
        path.write_bytes(b"half a checkpoint")
    assert main(train_args(out, "train.steps=4", "train.ckpt_every=2", "train.stop_after=2")) == 0
    assert not any(p.exists() for p in left)
    assert f"removing {left[0]}" in caplog.text
    left[0].write_bytes(b"half a checkpoint")  # killed again, then resumed
    assert main(train_args(out, "train.steps=4", "train.ckpt_every=2", "--resume")) == 0
    assert not left[0].exists()
    assert sorted(p.name for p in ckpts.iterdir()) == ["last.pt", "step_00000002.pt",
                                                       "step_00000004.pt"]


def test_a_truncated_newest_checkpoint_is_set_aside_so_pruning_keeps_the_good_one(tmp_path, caplog):
    """Checkpoints at 6 and 8, step 8 cut short; `--resume train.stop_after=1 train.keep_last=1`
    saves step 7 and prunes: step 7 must survive (the cut step 8 sorted as the newest before), so
    the next --resume continues. With every step checkpoint damaged, `last.pt` is used."""
    caplog.set_level(logging.INFO)
    out = tmp_path / "run"
    ckpts = out / "checkpoints"
    args = ["train.steps=8", "train.ckpt_every=6"]
    assert main(train_args(out, *args)) == 0
    assert sorted(p.name for p in ckpts.glob("step_*")) == ["step_00000006.pt", "step_00000008.pt"]
    (ckpts / "step_00000008.pt").write_bytes((ckpts / "step_00000008.pt").read_bytes()[:5000])
    caplog.clear()
    assert main(train_args(out, *args, "--resume", "train.stop_after=1", "train.keep_last=1")) == 0
    assert "skipping step_00000008.pt (renamed to step_00000008.pt.bad)" in caplog.text
    assert "not a PyTorch file, or truncated (5000 bytes)" in caplog.text
    assert sorted(p.name for p in ckpts.glob("step_*")) == ["step_00000007.pt", "step_00000008.pt.bad"]
    caplog.clear()
    assert main(train_args(out, *args, "--resume", "train.keep_last=1")) == 0
    assert "resumed" in caplog.text and "step_00000007.pt at step 7" in caplog.text
    # the only step checkpoint cut short (a new file: last.pt, a link to the old one, stays whole)
    cut_short(ckpts / "step_00000008.pt")
    caplog.clear()
    assert main(train_args(out, "train.steps=9", "train.ckpt_every=6", "--resume")) == 0
    assert "skipping step_00000008.pt" in caplog.text and "last.pt at step 8" in caplog.text
    assert [r["step"] for r in log_lines(out)] == list(range(1, 10))
    assert (ckpts / "step_00000009.pt").is_file()


# --- unreadable checkpoints: the reason ---------------------------------------------------------


def damage(path: Path, kind: str) -> None:
    """Overwrite the checkpoint `path` in place (its hard links too) with a damaged one."""
    if kind == "random-bytes":
        path.write_bytes(np.random.default_rng(0).integers(0, 256, 3000, np.uint8).tobytes())
    elif kind == "truncated":
        path.write_bytes(path.read_bytes()[:5000])
    else:  # a dict with a Python object inside: the tensor-only unpickler refuses to build it
        buffer = io.BytesIO()
        torch.save({"format": FORMAT, "x": io.BytesIO()}, buffer)
        path.write_bytes(buffer.getvalue())


REASONS = {"random-bytes": "not a PyTorch file, or truncated (3000 bytes)",
           "truncated": "not a PyTorch file, or truncated (5000 bytes)",
           "python-object": "it holds Python objects other than tensors and plain values (_io.BytesIO)"}


def assert_clean(text: str) -> None:
    for word in ("weights_only", "\x1b[", "Errno", "Unsupported operand", "PytorchStreamReader"):
        assert word not in text, text[-2000:]


@pytest.fixture(scope="module")
def tracker_inputs(tmp_path_factory):
    """A DynPT checkpoint, a folder of three 32x32 frames and a 2-step run (checkpoint at 2)."""
    folder = tmp_path_factory.mktemp("track-inputs")
    ckpt = save_checkpoint(folder / "tiny.pt", build_model(load_config("dynpt", "tiny-cpu").model), 0)
    frames = folder / "frames"
    frames.mkdir()
    for t in range(3):
        write_image(frames / f"{t:03d}.png", np.full((32, 32, 3), 60 * t, np.uint8))
    run = folder / "run"
    assert main(train_args(run, "train.steps=4", "train.ckpt_every=2", "train.stop_after=2")) == 0
    return {"ckpt": ckpt, "frames": frames, "run": run}


@pytest.mark.parametrize("kind", sorted(REASONS))
def test_an_unreadable_checkpoint_says_why_for_track_and_resume(tmp_path, capsys, caplog,
                                                                tracker_inputs, kind):
    ckpt = tmp_path / "model.pt"
    shutil.copyfile(tracker_inputs["ckpt"], ckpt)
    damage(ckpt, kind)
    code = main(["track", str(tracker_inputs["frames"]), "--ckpt", str(ckpt), "--out",
                 str(tmp_path / "t")])
    err = capsys.readouterr().err
    assert_one_line_error(code, err, str(ckpt), REASONS[kind])
    assert_clean(err)
    run = tmp_path / "run"
    shutil.copytree(tracker_inputs["run"], run)
    for name in ("step_00000002.pt", "last.pt"):  # copytree made last.pt a file of its own
        damage(run / "checkpoints" / name, kind)
    caplog.clear()
    code = main(train_args(run, "train.steps=4", "train.ckpt_every=2", "--resume"))
    err = capsys.readouterr().err
    assert_one_line_error(code, err, "no readable checkpoint", "without --resume")
    assert "skipping step_00000002.pt" in caplog.text and REASONS[kind] in caplog.text
    assert_clean(caplog.text + err)
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["last.pt.bad",
                                                                       "step_00000002.pt.bad"]


def test_random_bytes_as_dust3r_weights_are_not_unpickled(tmp_path, caplog):
    from dynpt.dust3r.checkpoint import read_checkpoint

    path = tmp_path / "dust3r.pth"
    damage(path, "random-bytes")
    with pytest.raises(UserError, match=r"not a PyTorch file, or truncated \(3000 bytes\)") as info:
        read_checkpoint(path)
    assert "full unpickler" not in caplog.text  # not loaded as "holding Python objects"
    assert_clean(str(info.value))


# --- a folder as a checkpoint -------------------------------------------------------------------


def test_a_folder_given_as_any_checkpoint_is_named_as_a_folder(tmp_path, capsys, tracker_inputs):
    from c4d_pipeline.raft import load_raft
    from dynpt.cotracker3_weights import read_state
    from dynpt.dust3r.checkpoint import read_checkpoint
    from dynpt.inference import load_tracker

    folder = tmp_path / "weights"
    folder.mkdir()
    (folder / "model.pth").write_bytes(b"")
    for read in (read_checkpoint, load_raft, read_state, load_tracker):
        with pytest.raises(UserError, match="is a folder, not a file .it holds model.pth.; pass "
                                            "the checkpoint file inside it"):
            read(folder)
    for override in (f"model.init_from=cotracker3:{folder}", f"model.encoder_3d.checkpoint={folder}"):
        code = main(train_args(tmp_path / "run", "train.steps=3", override))
        assert_one_line_error(code, capsys.readouterr().err, str(folder), "is a folder, not a file")


# --- c4d pretrain-pointmaps: the same repairs ---------------------------------------------------

POINTMAPS = ["--config", "tiny-cpu", "model.enc_embed_dim=16", "model.enc_depth=1",
             "model.dec_embed_dim=16", "model.dec_depth=1", "model.patch_size=8",
             "train.batch_size=2", "train.log_every=1", "train.steps=6"]


@pytest.fixture(scope="module")
def depth_shards(tmp_path_factory):
    """Two synthetic 32x32 scenes with a constant depth (pointmap training needs depth)."""
    out = tmp_path_factory.mktemp("depth-shards")
    with ShardWriter(out / "train-000000.tar") as writer:
        for i in range(2):
            scene = dataclasses.replace(synthetic_scene(i), depth=np.full((10, 32, 32), 2.0 + i, np.float32))
            writer.write(encode_scene(scene, scene_key("train", i)))
    return out


def pointmaps(out: Path, shards: Path, *extra: str) -> list[str]:
    return ["pretrain-pointmaps", *POINTMAPS, f"data.sources=[{shards}]", f"train.out_dir={out}",
            *extra]


def test_pointmap_training_killed_before_its_first_checkpoint_reruns_without_duplicates(
        tmp_path, depth_shards):
    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "c4d", *pointmaps(out, depth_shards,
                             "train.steps=100000", "train.ckpt_every=100000")],
                            env=ENV, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    log = out / "log.jsonl"
    wait_for(lambda: (log.exists() and log.read_text().count("\n") >= 2) or proc.poll() is not None,
             200, "two log lines")
    proc.kill()
    _, err = proc.communicate()
    assert not (out / "last.pt").exists(), err[-2000:]
    assert main(pointmaps(out, depth_shards, "train.steps=3")) == 0
    assert [r["step"] for r in log_lines(out)] == [1, 2, 3]


def test_pointmap_training_resume_drops_a_torn_line_and_refuses_a_damaged_state(
        tmp_path, capsys, caplog, depth_shards):
    out = tmp_path / "run"
    assert main(pointmaps(out, depth_shards, "train.stop_after=2")) == 0
    with open(out / "log.jsonl", "a") as f:  # a step past the checkpoint, then a torn line
        f.write(json.dumps({"step": 3, "loss": 1.0}) + '\n{"step": 4, "lo')
    assert main(pointmaps(out, depth_shards, "train.stop_after=1", "--resume")) == 0
    assert "torn last line" in caplog.text
    lines = (out / "log.jsonl").read_text()
    assert lines.endswith("\n") and [r["step"] for r in log_lines(out)] == [1, 2, 3]
    assert log_lines(out)[2]["loss"] != 1.0  # step 3 of the resumed run, not the dropped line
    state = out / "last.pt"
    state.write_bytes(state.read_bytes()[: os.path.getsize(state) // 2])
    code = main(pointmaps(out, depth_shards, "--resume"))
    err = capsys.readouterr().err
    assert_one_line_error(code, err, str(state), "not a PyTorch file, or truncated",
                          "without --resume")
    assert_clean(err)
