"""DynPT checkpoint files: one self-describing file per checkpoint.

Layout (a `torch.save`d dict, readable with `torch.load(weights_only=True)`):
    format  'dynpt-checkpoint-v1'
    config  the model config (plain dict; the 3D encoder's sizes filled in, its source path kept
            for the record only)
    model   the full state dict, the frozen 3D encoder's weights INCLUDED, so a checkpoint loads
            without the DUSt3R file it was built from (a ViT-L adds about 1.2 GB in float32)
    step    training step (int)
    extra   free-form dict (optimizer state, data config, metrics, ...) or {}
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Mapping

import torch
from torch import nn

from c4d_core.errors import UserError
from dynpt.model import DynPT, build_model, plain_config
from dynpt.torch_files import load_failure, require_file, save_atomic

log = logging.getLogger(__name__)

FORMAT = "dynpt-checkpoint-v1"


class CheckpointUnreadable(UserError):
    """The file exists but cannot be read as a checkpoint (truncated, damaged, another format)."""


def save_checkpoint(path: str | os.PathLike, model: DynPT, step: int, extra: dict | None = None) -> Path:
    """Write `model` (config + weights), `step` and `extra` to `path` atomically (temp + rename)."""
    path = Path(path)
    state = {k: v.detach().cpu() for k, v in model.state_dict().items()}
    payload = {"format": FORMAT, "config": model.config, "model": state, "step": int(step),
               "extra": extra or {}}
    return save_atomic(path, payload)


def load_checkpoint(path: str | os.PathLike, model_cfg: Mapping | None = None) -> dict:
    """Read a DynPT checkpoint: dict with 'format', 'config', 'model', 'step', 'extra' (on CPU).

    With `model_cfg` (the `model:` section the caller expects, e.g. when resuming training), any
    architecture difference from the stored config is a `UserError` naming the keys.
    """
    path = Path(path)
    require_file(path, "checkpoint", "pass the path of a DynPT checkpoint written by `c4d train`")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # a damaged file can fail anywhere inside the unpickler
        raise CheckpointUnreadable(f"cannot read {str(path)!r} as a DynPT checkpoint "
                                   f"({load_failure(exc, path)}); pass a checkpoint written by "
                                   "`c4d train`") from exc
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
        found = ckpt.get("format", "no format tag") if isinstance(ckpt, dict) else type(ckpt).__name__
        raise CheckpointUnreadable(f"{str(path)!r} is not a DynPT checkpoint (expected format {FORMAT!r}, found "
                        f"{found!r}); DUSt3R/MASt3R files go to model.encoder_3d.checkpoint instead")
    if model_cfg is not None:
        check_config(ckpt["config"], model_cfg, path)
    return ckpt


# keys that only steer inference or name a file: they may differ without changing the weights
_NON_ARCHITECTURE = {"window_stride", "train_iters", "eval_iters", "resolution", "visibility_threshold",
                     "visibility_rule",
                     "checkpoint", "require_checkpoint", "random_init", "init_from"}


def _differences(stored, wanted, prefix: str = "") -> list[str]:
    if isinstance(stored, Mapping) and isinstance(wanted, Mapping):
        keys = sorted(set(stored) | set(wanted))
        return [d for k in keys if k not in _NON_ARCHITECTURE
                for d in _differences(stored.get(k), wanted.get(k), f"{prefix}{k}.")]
    return [] if stored == wanted else [f"{prefix[:-1]} (file {stored!r}, config {wanted!r})"]


def check_config(stored: Mapping, model_cfg: Mapping, path: Path) -> None:
    """`UserError` if `model_cfg` describes another architecture than the stored config."""
    wanted = plain_config(model_cfg)
    if wanted["encoder_3d"].get("checkpoint"):  # sizes come from that file, as recorded in `stored`
        sizes = ("patch_size", "embed_dim", "depth", "num_heads", "mlp_ratio", "rope_freq")
        wanted["encoder_3d"].update({k: stored["encoder_3d"][k] for k in sizes})
    diffs = _differences(plain_config(stored), wanted)
    if diffs:
        raise UserError(f"checkpoint {str(path)!r} was trained with another model config: "
                        f"{'; '.join(diffs[:5])}; use the checkpoint's own config or start a new run")


def model_from_checkpoint(ckpt: dict, path: str | os.PathLike = "checkpoint") -> DynPT:
    """Rebuild the model of a loaded checkpoint and load its weights (strict)."""
    if ckpt["config"]["encoder_3d"].get("random_init"):
        log.warning("%s: this checkpoint's 3D encoder was randomly initialised (a test model)", path)
    model = build_model(ckpt["config"], weights_from_state_dict=True)
    load_weights(model, ckpt["model"], path)
    return model


def load_weights(model: nn.Module, state: dict, path: str | os.PathLike = "checkpoint") -> None:
    """`model.load_state_dict(state)` with a `UserError` naming the mismatching keys."""
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        detail = str(exc).split("\n\t", 1)[-1].splitlines()[0][:300]
        raise UserError(f"weights in {str(path)!r} do not fit its model config ({detail}); the file "
                        "is damaged or was edited") from exc
