"""The DUSt3R image encoder: a ViT with 2-D rotary position embedding (CroCo/DUSt3R layout).

Parameter names match the official DUSt3R, MASt3R and MonST3R checkpoints exactly
(`patch_embed.proj.*`, `enc_blocks.{i}.{norm1,attn.qkv,attn.proj,norm2,mlp.fc1,mlp.fc2}.*`,
`enc_norm.*`), so the encoder of any of those files loads with `load_dust3r_encoder(path)`.
The building blocks (RoPE2D, Attention, Mlp) are shared with the full pointmap network in
`dynpt/dust3r/net.py`.

2-D RoPE (CroCo): each attention head's channels are split in two halves; the first half is
rotated by the token's row index y, the second by its column index x. Within a half of D channels,
channel pair (c, c + D/2) is rotated by the angle pos * base^(-2c/D), with base 100.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import torch
import torch.nn as nn
import torch.nn.functional as F

from c4d_core.errors import UserError
from dynpt.dust3r.checkpoint import (OfficialCheckpoint, block_count, head_count, read_checkpoint,
                                     rope_frequency)

ENCODER_PREFIXES = ("patch_embed.", "enc_blocks.", "enc_norm.")
LAYER_NORM_EPS = 1e-6


def patch_positions(batch: int, rows: int, cols: int, device: torch.device) -> torch.Tensor:
    """(y, x) grid position of every patch in row-major order: long (batch, rows*cols, 2)."""
    y, x = torch.meshgrid(torch.arange(rows, device=device), torch.arange(cols, device=device),
                          indexing="ij")
    pos = torch.stack([y.reshape(-1), x.reshape(-1)], dim=-1)  # (P, 2)
    return pos[None].expand(batch, -1, -1)


class RoPE2D(nn.Module):
    """2-D rotary position embedding applied to queries or keys (no parameters)."""

    def __init__(self, base: float = 100.0):
        super().__init__()
        self.base = base

    def _cos_sin(self, dim: int, length: int, device: torch.device, dtype: torch.dtype):
        """cos, sin tables (length, dim) for 1-D positions 0..length-1 over `dim` channels."""
        inv_freq = self.base ** (-torch.arange(0, dim, 2, device=device, dtype=torch.float32) / dim)
        angles = torch.arange(length, device=device, dtype=torch.float32)[:, None] * inv_freq  # (L, dim/2)
        angles = torch.cat([angles, angles], dim=-1)  # (L, dim)
        return angles.cos().to(dtype), angles.sin().to(dtype)

    @staticmethod
    def _rotate_1d(x: torch.Tensor, pos: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor):
        """Rotate x (B,h,N,D) by 1-D positions pos (B,N)."""
        cos, sin = cos[pos][:, None], sin[pos][:, None]  # (B,1,N,D)
        first, second = x.chunk(2, dim=-1)
        return x * cos + torch.cat([-second, first], dim=-1) * sin

    def forward(self, tokens: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:
        """tokens (B, heads, N, head_dim), pos long (B, N, 2) as (y, x) -> same shape as tokens."""
        half = tokens.shape[-1] // 2
        cos, sin = self._cos_sin(half, int(pos.max()) + 1, tokens.device, tokens.dtype)
        y_part, x_part = tokens.chunk(2, dim=-1)  # (B,h,N,half) each
        return torch.cat([self._rotate_1d(y_part, pos[..., 0], cos, sin),
                          self._rotate_1d(x_part, pos[..., 1], cos, sin)], dim=-1)


def split_heads(x: torch.Tensor, heads: int) -> torch.Tensor:
    """(B, N, C) -> (B, heads, N, C/heads)."""
    return x.unflatten(-1, (heads, -1)).transpose(1, 2)


class Attention(nn.Module):
    """Multi-head self-attention with RoPE on q and k; keys `qkv.*`, `proj.*`."""

    def __init__(self, dim: int, num_heads: int, rope: RoPE2D):
        super().__init__()
        self.num_heads = num_heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)
        self.rope = rope

    def forward(self, x: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:
        """x (B,N,C), pos (B,N,2) -> (B,N,C)."""
        q, k, v = self.qkv(x).unflatten(-1, (3, -1)).unbind(dim=2)  # 3 x (B,N,C)
        q, k, v = (split_heads(t, self.num_heads) for t in (q, k, v))  # (B,h,N,d)
        q, k = self.rope(q, pos), self.rope(k, pos)
        out = F.scaled_dot_product_attention(q, k, v)  # (B,h,N,d)
        return self.proj(out.transpose(1, 2).flatten(2))  # (B,N,C)


class Mlp(nn.Module):
    """Two-layer GELU MLP; keys `fc1.*`, `fc2.*`."""

    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(F.gelu(self.fc1(x)))


class EncoderBlock(nn.Module):
    """Pre-norm transformer block: x + attn(norm1(x)), then x + mlp(norm2(x))."""

    def __init__(self, dim: int, num_heads: int, mlp_ratio: float, rope: RoPE2D):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=LAYER_NORM_EPS)
        self.attn = Attention(dim, num_heads, rope)
        self.norm2 = nn.LayerNorm(dim, eps=LAYER_NORM_EPS)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))

    def forward(self, x: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:
        x = x + self.attn(self.norm1(x), pos)
        return x + self.mlp(self.norm2(x))


class PatchEmbed(nn.Module):
    """Non-overlapping patches to tokens; key `proj.*` (Conv2d 3 -> dim, kernel = stride = patch)."""

    def __init__(self, patch_size: int, dim: int):
        super().__init__()
        self.patch_size = patch_size
        self.proj = nn.Conv2d(3, dim, kernel_size=patch_size, stride=patch_size)

    def forward(self, img: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """img (B,3,H,W) with H, W multiples of the patch size -> tokens (B,P,D), pos (B,P,2)."""
        B, _, H, W = img.shape
        p = self.patch_size
        if H % p or W % p:
            raise ValueError(f"image size {H}x{W} is not a multiple of the patch size {p}")
        tokens = self.proj(img).flatten(2).transpose(1, 2)  # (B, H/p*W/p, D)
        return tokens, patch_positions(B, H // p, W // p, img.device)


class Dust3rEncoder(nn.Module):
    """DUSt3R's ViT encoder (ViT-L by default: 24 blocks, 1024 channels, 16 heads, 16x16 patches)."""

    def __init__(self, patch_size: int = 16, embed_dim: int = 1024, depth: int = 24,
                 num_heads: int = 16, mlp_ratio: float = 4.0, rope_freq: float = 100.0):
        super().__init__()
        self.patch_size, self.embed_dim = patch_size, embed_dim
        self.rope = RoPE2D(rope_freq)
        self.patch_embed = PatchEmbed(patch_size, embed_dim)
        self.enc_blocks = nn.ModuleList(
            EncoderBlock(embed_dim, num_heads, mlp_ratio, self.rope) for _ in range(depth))
        self.enc_norm = nn.LayerNorm(embed_dim, eps=LAYER_NORM_EPS)

    def forward(self, img: torch.Tensor, return_layers: Sequence[int] = ()
                ) -> tuple[torch.Tensor, torch.Tensor, list[torch.Tensor]]:
        """Encode images.

        img: (B,3,H,W) in [-1, 1], H and W multiples of the patch size.
        return_layers: indices i of blocks whose raw outputs (before enc_norm) to return, in order.
        Returns tokens (B,P,D) after enc_norm, pos long (B,P,2) as (y, x) patch indices (row-major,
        P = H/16 * W/16), and the requested blocks' outputs, each (B,P,D).
        """
        x, pos = self.patch_embed(img)  # (B,P,D), (B,P,2)
        wanted = {i % len(self.enc_blocks): n for n, i in enumerate(return_layers)}
        layers: list[torch.Tensor | None] = [None] * len(return_layers)
        for i, block in enumerate(self.enc_blocks):
            x = block(x, pos)
            if i in wanted:
                layers[wanted[i]] = x
        return self.enc_norm(x), pos, layers


def encoder_kwargs(ckpt: OfficialCheckpoint) -> dict[str, Any]:
    """Dust3rEncoder constructor arguments: sizes from the weights, heads and RoPE from args.model
    (heads: `dynpt.dust3r.checkpoint.head_count`)."""
    state_dict = ckpt.state_dict
    proj = state_dict["patch_embed.proj.weight"]  # (D, 3, p, p)
    dim = proj.shape[0]
    depth = block_count(state_dict, "enc_blocks.")
    hidden = state_dict["enc_blocks.0.mlp.fc1.weight"].shape[0] if depth else 4 * dim
    num_heads = head_count(ckpt, "enc_num_heads", dim)
    return dict(patch_size=proj.shape[-1], embed_dim=dim, depth=depth, num_heads=num_heads,
                mlp_ratio=hidden / dim, rope_freq=rope_frequency(ckpt.kwargs))


def encoder_from_checkpoint(ckpt: OfficialCheckpoint) -> Dust3rEncoder:
    """Build the encoder of an already-read official checkpoint and load its weights (strict)."""
    state = {k: v for k, v in ckpt.state_dict.items() if k.startswith(ENCODER_PREFIXES)}
    if "patch_embed.proj.weight" not in state:
        raise UserError(f"{str(ckpt.path)!r} has no DUSt3R encoder weights (patch_embed.proj.weight); "
                        "pass a DUSt3R, MASt3R or MonST3R checkpoint")
    encoder = Dust3rEncoder(**encoder_kwargs(ckpt))
    missing, unexpected = encoder.load_state_dict(state, strict=False)
    if missing or unexpected:
        raise UserError(f"encoder weights in {str(ckpt.path)!r} do not fit a DUSt3R ViT: missing "
                        f"{missing[:4]}, unexpected {unexpected[:4]}; pass an official checkpoint")
    return encoder.eval()


def load_dust3r_encoder(path: str | Path, map_location: Any = "cpu") -> Dust3rEncoder:
    """The ViT encoder of an official DUSt3R/MASt3R/MonST3R checkpoint file, in eval mode.

    Sizes (width, depth, patch, MLP ratio) are read from the weights; the head count and RoPE base
    from the file's `args.model` string (parsed, never executed; a string without the head count
    means CroCo's default of 12, a bare state dict width/64; RoPE base 100 by default).
    See `dynpt.dust3r.checkpoint` for how the file is unpickled.
    """
    return encoder_from_checkpoint(read_checkpoint(path, map_location))
