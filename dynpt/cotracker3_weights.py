"""CoTracker3's released weights (scaled_offline.pth, scaled_online.pth, baseline_*.pth) in DynPT.

DynPT is CoTracker3's network plus a mobility input and head, so all of CoTracker3's 188 tensors
have a DynPT counterpart. The mapping table (`dynpt_key` renames, `map_state` transforms values):

    CoTracker3                                     DynPT                                  value
    fnet.*                                         cnn.*                                  as is
    corr_mlp.fc1.weight (H, (2r+1)^4)              corr.mlp.0.weight                      columns reordered (1)
    corr_mlp.fc1.bias, corr_mlp.fc2.*              corr.mlp.0.bias, corr.mlp.2.*          as is
    updateformer.input_transform.weight (D, 1110)  transformer.input_transform.weight     token columns (2)
    time_emb (1, L, 1110)                          transformer.time_emb (1, L, 1111)      token columns (2)
    updateformer.virual_tracks                     transformer.virtual_tracks             as is
    updateformer.time_blocks.i.*                   transformer.time_blocks.i.*            (3)
    updateformer.space_virtual2point_blocks.i.*    transformer.virtual_from_points.i.*    (3)
    updateformer.space_virtual_blocks.i.*          transformer.virtual_blocks.i.*         (3)
    updateformer.space_point2virtual_blocks.i.*    transformer.points_from_virtual.i.*    (3)
    updateformer.flow_head (2 rows), vis_conf_head transformer.flow_head, vis_conf_head   as is
    updateformer.flow_head (4 rows, no vis_conf)   transformer.flow_head + vis_conf_head  rows 0:2 / 2:4

(1) CoTracker3 flattens each 7x7 correlation patch x-offset-major, DynPT y-offset-major: same
    shape, so a plain rename loads and is silently wrong. (2) DynPT's token has one more input,
    the mobility logit, at column 2: it gets a zero column (so the first forward pass equals
    CoTracker3's); DynPT's forward motion is P_{t+1} - P_t, CoTracker3's P_t - P_{t+1}, so the raw
    and sine columns of the forward displacement (2 + 2 * fourier_freqs = 22) are negated; the
    time embedding is added to the token, so it gets the same column change. (3) inside blocks:
    `cross_attn.` -> `attn.`, `mlp.fc1.` -> `mlp.0.`, `mlp.fc2.` -> `mlp.2.`.

DynPT tensors CoTracker3 lacks start fresh (`FRESH_PREFIXES`): the mobility head (random, small)
and, with the 3D encoder, the fusion layers: `vit_proj` random, `fuse` identity on the CNN
features and zero on the 3D ones, so the first forward pass is still CoTracker3's (the encoder
itself comes from its own file). The
model must be built with `time_embedding: cotracker3` and CoTracker3's sizes (configs/dynpt/
model/cotracker3.yaml); `sampling: cotracker3` and a CoTracker3 `windowing` reproduce its outputs.
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path
from typing import Mapping

import torch

from c4d_core.config import load_config
from c4d_core.errors import UserError
from dynpt.torch_files import read_tensor_file
from dynpt.model import build_model, plain_config

log = logging.getLogger(__name__)

# DynPT tensors with no CoTracker3 counterpart (besides the 3D encoder, loaded from its own file)
FRESH_PREFIXES = ("transformer.mobility_head.", "vit_proj.", "fuse.")
_OWN_FILE = "encoder_3d."
_BLOCKS = {"time_blocks": "time_blocks", "space_virtual2point_blocks": "virtual_from_points",
           "space_virtual_blocks": "virtual_blocks", "space_point2virtual_blocks": "points_from_virtual"}
COTRACKER3_HEAD_DIM = 48  # CoTracker3's attention heads are 48 wide (num_heads = hidden / 48)
COTRACKER3_FOURIER_FREQS = 10  # its displacement encoding: raw + sin/cos at 2^0..2^9


def dynpt_key(key: str) -> str | None:
    """The DynPT name of a CoTracker3 tensor, or None if the name is not CoTracker3's."""
    if key == "time_emb":
        return "transformer.time_emb"
    if key.startswith("fnet."):
        return "cnn." + key[5:]
    m = re.fullmatch(r"corr_mlp\.fc([12])\.(weight|bias)", key)
    if m:
        return f"corr.mlp.{0 if m[1] == '1' else 2}.{m[2]}"
    if key == "updateformer.virual_tracks":
        return "transformer.virtual_tracks"
    m = re.fullmatch(r"updateformer\.(input_transform|flow_head|vis_conf_head)\.(weight|bias)", key)
    if m:
        return f"transformer.{m[1]}.{m[2]}"
    m = re.fullmatch(r"updateformer\.(\w+?)\.(\d+)\.(.+)", key)
    if m and m[1] in _BLOCKS:
        inner = m[3].replace("cross_attn.", "attn.").replace("mlp.fc1.", "mlp.0.").replace("mlp.fc2.", "mlp.2.")
        return f"transformer.{_BLOCKS[m[1]]}.{m[2]}.{inner}"
    return None


def is_cotracker3_state(state: Mapping) -> bool:
    """True if `state` looks like a CoTracker3 state dict (its CNN and update transformer)."""
    return "updateformer.input_transform.weight" in state and "fnet.conv1.weight" in state


RELEASED = "scaled_offline.pth or scaled_online.pth from huggingface.co/facebook/cotracker3"


def read_state(path: str | os.PathLike) -> dict[str, torch.Tensor]:
    """CoTracker3's state dict from a file: as released, a plain state dict, or one under `model`."""
    state = read_tensor_file(Path(path), "CoTracker3", f"download {RELEASED}",
                             f"the file is truncated or damaged: download {RELEASED} again",
                             f"a CoTracker3 checkpoint holds tensors alone: pass {RELEASED}")
    if isinstance(state, Mapping) and isinstance(state.get("model"), Mapping):
        state = state["model"]
    if not isinstance(state, Mapping) or not is_cotracker3_state(state):
        raise UserError(f"{str(path)!r} is not a CoTracker3 checkpoint (no fnet.* / updateformer.* "
                        f"tensors); expected {RELEASED}")
    check_state(state, repr(str(path)))
    return dict(state)


# The tensors whose shapes give a DynPT config its sizes (`config_from_state`), with their ranks.
SIZE_TENSORS = {
    "time_emb": 3, "corr_mlp.fc1.weight": 2, "corr_mlp.fc2.weight": 2,
    "updateformer.input_transform.weight": 2, "updateformer.virual_tracks": 4,
    "updateformer.time_blocks.0.mlp.fc1.weight": 2, "fnet.conv3.weight": 4,
    **{f"fnet.layer{i}.0.conv1.weight": 4 for i in range(1, 5)},
}


def check_state(state: Mapping[str, torch.Tensor], source: str = "file") -> None:
    """`UserError`, one line naming the tensor at fault, unless `state` is a whole CoTracker3 state
    dict whose sizes agree with each other: every name CoTracker3's (a CoTracker2 file has others),
    every tensor the sizes are read from present with its rank, the correlation MLP taking a
    (2r+1)^4 patch, and the input projection (and the time embedding added before it) as wide as
    2 + levels x corr_mlp.fc2's outputs + the displacement encoding."""
    for key, value in state.items():
        if dynpt_key(key) is None:
            raise UserError(f"{source}: tensor {key!r} is not part of CoTracker3's network; "
                            "not a CoTracker3 checkpoint, or another version (CoTracker2?)")
        if not isinstance(value, torch.Tensor):
            raise UserError(f"{source}: {key!r} is a {type(value).__name__}, not a tensor; "
                            "not a CoTracker3 checkpoint")
    for key, rank in SIZE_TENSORS.items():
        if key not in state:
            raise UserError(f"{source}: no tensor {key!r}; the file lacks part of CoTracker3's "
                            "network (a released file holds all 188)")
        if state[key].dim() != rank:
            raise UserError(f"{source}: {key} is {tuple(state[key].shape)}, CoTracker3's has "
                            f"{rank} dimensions; not a CoTracker3 checkpoint")
    cells = state["corr_mlp.fc1.weight"].shape[1]
    k = round(cells ** 0.25)
    if k ** 4 != cells or k % 2 == 0:
        raise UserError(f"{source}: corr_mlp.fc1.weight has {cells} inputs, not the (2r+1)^4 of a "
                        "square correlation patch; not a CoTracker3 checkpoint")
    hidden, tokens = state["updateformer.input_transform.weight"].shape
    corr_out = state["corr_mlp.fc2.weight"].shape[0]
    encoding = 4 * (1 + 2 * COTRACKER3_FOURIER_FREQS)  # forward and backward (dx, dy), raw + sin/cos
    if tokens - 2 - encoding <= 0 or (tokens - 2 - encoding) % corr_out:
        raise UserError(f"{source}: updateformer.input_transform.weight has {tokens} token inputs; "
                        f"CoTracker3's are 2 + levels x {corr_out} (corr_mlp.fc2's outputs) + "
                        f"{encoding}, e.g. {2 + 4 * corr_out + encoding}")
    if state["time_emb"].shape[-1] != tokens:
        raise UserError(f"{source}: time_emb is {state['time_emb'].shape[-1]} wide but "
                        f"updateformer.input_transform.weight takes {tokens} token inputs; they "
                        "must agree (the embedding is added to the token)")
    if hidden % COTRACKER3_HEAD_DIM or state["updateformer.virual_tracks"].shape[-1] != hidden:
        raise UserError(f"{source}: updateformer.virual_tracks is "
                        f"{tuple(state['updateformer.virual_tracks'].shape)} for a transformer "
                        f"{hidden} wide; CoTracker3's width is a multiple of {COTRACKER3_HEAD_DIM} "
                        "and its virtual tracks have it")


def _token_columns(x: torch.Tensor, posenc_start: int, fourier_freqs: int) -> torch.Tensor:
    """CoTracker3 token columns (last dim, [vis, conf, corr..., posenc(fwd, bwd)]) -> DynPT's
    ([vis, conf, moving=0, corr..., fourier(fwd, bwd)] with the forward motion negated)."""
    x = x.clone()
    raw = [posenc_start, posenc_start + 1]  # forward dx, dy
    sines = [posenc_start + 4 + 4 * f + d for f in range(fourier_freqs) for d in (0, 1)]
    x[..., raw + sines] *= -1  # sin(-a) = -sin(a); the cosines are even
    return torch.cat([x[..., :2], torch.zeros_like(x[..., :1]), x[..., 2:]], dim=-1)


def _corr_columns(w: torch.Tensor, radius: int) -> torch.Tensor:
    """corr_mlp.fc1.weight (H, P^2), P patch cells: CoTracker3 column order (target x, target y,
    query x, query y) -> DynPT's (target y, target x, query y, query x)."""
    k = 2 * radius + 1
    return w.reshape(w.shape[0], k, k, k, k).permute(0, 2, 1, 4, 3).reshape(w.shape)


def map_state(state: Mapping[str, torch.Tensor], model_config: Mapping, target: Mapping[str, torch.Tensor],
              source: str = "file") -> tuple[dict[str, torch.Tensor], list[str]]:
    """CoTracker3 `state` -> (DynPT tensors, names of the DynPT tensors that start fresh).

    `target` is the DynPT model's own state dict (names and shapes to fit); `model_config` its
    config (for the token layout). `UserError` (one line) on any key or shape that does not fit.
    """
    check_state(state, source)
    c = model_config
    if c["time_embedding"] != "cotracker3" and "time_emb" in state:
        raise UserError("CoTracker3 weights need model.time_embedding=cotracker3 (its time embedding "
                        "is added before the input projection); use configs/dynpt/model/cotracker3.yaml")
    posenc_start = 2 + c["corr_levels"] * c["corr_out_dim"]
    out: dict[str, torch.Tensor] = {}
    for key, value in state.items():
        name = dynpt_key(key)  # never None: check_state refused other names
        if name == "transformer.flow_head.weight" and value.shape[0] == 4 or \
                name == "transformer.flow_head.bias" and value.shape[0] == 4:  # one head for all four
            field = name.rsplit(".", 1)[1]
            out[f"transformer.flow_head.{field}"] = value[:2]
            out[f"transformer.vis_conf_head.{field}"] = value[2:]
            continue
        if name in ("transformer.input_transform.weight", "transformer.time_emb"):
            if value.shape[-1] != posenc_start + 4 * (1 + 2 * c["fourier_freqs"]):
                raise UserError(f"{source}: {key} has {value.shape[-1]} token inputs, but the DynPT config "
                                f"expects {posenc_start + 4 * (1 + 2 * c['fourier_freqs'])} (corr_levels x "
                                "corr_out_dim + Fourier sizes differ); use CoTracker3's sizes")
            value = _token_columns(value, posenc_start, c["fourier_freqs"])
        elif name == "corr.mlp.0.weight":
            if value.shape[1] != (2 * c["corr_radius"] + 1) ** 4:
                raise UserError(f"{source}: {key} has {value.shape[1]} correlation inputs; the DynPT config "
                                f"expects {(2 * c['corr_radius'] + 1) ** 4} (corr_radius={c['corr_radius']})")
            value = _corr_columns(value, c["corr_radius"])
        out[name] = value
    for name, value in out.items():
        if name not in target:
            raise UserError(f"{source}: CoTracker3 tensor for {name!r} has no place in this DynPT config "
                            "(fewer blocks or levels?); use CoTracker3's sizes (model/cotracker3.yaml)")
        if tuple(value.shape) != tuple(target[name].shape):
            raise UserError(f"{source}: {name} is {tuple(value.shape)} in the file but "
                            f"{tuple(target[name].shape)} in this DynPT config; use CoTracker3's sizes")
    missing = [k for k in target if k not in out and not k.startswith(_OWN_FILE)]
    unfilled = [k for k in missing if not k.startswith(FRESH_PREFIXES)]
    if unfilled:
        raise UserError(f"{source}: no CoTracker3 tensor for DynPT's {unfilled[0]} (and {len(unfilled) - 1} "
                        "more); the file lacks part of CoTracker3's network")
    return out, missing


def release_windowing(state: Mapping[str, torch.Tensor]) -> str:
    """"cotracker3_offline" for a time embedding of more than 16 rows (the offline release has
    60), else "cotracker3_online" (16-frame windows moved by 8, as released)."""
    return "cotracker3_offline" if state["time_emb"].shape[1] > 16 else "cotracker3_online"


def config_from_state(state: Mapping[str, torch.Tensor], base: Mapping, windowing: str | None = None) -> dict:
    """A DynPT model config with the sizes of a CoTracker3 state dict; the other keys from `base`.

    `windowing` None: `release_windowing(state)`.
    """
    check_state(state)
    fc1, fc2 = state["corr_mlp.fc1.weight"], state["corr_mlp.fc2.weight"]
    hidden, tokens = state["updateformer.input_transform.weight"].shape
    depth = len({k.split(".")[2] for k in state if k.startswith("updateformer.time_blocks.")})
    rows = state["time_emb"].shape[1]
    windowing = windowing or release_windowing(state)
    levels = (tokens - 2 - 4 * (1 + 2 * COTRACKER3_FOURIER_FREQS)) // fc2.shape[0]
    cfg = dict(base)
    cfg.update(
        cnn_widths=[state[f"fnet.layer{i}.0.conv1.weight"].shape[0] for i in range(1, 5)],
        feature_dim=state["fnet.conv3.weight"].shape[0],
        corr_levels=levels, corr_radius=(round(fc1.shape[1] ** 0.25) - 1) // 2,
        corr_hidden_dim=fc1.shape[0], corr_out_dim=fc2.shape[0],
        hidden_dim=hidden, num_heads=hidden // COTRACKER3_HEAD_DIM, depth=depth,
        mlp_ratio=state["updateformer.time_blocks.0.mlp.fc1.weight"].shape[0] / hidden,
        num_virtual_tracks=state["updateformer.virual_tracks"].shape[1],
        fourier_freqs=COTRACKER3_FOURIER_FREQS, displacement_scale=[512.0, 384.0],
        time_embedding="cotracker3", time_emb_len=rows, sampling="cotracker3", windowing=windowing,
        window_len=rows if windowing == "cotracker3_online" else base["window_len"],
        window_stride=rows // 2 if windowing == "cotracker3_online" else base["window_stride"],
    )
    return cfg


def load_into(model: torch.nn.Module, path: str | os.PathLike, state: Mapping | None = None) -> list[str]:
    """Load a CoTracker3 file (or its already read `state`) into a DynPT `model` (in place);
    returns the names of the tensors left fresh."""
    state = read_state(path) if state is None else state
    mapped, fresh = map_state(state, model.config, model.state_dict(), source=str(path))
    model.load_state_dict(mapped, strict=False)
    fuse = getattr(model, "fuse", None)
    if fuse is not None:  # identity on the CNN half, zero on the 3D half: the first pass is CoTracker3's
        C = fuse.out_channels
        with torch.no_grad():
            fuse.weight.zero_()
            fuse.weight[:, :C, 0, 0] = torch.eye(C)
            fuse.bias.zero_()
    log.info("DynPT from CoTracker3 %s: %d tensors mapped; starting fresh: %s", path, len(mapped),
             ", ".join(fresh) or "none")
    return fresh


def build_from_file(path: str | os.PathLike, windowing: str | None = None):
    """A DynPT with the sizes and weights of a CoTracker3 file (mobility head fresh; see
    `config_from_state` for `windowing`); the other model keys, such as the visibility rule of
    CoTracker3's predictor for these weights, from model/cotracker3-offline.yaml or -online.yaml."""
    state = read_state(path)
    windowing = windowing or release_windowing(state)
    preset = "offline" if windowing == "cotracker3_offline" else "online"
    base = plain_config(load_config("dynpt", f"model/cotracker3-{preset}").model)
    model = build_model(config_from_state(state, base, windowing))
    load_into(model, path, state)
    return model


def parse_init(spec: str) -> Path:
    """`cotracker3:PATH` (model.init_from / --init) -> PATH; `UserError` for another form."""
    kind, sep, path = spec.partition(":")
    if kind != "cotracker3" or not sep or not path:
        raise UserError(f"model.init_from={spec!r}: expected cotracker3:/path/to/scaled_offline.pth "
                        "(or scaled_online.pth, baseline_*.pth)")
    return Path(path)
