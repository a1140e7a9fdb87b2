"""Fixed (parameter-free) encodings: Fourier features of displacements and 1-D sin-cos time embeddings."""

from __future__ import annotations

import math

import torch


def fourier_encode(x: torch.Tensor, num_freqs: int) -> torch.Tensor:
    """Fourier features of `x` (..., D): [x, sin(x * 2^k), cos(x * 2^k) for k < num_freqs].

    Returns (..., D * (1 + 2 * num_freqs)). The raw values come first, then all sines, then all
    cosines (cos written as sin shifted by pi/2).
    """
    scales = 2.0 ** torch.arange(num_freqs, device=x.device, dtype=x.dtype)  # (F,)
    xs = (x[..., None, :] * scales[:, None]).flatten(-2)  # (..., F*D)
    return torch.cat([x, torch.sin(xs), torch.sin(xs + math.pi / 2)], dim=-1)


def fourier_dim(in_dim: int, num_freqs: int) -> int:
    """Output width of `fourier_encode` for `in_dim` inputs."""
    return in_dim * (1 + 2 * num_freqs)


def sincos_time_embedding(length: int, dim: int, device=None) -> torch.Tensor:
    """1-D sin-cos embedding of positions 0..length-1, shape (length, dim); dim must be even.

    Half the channels are sin(pos * w_k), half cos(pos * w_k), with w_k = 1 / 10000^(k / (dim/2)).
    """
    if dim % 2:
        raise ValueError(f"sin-cos embedding needs an even dim, got {dim}")
    omega = 1.0 / 10000 ** (torch.arange(dim // 2, device=device, dtype=torch.float32) / (dim / 2))
    angles = torch.arange(length, device=device, dtype=torch.float32)[:, None] * omega  # (L, dim/2)
    return torch.cat([torch.sin(angles), torch.cos(angles)], dim=1)  # (L, dim)
