"""DynPT training: a tiny model learns on tiny shards; resume reproduces the uninterrupted run."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from c4d.cli import main
from c4d_core.config import load_config
from c4d_core.errors import UserError
from dynpt.checkpoint import load_checkpoint
from dynpt.train import accumulation_steps, train
from tests.dynpt_testdata import generated_shards, synthetic_shards


def _cfg(out_dir, shards, *extra):
    return load_config("dynpt", "tiny-cpu", overrides=[
        f"data.sources=[{shards}]", f"train.out_dir={out_dir}", "data.crop_size=[32,32]",
        "data.num_frames=6", "data.num_tracks=12", "train.total_batch=2", "train.batch_size=1",
        "train.log_every=2", "eval.every=0", *extra])


def _log(out_dir):
    return [json.loads(line) for line in (Path(out_dir) / "log.jsonl").read_text().splitlines()]


def test_resume_continues_the_same_run(tmp_path):
    """6 steps in one go == 3 steps, stop, --resume 3 more (same data, same losses)."""
    shards = synthetic_shards(12, 3)
    train(_cfg(tmp_path / "full", shards, "train.steps=6", "train.ckpt_every=3"))
    train(_cfg(tmp_path / "split", shards, "train.steps=6", "train.ckpt_every=3",
               "train.stop_after=3"))
    assert [r["step"] for r in _log(tmp_path / "split")] == [1, 2, 3]
    with pytest.raises(UserError, match="--resume"):
        train(_cfg(tmp_path / "split", shards, "train.steps=6"))
    train(_cfg(tmp_path / "split", shards, "train.steps=6", "train.ckpt_every=3"), resume=True)
    full, split = _log(tmp_path / "full"), _log(tmp_path / "split")
    assert [r["step"] for r in split] == list(range(1, 7))
    for a, b in zip(full, split):
        assert a["lr"] == pytest.approx(b["lr"])
        for key in ("total", "track_visible", "visibility", "mobility"):
            assert a[key] == pytest.approx(b[key], rel=1e-4, abs=1e-6), (a["step"], key)
    ckpts = sorted(p.name for p in (tmp_path / "split" / "checkpoints").glob("step_*.pt"))
    assert ckpts == ["step_00000003.pt", "step_00000006.pt"]
    ckpt = load_checkpoint(tmp_path / "split" / "checkpoints" / "step_00000006.pt")
    assert ckpt["step"] == 6 and {"optimizer", "scheduler", "rng", "data"} <= set(ckpt["extra"])
    a = torch.load(tmp_path / "full" / "checkpoints" / "step_00000006.pt", weights_only=True)
    for key, value in a["model"].items():
        torch.testing.assert_close(value, ckpt["model"][key], rtol=1e-4, atol=1e-5)


def test_total_batch_must_split_evenly():
    assert accumulation_steps(32, 1, 8) == 4
    with pytest.raises(UserError, match="total_batch"):
        accumulation_steps(32, 3, 2)


def _balanced_d_acc(out_dir):
    """Mean of D-ACC on moving and on static points, read from the eval JSON (chance: 0.5)."""
    s = json.loads((out_dir / "eval.json").read_text())["summary"]
    return 0.5 * (s["d_acc_moving"] + s["d_acc_static"]), s


def test_tiny_model_learns_on_generated_shards(tmp_path):
    """Loss falls and mobility is learned well above chance on the training scenes."""
    shards = generated_shards()
    run = tmp_path / "run"
    cfg = load_config("dynpt", "tiny-cpu", overrides=[
        f"data.sources=[{shards}]", f"eval.source={shards}", f"train.out_dir={run}",
        "train.steps=120", "train.ckpt_every=60", "train.keep_last=1", "eval.every=60",
        "eval.num_tracks=64", "train.total_batch=2", "train.batch_size=2", "data.num_tracks=32"])
    train(cfg)
    log = _log(run)
    assert np.mean([r["total"] for r in log[-15:]]) < 0.8 * np.mean([r["total"] for r in log[:5]])
    assert [p.name for p in (run / "checkpoints").glob("step_*.pt")] == ["step_00000120.pt"]
    assert (run / "checkpoints" / "best.pt").exists()
    assert list((run / "tb").glob("events.out.tfevents.*"))
    out = tmp_path / "eval"
    assert main(["eval", "--ckpt", str(run / "checkpoints" / "step_00000120.pt"), "--data",
                 str(shards), "--config", "tiny-cpu", "--out", str(out),
                 "eval.resolution=[64,64]", "eval.num_tracks=64"]) == 0
    balanced, summary = _balanced_d_acc(out)
    assert balanced > 0.6, summary  # an untrained model scores 0.5 (all static)
