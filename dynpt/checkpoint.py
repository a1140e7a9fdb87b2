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

import errno
import logging
import os
from pathlib import Path
from typing import Mapping

import torch
from torch import nn

from c4d_core.errors import UserError
from c4d_core.files import atomic_path, disk_error
from dynpt.dust3r.checkpoint import load_failure, require_file
from dynpt.model import DynPT, build_model, plain_config

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


def save_atomic(path: str | os.PathLike, payload) -> Path:
    """`torch.save(payload)` to `path` atomically; a failed write (disk full) is a `UserError`."""
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:  # a handle: no temporary name inside
        try:
            torch.save(payload, fh)
        except RuntimeError as exc:  # PyTorch's writer turns the OSError of a full disk into this
            cause = exc.__cause__ or exc.__context__
            if isinstance(cause, OSError) and cause.errno is not None:
                raise disk_error(path, cause) from exc
            if "write" not in str(exc).lower():
                raise
            raise disk_error(path, OSError(errno.ENOSPC, "the file could not be written")) from exc
    return path


def read_tensor_file(path: Path, kind: str, missing_hint: str, damaged_hint: str):
    """`torch.load(path, weights_only=True)` on the CPU; a missing or unreadable file is a one-line
    `UserError` ("<kind> checkpoint ... does not exist; <missing_hint>" / "...; <damaged_hint>");
    a folder is named as one."""
    require_file(path, f"{kind} checkpoint", missing_hint)
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # a damaged file can fail anywhere inside the unpickler
        raise UserError(f"cannot read {str(path)!r} as a {kind} checkpoint "
                        f"({load_failure(exc, path)}); {damaged_hint}") from exc


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
