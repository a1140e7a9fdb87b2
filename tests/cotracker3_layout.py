"""Stand-ins for CoTracker3's released files (scaled_offline.pth & co): random weights, released layout.

No CoTracker3 file exists offline, so the tests that start from one (`c4d train --init
cotracker3:PATH`, `c4d track --ckpt cotracker3:PATH`, the documented fine-tuning lines) write one:
`released_state(model_cfg)` holds CoTracker3's tensor names and shapes for the DynPT `model_cfg`
(model/cotracker3-offline.yaml: the released sizes, 188 tensors, 25.4 M values, ~100 MB; smaller
sizes for quick tests), random values. The names are written here from CoTracker3's side, not
through `dynpt.cotracker3_weights`; tests/test_dynpt_cotracker3.py checks that this layout, at the
sizes of tests/fixtures/cotracker3_golden.pt, equals the one co-tracker's own classes write.

`expected_dynpt(state, model_cfg)` is the oracle of the documented transforms (the table in
dynpt/cotracker3_weights.py): the DynPT tensor each CoTracker3 tensor must become, derived from
DynPT's own token layout (`dynpt.embeddings.fourier_encode`) rather than from the loader's code.
"""

from __future__ import annotations

import itertools
import re
from pathlib import Path
from typing import Mapping

import torch

from dynpt.embeddings import fourier_encode
from dynpt.model import build_model

# DynPT block lists -> CoTracker3's (the cross-attention ones name their attention `cross_attn`)
_BLOCKS = {"time_blocks": ("time_blocks", False), "virtual_blocks": ("space_virtual_blocks", False),
           "virtual_from_points": ("space_virtual2point_blocks", True),
           "points_from_virtual": ("space_point2virtual_blocks", True)}
_TOKEN_TENSORS = ("transformer.input_transform.weight", "transformer.time_emb")
_NEW_IN_DYNPT = ("transformer.mobility_head.", "vit_proj.", "fuse.", "encoder_3d.")


def released_name(dynpt_name: str) -> str | None:
    """CoTracker3's name of DynPT tensor `dynpt_name`; None for DynPT's own (mobility, 3D fusion)."""
    if dynpt_name.startswith(_NEW_IN_DYNPT):
        return None
    if dynpt_name == "transformer.time_emb":
        return "time_emb"
    if dynpt_name == "transformer.virtual_tracks":
        return "updateformer.virual_tracks"  # sic: CoTracker3's spelling
    if dynpt_name.startswith("cnn."):
        return "fnet." + dynpt_name[4:]
    m = re.fullmatch(r"corr\.mlp\.([02])\.(weight|bias)", dynpt_name)
    if m:
        return f"corr_mlp.fc{1 if m[1] == '0' else 2}.{m[2]}"
    m = re.fullmatch(r"transformer\.(\w+?)\.(\d+)\.(.+)", dynpt_name)
    if m and m[1] in _BLOCKS:
        block, cross = _BLOCKS[m[1]]
        inner = m[3].replace("mlp.0.", "mlp.fc1.").replace("mlp.2.", "mlp.fc2.")
        if cross:
            inner = inner.replace("attn.", "cross_attn.")
        return f"updateformer.{block}.{m[2]}.{inner}"
    if dynpt_name.startswith("transformer."):
        return "updateformer." + dynpt_name[len("transformer."):]
    raise AssertionError(f"no CoTracker3 name for DynPT's {dynpt_name}")


def released_state(model_cfg: Mapping, seed: int = 0) -> dict[str, torch.Tensor]:
    """A CoTracker3 state dict (released names and shapes) for the DynPT `model_cfg`, random values
    (normal, std 0.02): the token tensors have CoTracker3's width, one input fewer than DynPT's."""
    gen = torch.Generator().manual_seed(seed)
    out = {}
    for name, value in build_model(model_cfg).state_dict().items():
        key = released_name(name)
        if key is None:
            continue
        shape = list(value.shape)
        if name in _TOKEN_TENSORS:
            shape[-1] -= 1  # no mobility input
        out[key] = 0.02 * torch.randn(shape, generator=gen)
    return out


def write_released(path: Path, model_cfg: Mapping, seed: int = 0, wrapped: bool = False) -> dict:
    """Write `released_state(model_cfg, seed)` to `path` as released (a plain state dict) or as
    CoTracker3's training writes it (`wrapped`: under `model`); returns the state."""
    state = released_state(model_cfg, seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"model": state, "total_steps": 0} if wrapped else state, path)
    return state


def _forward_odd_columns(fourier_freqs: int) -> torch.Tensor:
    """Which of DynPT's Fourier columns change sign with the forward displacement: (4 (1 + 2F),) bool."""
    disp = torch.tensor([[0.013, -0.021, 0.017, 0.011]])  # (fwd dx, dy, bwd dx, dy)
    flipped = disp * torch.tensor([-1.0, -1.0, 1.0, 1.0])
    a, b = fourier_encode(disp, fourier_freqs)[0], fourier_encode(flipped, fourier_freqs)[0]
    return torch.isclose(a, -b, atol=1e-7) & ~torch.isclose(a, b, atol=1e-7)


def expected_dynpt(state: Mapping[str, torch.Tensor], model_cfg: Mapping) -> dict[str, torch.Tensor]:
    """The DynPT tensors (by DynPT name) a CoTracker3 `state` must load as, per the documented
    transforms: the correlation MLP's input columns from CoTracker3's (target x, target y, query x,
    query y) order to DynPT's (target y, target x, query y, query x); the token columns [vis, conf,
    corr..., displacement encoding] -> [vis, conf, mobility = 0, corr..., encoding with the forward
    displacement negated]; everything else as is."""
    c = model_cfg
    k = 2 * c["corr_radius"] + 1
    # DynPT column of patch cell (ty, tx, qy, qx) reads CoTracker3's column of (tx, ty, qx, qy)
    corr_src = torch.tensor([((tx * k + ty) * k + qx) * k + qy
                             for ty, tx, qy, qx in itertools.product(range(k), repeat=4)])
    posenc = 2 + c["corr_levels"] * c["corr_out_dim"]
    sign = torch.ones(posenc + 4 * (1 + 2 * c["fourier_freqs"]))
    sign[posenc:][_forward_odd_columns(c["fourier_freqs"])] = -1
    names = {released_name(n): n for n in build_model(model_cfg).state_dict() if released_name(n)}
    out = {}
    for key, value in state.items():
        name = names[key]
        if name == "corr.mlp.0.weight":
            value = value[:, corr_src]
        elif name in _TOKEN_TENSORS:
            value = value * sign
            value = torch.cat([value[..., :2], torch.zeros_like(value[..., :1]), value[..., 2:]], dim=-1)
        out[name] = value
    return out
