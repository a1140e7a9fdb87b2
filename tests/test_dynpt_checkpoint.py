"""DynPT checkpoint files: round trip (weights, step, extra, outputs) and clear errors."""

import os

import pytest
import torch

from c4d_core.errors import UserError
from dynpt.checkpoint import FORMAT, load_checkpoint, model_from_checkpoint, save_checkpoint
from dynpt.inference import load_tracker
from test_dynpt_model import (
    make_model, random_queries, random_video, tiny_cfg, write_official_checkpoint,
)


def test_round_trip_restores_weights_step_extra_and_outputs(tmp_path):
    model = make_model("model.encoder_3d.random_init=true", seed=2)
    path = save_checkpoint(tmp_path / "run" / "ckpt.pt", model, step=123, extra={"lr": 1e-4, "note": "x"})
    assert [p.name for p in path.parent.iterdir()] == ["ckpt.pt"]  # no temp file left behind
    ckpt = load_checkpoint(path)
    assert ckpt["format"] == FORMAT and ckpt["step"] == 123 and ckpt["extra"] == {"lr": 1e-4, "note": "x"}
    restored = model_from_checkpoint(ckpt, path)
    for (k, a), (k2, b) in zip(model.state_dict().items(), restored.state_dict().items()):
        assert k == k2 and torch.equal(a, b), k
    video, queries = random_video(1, 6, 36, 40), random_queries(1, 3, 6, 36, 40)
    with torch.no_grad():
        a, b = model.eval()(video, queries), restored.eval()(video, queries)
    assert torch.equal(a.coords[-1], b.coords[-1]) and torch.equal(a.moving_logits[-1], b.moving_logits[-1])
    assert not load_tracker(path).model.training


def test_checkpoint_with_dust3r_encoder_loads_without_the_dust3r_file(tmp_path):
    dust3r = tmp_path / "dust3r.pth"
    expected = write_official_checkpoint(dust3r, seed=4)
    model = make_model(f"model.encoder_3d.checkpoint={dust3r}")
    path = save_checkpoint(tmp_path / "ckpt.pt", model, step=1)
    dust3r.unlink()  # the DynPT checkpoint is self-contained
    restored = load_tracker(path).model
    for k, v in expected.items():
        assert torch.equal(restored.encoder_3d.state_dict()[k], v), k
    assert not any(p.requires_grad for p in restored.encoder_3d.parameters())


def test_missing_truncated_and_foreign_files_are_user_errors(tmp_path):
    with pytest.raises(UserError, match="does not exist"):
        load_checkpoint(tmp_path / "nope.pt")
    foreign = tmp_path / "foreign.pt"
    torch.save({"model": {"w": torch.zeros(1)}}, foreign)
    with pytest.raises(UserError, match="not a DynPT checkpoint"):
        load_checkpoint(foreign)
    good = save_checkpoint(tmp_path / "good.pt", make_model(), step=0)
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(good.read_bytes()[: os.path.getsize(good) // 2])
    with pytest.raises(UserError, match="cannot read"):
        load_checkpoint(truncated)
    text = tmp_path / "text.pt"
    text.write_text("hello")
    with pytest.raises(UserError, match="cannot read"):
        load_checkpoint(text)


def test_mismatching_config_is_named(tmp_path):
    path = save_checkpoint(tmp_path / "ckpt.pt", make_model(), step=0)
    load_checkpoint(path, tiny_cfg("model.eval_iters=9"))  # inference-only keys may differ
    with pytest.raises(UserError, match="hidden_dim"):
        load_checkpoint(path, tiny_cfg("model.hidden_dim=64"))
    ckpt = load_checkpoint(path)
    ckpt["config"]["depth"] = 2  # config edited: weights no longer fit
    with pytest.raises(UserError, match="do not fit"):
        model_from_checkpoint(ckpt, path)


def test_failed_save_keeps_the_previous_file(tmp_path, monkeypatch):
    path = save_checkpoint(tmp_path / "ckpt.pt", make_model(), step=1)

    def broken_save(obj, f, *a, **k):
        f.write(b"partial")
        raise OSError("disk full")

    monkeypatch.setattr(torch, "save", broken_save)
    with pytest.raises(OSError):
        save_checkpoint(path, make_model(), step=2)
    monkeypatch.undo()
    assert load_checkpoint(path)["step"] == 1
    assert [p.name for p in tmp_path.iterdir()] == ["ckpt.pt"]
