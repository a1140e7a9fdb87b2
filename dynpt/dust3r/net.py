"""The DUSt3R pointmap network (AsymmetricCroCo3DStereo), loadable from official checkpoints.

Two images go through the shared ViT encoder (`dynpt.dust3r.vit_encoder.Dust3rEncoder`); two
ViT-B-width decoders exchange information by cross-attention layer by layer; one head per view
turns the decoder tokens into a pointmap (x, y, z per pixel, both views in view 1's camera frame)
and a confidence. Parameter names are the official ones, so DUSt3R 224/512 linear and DPT, MonST3R
and MASt3R files load with `load_dust3r(path)`:

  patch_embed / enc_blocks / enc_norm          encoder (see dynpt/dust3r/vit_encoder.py)
  decoder_embed                                Linear enc_dim -> dec_dim
  dec_blocks.{i}, dec_blocks2.{i}              norm1, attn.{qkv,proj}, norm2, cross_attn.{projq,
                                               projk,projv,proj}, norm3, norm_y, mlp.{fc1,fc2}
  dec_norm                                     LayerNorm on the last decoder output
  downstream_head{1,2}.proj                    linear head: Linear dec_dim -> 4*p*p, pixel shuffle
  downstream_head{1,2}.dpt.*                   DPT head (act_postprocess, scratch, head)

Output parametrisation (official depth_mode ('exp', -inf, inf), conf_mode ('exp', 1, inf)):
pts = xyz / |xyz| * expm1(|xyz|) and conf = 1 + exp(c), so conf >= 1.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
import torch.nn as nn
import torch.nn.functional as F

from c4d_core.errors import UserError
from dynpt.dust3r.checkpoint import OfficialCheckpoint, block_count, head_count, read_checkpoint
from dynpt.dust3r.vit_encoder import (LAYER_NORM_EPS, Attention, Dust3rEncoder, Mlp, RoPE2D,
                                      encoder_kwargs, split_heads)

log = logging.getLogger(__name__)


class CrossAttention(nn.Module):
    """Queries from one view attend to the other view's tokens; keys projq/projk/projv/proj."""

    def __init__(self, dim: int, num_heads: int, rope: RoPE2D):
        super().__init__()
        self.num_heads = num_heads
        self.projq, self.projk, self.projv = nn.Linear(dim, dim), nn.Linear(dim, dim), nn.Linear(dim, dim)
        self.proj = nn.Linear(dim, dim)
        self.rope = rope

    def forward(self, x, memory, pos_x, pos_mem):
        """x (B,N,C), memory (B,M,C), positions (B,N,2), (B,M,2) -> (B,N,C)."""
        q = self.rope(split_heads(self.projq(x), self.num_heads), pos_x)  # (B,h,N,d)
        k = self.rope(split_heads(self.projk(memory), self.num_heads), pos_mem)  # (B,h,M,d)
        v = split_heads(self.projv(memory), self.num_heads)  # (B,h,M,d)
        out = F.scaled_dot_product_attention(q, k, v)  # (B,h,N,d)
        return self.proj(out.transpose(1, 2).flatten(2))


class DecoderBlock(nn.Module):
    """Self-attention, cross-attention to the other view (memory normalised by norm_y), MLP."""

    def __init__(self, dim: int, num_heads: int, mlp_ratio: float, rope: RoPE2D):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=LAYER_NORM_EPS)
        self.attn = Attention(dim, num_heads, rope)
        self.norm2 = nn.LayerNorm(dim, eps=LAYER_NORM_EPS)
        self.cross_attn = CrossAttention(dim, num_heads, rope)
        self.norm3 = nn.LayerNorm(dim, eps=LAYER_NORM_EPS)
        self.norm_y = nn.LayerNorm(dim, eps=LAYER_NORM_EPS)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))

    def forward(self, x, other, pos_x, pos_other):
        """x, other (B,N,C) tokens of this and the other view -> updated x (B,N,C)."""
        x = x + self.attn(self.norm1(x), pos_x)
        memory = self.norm_y(other)
        x = x + self.cross_attn(self.norm2(x), memory, pos_x, pos_other)
        return x + self.mlp(self.norm3(x))


def postprocess(raw: torch.Tensor, depth_mode: tuple, conf_mode: tuple) -> tuple[torch.Tensor, torch.Tensor]:
    """Head output (B,4,H,W) -> points (B,H,W,3) and confidence (B,H,W), DUSt3R parametrisation.

    depth_mode ('exp'|'square'|'linear', -inf, inf): direction xyz/|xyz| times expm1(|xyz|),
    |xyz|^2 or |xyz|. conf_mode ('exp', vmin, vmax): vmin + exp(c) clipped at vmax - vmin.
    """
    fmap = raw.permute(0, 2, 3, 1).float()  # (B,H,W,4)
    xyz, c = fmap[..., :3], fmap[..., 3]
    norm = xyz.norm(dim=-1, keepdim=True)  # (B,H,W,1)
    direction = xyz / norm.clamp(min=1e-8)
    scale = {"exp": torch.expm1, "square": torch.square, "linear": lambda d: d}[depth_mode[0]](norm)
    conf_min, conf_max = float(conf_mode[1]), float(conf_mode[2])
    return direction * scale, conf_min + c.exp().clamp(max=conf_max - conf_min)


class LinearHead(nn.Module):
    """Per-patch linear map to 4 x p x p values, pixel-shuffled to full resolution; key `proj`."""

    def __init__(self, dec_dim: int, patch_size: int, channels: int = 4):
        super().__init__()
        self.patch_size = patch_size
        self.proj = nn.Linear(dec_dim, channels * patch_size ** 2)

    def forward(self, layers: list[torch.Tensor], hw: tuple[int, int]) -> torch.Tensor:
        """layers: decoder outputs, the last (B,P,C) is used -> (B,4,H,W)."""
        p = self.patch_size
        feat = self.proj(layers[-1]).transpose(1, 2)  # (B, 4*p*p, P)
        feat = feat.unflatten(-1, (hw[0] // p, hw[1] // p))  # (B, 4*p*p, H/p, W/p)
        return F.pixel_shuffle(feat, p)  # (B,4,H,W)


class ResidualConvUnit(nn.Module):
    """x + conv2(relu(conv1(relu(x)))); keys conv1, conv2."""

    def __init__(self, dim: int):
        super().__init__()
        self.conv1 = nn.Conv2d(dim, dim, 3, padding=1)
        self.conv2 = nn.Conv2d(dim, dim, 3, padding=1)

    def forward(self, x):
        return x + self.conv2(F.relu(self.conv1(F.relu(x))))


class FusionBlock(nn.Module):
    """DPT refinement: add the skip (through resConfUnit1), resConfUnit2, upsample x2, out_conv."""

    def __init__(self, dim: int):
        super().__init__()
        self.resConfUnit1 = ResidualConvUnit(dim)
        self.resConfUnit2 = ResidualConvUnit(dim)
        self.out_conv = nn.Conv2d(dim, dim, 1)

    def forward(self, x, skip=None):
        if skip is not None:
            x = x + self.resConfUnit1(skip)
        x = self.resConfUnit2(x)
        x = F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=True)
        return self.out_conv(x)


class DPTAdapter(nn.Module):
    """DPT decoder of four hooked token maps (official `dpt.*` layout, incl. duplicate scratch keys).

    Token maps at 1/16 resolution are brought to 1/4, 1/8, 1/16 and 1/32 (act_postprocess),
    projected to `feature_dim` (scratch.layer{k}_rn, also registered as scratch.layer_rn.{k-1}
    as in the official files), fused coarse to fine (scratch.refinenet4..1) and regressed to
    `channels` maps at full resolution (head).
    """

    def __init__(self, dims_in: list[int], hooks: list[int], layer_dims=(96, 192, 384, 768),
                 feature_dim: int = 256, last_dim: int = 128, channels: int = 4, patch_size: int = 16):
        super().__init__()
        self.hooks, self.patch_size = list(hooks), patch_size
        resamplers = [
            nn.ConvTranspose2d(layer_dims[0], layer_dims[0], 4, stride=4),  # 1/16 -> 1/4
            nn.ConvTranspose2d(layer_dims[1], layer_dims[1], 2, stride=2),  # -> 1/8
            None,  # stays at 1/16
            nn.Conv2d(layer_dims[3], layer_dims[3], 3, stride=2, padding=1),  # -> 1/32
        ]
        self.act_postprocess = nn.ModuleList(
            nn.Sequential(nn.Conv2d(d_in, d, 1), *([r] if r is not None else []))
            for d_in, d, r in zip(dims_in, layer_dims, resamplers))
        self.scratch = nn.Module()
        for k, d in enumerate(layer_dims, start=1):
            setattr(self.scratch, f"layer{k}_rn", nn.Conv2d(d, feature_dim, 3, padding=1, bias=False))
        self.scratch.layer_rn = nn.ModuleList(getattr(self.scratch, f"layer{k}_rn") for k in range(1, 5))
        for k in range(1, 5):
            setattr(self.scratch, f"refinenet{k}", FusionBlock(feature_dim))
        self.head = nn.Sequential(
            nn.Conv2d(feature_dim, feature_dim // 2, 3, padding=1),
            nn.Upsample(scale_factor=2, mode="bilinear", align_corners=True),
            nn.Conv2d(feature_dim // 2, last_dim, 3, padding=1),
            nn.ReLU(),
            nn.Conv2d(last_dim, channels, 1),
        )

    def forward(self, layers: list[torch.Tensor], hw: tuple[int, int]) -> torch.Tensor:
        """layers: all decoder outputs (B,P,C_l); hw: image (H,W) -> (B,channels,H,W)."""
        rows, cols = hw[0] // self.patch_size, hw[1] // self.patch_size
        maps = [layers[h].transpose(1, 2).unflatten(-1, (rows, cols)) for h in self.hooks]  # (B,C,h,w)
        maps = [rn(post(m)) for m, post, rn in zip(maps, self.act_postprocess, self.scratch.layer_rn)]
        s = self.scratch
        path = s.refinenet4(maps[3])[:, :, :maps[2].shape[2], :maps[2].shape[3]]  # 1/16
        path = s.refinenet3(path, maps[2])  # 1/8
        path = s.refinenet2(path, maps[1])  # 1/4
        path = s.refinenet1(path, maps[0])  # 1/2
        return self.head(path)  # (B,channels,H,W)


class DPTHead(nn.Module):
    """Wrapper giving the official `downstream_head{k}.dpt.*` key prefix."""

    def __init__(self, **kwargs):
        super().__init__()
        self.dpt = DPTAdapter(**kwargs)

    def forward(self, layers, hw):
        return self.dpt(layers, hw)


@dataclass(frozen=True)
class Dust3rConfig:
    """Constructor arguments of the network (official names where they exist)."""

    enc_embed_dim: int = 1024
    enc_depth: int = 24
    enc_num_heads: int = 16
    enc_mlp_ratio: float = 4.0
    dec_embed_dim: int = 768
    dec_depth: int = 12
    dec_num_heads: int = 12
    dec_mlp_ratio: float = 4.0
    patch_size: int = 16
    rope_freq: float = 100.0
    head_type: str = "dpt"  # 'dpt' or 'linear'
    depth_mode: tuple = ("exp", -math.inf, math.inf)
    conf_mode: tuple = ("exp", 1, math.inf)
    dpt_layer_dims: tuple = (96, 192, 384, 768)
    dpt_feature_dim: int = 256
    dpt_last_dim: int = 128
    img_size: int = 512  # training resolution (long side), 512 or 224 for released files


class Dust3rNet(Dust3rEncoder):
    """Pairwise pointmap network; `forward(img1, img2)` -> pts1, conf1, pts2 (in view 1), conf2.

    It extends the encoder (as the official network extends CroCo's), so the encoder's parameters
    keep their official top-level names (patch_embed.*, enc_blocks.*, enc_norm.*).
    """

    def __init__(self, cfg: Dust3rConfig = Dust3rConfig()):
        if cfg.head_type not in ("dpt", "linear"):
            raise UserError(f"head_type {cfg.head_type!r} is not supported; use 'dpt' or 'linear'")
        if cfg.head_type == "dpt" and cfg.patch_size != 16:
            raise UserError(f"the DPT head needs 16x16 patches, the checkpoint has {cfg.patch_size}")
        super().__init__(cfg.patch_size, cfg.enc_embed_dim, cfg.enc_depth, cfg.enc_num_heads,
                         cfg.enc_mlp_ratio, cfg.rope_freq)
        self.cfg = cfg
        self.decoder_embed = nn.Linear(cfg.enc_embed_dim, cfg.dec_embed_dim)
        self.dec_blocks, self.dec_blocks2 = (
            nn.ModuleList(DecoderBlock(cfg.dec_embed_dim, cfg.dec_num_heads, cfg.dec_mlp_ratio, self.rope)
                          for _ in range(cfg.dec_depth)) for _ in range(2))
        self.dec_norm = nn.LayerNorm(cfg.dec_embed_dim, eps=LAYER_NORM_EPS)
        self.downstream_head1, self.downstream_head2 = (self._make_head(cfg) for _ in range(2))

    @staticmethod
    def _make_head(cfg: Dust3rConfig) -> nn.Module:
        if cfg.head_type == "linear":
            return LinearHead(cfg.dec_embed_dim, cfg.patch_size)
        depth = cfg.dec_depth  # official hooks [0, 6, 9, 12] for 12 blocks; 0 is the encoder output
        return DPTHead(dims_in=[cfg.enc_embed_dim] + [cfg.dec_embed_dim] * 3,
                       hooks=[0, depth * 2 // 4, depth * 3 // 4, depth], layer_dims=cfg.dpt_layer_dims,
                       feature_dim=cfg.dpt_feature_dim, last_dim=cfg.dpt_last_dim,
                       patch_size=cfg.patch_size)

    def encode(self, img: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """img (B,3,H,W) -> encoder tokens (B,P,Ce) and patch positions (B,P,2)."""
        tokens, pos, _ = Dust3rEncoder.forward(self, img)
        return tokens, pos

    def _decode(self, f1, f2, pos1, pos2) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """Encoder tokens (B,P,Ce) of both views -> per view: [encoder tokens, block 1..L outputs],
        the last normalised by dec_norm (each (B,P,Cd) except the first)."""
        out1, out2 = [f1], [f2]
        x1, x2 = self.decoder_embed(f1), self.decoder_embed(f2)  # (B,P,Cd)
        for blk1, blk2 in zip(self.dec_blocks, self.dec_blocks2):
            x1, x2 = blk1(x1, x2, pos1, pos2), blk2(x2, x1, pos2, pos1)  # both see the previous layer
            out1.append(x1)
            out2.append(x2)
        out1[-1], out2[-1] = self.dec_norm(out1[-1]), self.dec_norm(out2[-1])
        return out1, out2

    def forward(self, img1: torch.Tensor, img2: torch.Tensor):
        """img1, img2: (B,3,H,W) in [-1, 1], same size, H and W multiples of the patch size.

        Returns pts1 (B,H,W,3) view 1 in camera 1's frame, conf1 (B,H,W) >= conf_mode[1],
        pts2 (B,H,W,3) view 2 in camera 1's frame, conf2 (B,H,W).
        """
        B, _, H, W = img1.shape
        tokens, pos = self.encode(torch.cat([img1, img2]))  # siamese: one batch (2B,P,Ce)
        (f1, f2), (pos1, pos2) = tokens.split(B), pos.split(B)
        out1, out2 = self._decode(f1, f2, pos1, pos2)
        with torch.autocast(device_type=img1.device.type, enabled=False):  # heads in fp32
            raw1 = self.downstream_head1([t.float() for t in out1], (H, W))  # (B,4,H,W)
            raw2 = self.downstream_head2([t.float() for t in out2], (H, W))
        pts1, conf1 = postprocess(raw1, self.cfg.depth_mode, self.cfg.conf_mode)
        pts2, conf2 = postprocess(raw2, self.cfg.depth_mode, self.cfg.conf_mode)
        return pts1, conf1, pts2, conf2


@dataclass
class LoadReport:
    """What `load_dust3r` did with a file: the network's config, and which keys it did not use."""

    path: Path
    constructor: str
    config: Dust3rConfig
    ignored_keys: list[str] = field(default_factory=list)
    copied_dec_blocks2: bool = False


def config_from_checkpoint(ckpt: OfficialCheckpoint) -> Dust3rConfig:
    """Network sizes from the weights, head counts and output modes from the parsed args.model."""
    sd, args = ckpt.state_dict, ckpt.kwargs
    if "decoder_embed.weight" not in sd or "dec_blocks.0.norm1.weight" not in sd:
        raise UserError(f"{str(ckpt.path)!r} has no DUSt3R decoder (decoder_embed, dec_blocks); pass a "
                        "DUSt3R, MASt3R or MonST3R checkpoint, not an encoder-only or CroCo file")
    enc = encoder_kwargs(ckpt)
    dec_dim = sd["decoder_embed.weight"].shape[0]
    if "downstream_head1.proj.weight" in sd:
        head, channels = "linear", sd["downstream_head1.proj.weight"].shape[0] // enc["patch_size"] ** 2
        dpt = {}
    elif "downstream_head1.dpt.head.0.weight" in sd:
        head, channels = "dpt", sd["downstream_head1.dpt.head.4.weight"].shape[0]
        prefix = "downstream_head1.dpt."
        dpt = dict(dpt_layer_dims=tuple(sd[f"{prefix}act_postprocess.{k}.0.weight"].shape[0] for k in range(4)),
                   dpt_feature_dim=sd[f"{prefix}scratch.layer1_rn.weight"].shape[0],
                   dpt_last_dim=sd[f"{prefix}head.2.weight"].shape[0])
    else:
        raise UserError(f"{str(ckpt.path)!r} has no pointmap head (downstream_head1.proj or .dpt); "
                        "pass a DUSt3R, MASt3R or MonST3R checkpoint")
    if channels != 4:
        raise UserError(f"the pointmap head of {str(ckpt.path)!r} predicts {channels} channels, not "
                        "xyz + confidence; only checkpoints with confidence are supported")
    depth_mode = tuple(args.get("depth_mode", ("exp", -math.inf, math.inf)))
    conf_mode = tuple(args.get("conf_mode", ("exp", 1, math.inf)))
    if depth_mode[0] not in ("exp", "square", "linear") or conf_mode[0] != "exp":
        raise UserError(f"unsupported output modes depth_mode={depth_mode}, conf_mode={conf_mode}; "
                        "official checkpoints use ('exp', -inf, inf) and ('exp', 1, inf)")
    dec_heads = head_count(ckpt, "dec_num_heads", dec_dim)
    return Dust3rConfig(
        enc_embed_dim=enc["embed_dim"], enc_depth=enc["depth"], enc_num_heads=enc["num_heads"],
        enc_mlp_ratio=enc["mlp_ratio"], dec_embed_dim=dec_dim,
        dec_depth=block_count(sd, "dec_blocks."), dec_num_heads=dec_heads,
        dec_mlp_ratio=sd["dec_blocks.0.mlp.fc1.weight"].shape[0] / dec_dim,
        patch_size=enc["patch_size"], rope_freq=enc["rope_freq"], head_type=head,
        depth_mode=depth_mode, conf_mode=conf_mode, img_size=_training_size(args), **dpt)


def _training_size(args: dict[str, Any]) -> int:
    """Long side the network was trained at, from args img_size (int or (H, W)); 512 if absent."""
    size = args.get("img_size", 512)
    return int(max(size) if isinstance(size, (tuple, list)) else size)


def load_dust3r(path: str | Path, map_location: Any = "cpu") -> tuple[Dust3rNet, LoadReport]:
    """Build the network described by an official checkpoint file and load its weights (eval mode).

    Works for DUSt3R 224/512 linear and DPT, MonST3R and MASt3R files (MASt3R's descriptor heads
    are not used: their keys are listed in `LoadReport.ignored_keys` and logged). A file without
    `dec_blocks2` (CroCo-style) gets them copied from `dec_blocks`, as upstream does. Raises
    `UserError` for missing files, unparsable args or weights that do not fit.
    """
    ckpt = read_checkpoint(path, map_location)
    cfg = config_from_checkpoint(ckpt)
    net = Dust3rNet(cfg)
    state = dict(ckpt.state_dict)
    copied = not any(k.startswith("dec_blocks2.") for k in state)
    if copied:
        state |= {"dec_blocks2." + k[len("dec_blocks."):]: v for k, v in state.items()
                  if k.startswith("dec_blocks.")}
    wanted = net.state_dict().keys()
    ignored = sorted(k for k in state if k not in wanted)
    try:
        missing, _ = net.load_state_dict({k: v for k, v in state.items() if k in wanted}, strict=False)
    except RuntimeError as exc:  # a tensor's shape disagrees with the sizes read from the others
        raise UserError(f"the weights in {str(path)!r} are inconsistent ({str(exc).splitlines()[-1].strip()}); "
                        "the file is damaged or not a DUSt3R-family checkpoint") from exc
    if missing:
        raise UserError(f"{str(path)!r} lacks {len(missing)} weights the network needs (e.g. "
                        f"{missing[:3]}); the file is incomplete or not a DUSt3R-family checkpoint")
    if ignored:
        groups = sorted({k.split(".")[0] + "." + k.split(".")[1] if k.count(".") else k for k in ignored})
        log.info("%s: %d checkpoint tensors not used by the pointmap network (%s)", path, len(ignored),
                 ", ".join(groups[:8]))
    report = LoadReport(Path(path), ckpt.constructor, cfg, ignored, copied)
    return net.eval(), report
