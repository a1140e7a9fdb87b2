"""The update transformer: attention across time per track, and across tracks through virtual tracks.

Tokens (B,N,T,D_in) -> per-token updates of position (2), visibility, confidence and mobility
logits. Design of CoTracker3's EfficientUpdateFormer: each layer is one time self-attention block
over every track (virtual ones included), then virtual<-point cross-attention, virtual
self-attention and point<-virtual cross-attention within each frame. A 1-D sin-cos embedding of
the frame's index in the window is added after the input projection (computed, not stored, so the
window length is not baked into the weights), or, with `time_embedding="cotracker3"`, a stored
input-width table of `time_emb_len` rows is added before it, linearly resized to the window
length as CoTracker3 does (its released weights expect that).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from dynpt.embeddings import sincos_time_embedding


class Attention(nn.Module):
    """Multi-head attention of x (B,L,D) over context (B,S,Dc) (self-attention when context is x).

    Keys as CoTracker3 releases them (`to_q`, `to_kv`, `to_out`), so its weights load by name.
    DUSt3R's attention (`dynpt.dust3r.vit_encoder.Attention`) is not a twin: its released layout is
    a fused `qkv` and `proj`, with RoPE on q and k, and its MLP uses the exact GELU (here tanh).
    """

    def __init__(self, dim: int, num_heads: int, context_dim: int | None = None):
        super().__init__()
        self.num_heads = num_heads
        self.to_q = nn.Linear(dim, dim)
        self.to_kv = nn.Linear(context_dim or dim, 2 * dim)
        self.to_out = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor, context: torch.Tensor | None = None) -> torch.Tensor:
        context = x if context is None else context
        heads = lambda y: y.unflatten(-1, (self.num_heads, -1)).transpose(1, 2)  # (B,h,L,d)
        q = heads(self.to_q(x))
        k, v = map(heads, self.to_kv(context).chunk(2, dim=-1))
        out = F.scaled_dot_product_attention(q, k, v)  # (B,h,L,d)
        return self.to_out(out.transpose(1, 2).flatten(-2))  # (B,L,D)


class Mlp(nn.Sequential):
    def __init__(self, dim: int, hidden: int):
        super().__init__(nn.Linear(dim, hidden), nn.GELU(approximate="tanh"), nn.Linear(hidden, dim))


class AttnBlock(nn.Module):
    """Pre-norm (self- or cross-) attention and MLP, each with a residual connection."""

    def __init__(self, dim: int, num_heads: int, mlp_ratio: float, cross: bool = False):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, elementwise_affine=False, eps=1e-6)
        self.norm_context = nn.LayerNorm(dim) if cross else None
        self.attn = Attention(dim, num_heads)
        self.norm2 = nn.LayerNorm(dim, elementwise_affine=False, eps=1e-6)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))

    def forward(self, x: torch.Tensor, context: torch.Tensor | None = None) -> torch.Tensor:
        ctx = None if self.norm_context is None else self.norm_context(context)
        x = x + self.attn(self.norm1(x), ctx)
        return x + self.mlp(self.norm2(x))


class UpdateTransformer(nn.Module):
    """Tokens (B,N,T,input_dim) -> (delta_xy (B,N,T,2), delta_logits (B,N,T,3): vis, conf, moving)."""

    def __init__(
        self, input_dim: int, hidden_dim: int, num_heads: int, depth: int,
        mlp_ratio: float, num_virtual_tracks: int, time_embedding: str = "hidden", time_emb_len: int = 16,
    ):
        super().__init__()
        self.time_embedding = time_embedding
        if time_embedding == "cotracker3":  # (1,L,input_dim); replaced by CoTracker3's when loading its weights
            emb = sincos_time_embedding(time_emb_len, input_dim - input_dim % 2)
            self.register_buffer("time_emb", F.pad(emb, (0, input_dim % 2))[None])
        self.input_transform = nn.Linear(input_dim, hidden_dim)
        self.virtual_tracks = nn.Parameter(torch.randn(1, num_virtual_tracks, 1, hidden_dim))
        block = lambda cross=False: AttnBlock(hidden_dim, num_heads, mlp_ratio, cross)
        self.time_blocks = nn.ModuleList(block() for _ in range(depth))
        self.virtual_from_points = nn.ModuleList(block(cross=True) for _ in range(depth))
        self.virtual_blocks = nn.ModuleList(block() for _ in range(depth))
        self.points_from_virtual = nn.ModuleList(block(cross=True) for _ in range(depth))
        self.flow_head = nn.Linear(hidden_dim, 2)
        self.vis_conf_head = nn.Linear(hidden_dim, 2)
        self.mobility_head = nn.Linear(hidden_dim, 1)  # separate, so vis/conf stay CoTracker-shaped
        self._init_weights()

    def _init_weights(self) -> None:
        for m in self.modules():
            if isinstance(m, nn.Linear):
                nn.init.xavier_uniform_(m.weight)
                nn.init.zeros_(m.bias)
        for head in (self.flow_head, self.vis_conf_head, self.mobility_head):
            nn.init.trunc_normal_(head.weight, std=0.001)

    def forward(self, tokens: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        B, N, T, _ = tokens.shape
        if self.time_embedding == "cotracker3":
            x = self.input_transform(tokens + self._resized_time_emb(T).to(tokens.dtype))  # (B,N,T,D)
        else:
            x = self.input_transform(tokens)  # (B,N,T,D)
            x = x + sincos_time_embedding(T, x.shape[-1], x.device).to(x.dtype)  # frame index in window
        V = self.virtual_tracks.shape[1]
        for layer, (time_blk, v_from_p, v_blk, p_from_v) in enumerate(zip(
            self.time_blocks, self.virtual_from_points, self.virtual_blocks, self.points_from_virtual
        )):
            if layer == 0:  # the virtual tracks join the points; before the first attention over T
                # they are the same in every frame and clip, and attention over T copies of a
                # token gives that token: one frame of them stands for all
                points = time_blk(x.flatten(0, 1)).unflatten(0, (B, N))  # (B,N,T,D)
                virtual = time_blk(self.virtual_tracks[0]).expand(B, V, T, -1)  # (1,V,1,D)[0] -> (B,V,T,D)
                x = torch.cat([points, virtual], dim=1)  # (B,N+V,T,D)
            else:
                x = time_blk(x.flatten(0, 1)).unflatten(0, (B, N + V))  # attention over T
            x = x.transpose(1, 2).flatten(0, 1)  # (B*T,N+V,D)
            points, virtual = x[:, :N], x[:, N:]
            virtual = v_from_p(virtual, points)
            virtual = v_blk(virtual)
            points = p_from_v(points, virtual)
            x = torch.cat([points, virtual], dim=1).unflatten(0, (B, T)).transpose(1, 2)  # (B,N+V,T,D)
        x = x[:, :N]  # drop virtual tracks
        logits = torch.cat([self.vis_conf_head(x), self.mobility_head(x)], dim=-1)  # (B,N,T,3)
        return self.flow_head(x), logits

    def _resized_time_emb(self, T: int) -> torch.Tensor:
        """The stored table linearly resized to T rows (align_corners=False): (T, input_dim)."""
        emb = self.time_emb
        if emb.shape[1] != T:
            emb = F.interpolate(emb.float().transpose(1, 2), size=T, mode="linear").transpose(1, 2)
        return emb[0]
