"""RAFT optical flow (Teed & Deng 2020, the "large" model) loading public weights.

Parameter names follow the original release (`raft-things.pth` etc.: fnet, cnet, update_block.
{encoder,gru,flow_head,mask}; a leading `module.` is removed). Weights saved in torchvision's
`raft_large` layout (feature_encoder, context_encoder, update_block.{motion_encoder,
recurrent_block,flow_head}, mask_predictor) are renamed on load; both are the same network.

The model: a feature encoder (instance norm) on both frames and a context encoder (batch norm) on
the first, at 1/8 resolution, 256 channels each; an all-pairs correlation volume / sqrt(256) with a
4-level average-pooled pyramid, looked up in a (2*4+1)^2 window per level around the current
match; `iters` updates of a separable ConvGRU (1x5 then 5x1) with hidden state 128 predicting
flow increments; a learned convex 8x upsampling (9-neighbour softmax weights, 0.25-scaled mask).
Frames are padded to multiples of 8 (and at least 64 pixels) by edge replication, centred; values
are scaled to [-1, 1].
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from c4d_core.errors import UserError
from c4d_pipeline.flow_inputs import check_flow_inputs
from dynpt.device import device_for
from dynpt.torch_files import read_tensor_file

log = logging.getLogger(__name__)

CORR_LEVELS, CORR_RADIUS = 4, 4
HIDDEN, CONTEXT = 128, 128
WEIGHTS_HINT = "pass raft-things.pth / raft-sintel.pth or torchvision's raft_large weights"


def _norm(kind: str, channels: int) -> nn.Module:
    return nn.InstanceNorm2d(channels) if kind == "instance" else nn.BatchNorm2d(channels)


class ResidualBlock(nn.Module):
    """Two 3x3 conv+norm+ReLU with a (strided 1x1 conv + norm) shortcut when downsampling."""

    def __init__(self, cin: int, cout: int, norm: str, stride: int):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride=stride, padding=1)
        self.conv2 = nn.Conv2d(cout, cout, 3, padding=1)
        self.norm1, self.norm2 = _norm(norm, cout), _norm(norm, cout)
        self.downsample = None
        if stride != 1:
            self.norm3 = _norm(norm, cout)  # registered twice, as in the released files
            self.downsample = nn.Sequential(nn.Conv2d(cin, cout, 1, stride=stride), self.norm3)

    def forward(self, x):
        y = F.relu(self.norm1(self.conv1(x)))
        y = F.relu(self.norm2(self.conv2(y)))
        return F.relu((x if self.downsample is None else self.downsample(x)) + y)


class BasicEncoder(nn.Module):
    """(B,3,H,W) -> (B,out,H/8,W/8): 7x7/2 conv, residual stages 64, 96/2, 128/2, 1x1 conv."""

    def __init__(self, out_dim: int = 256, norm: str = "instance"):
        super().__init__()
        self.conv1 = nn.Conv2d(3, 64, 7, stride=2, padding=3)
        self.norm1 = _norm(norm, 64)
        self.layer1 = nn.Sequential(ResidualBlock(64, 64, norm, 1), ResidualBlock(64, 64, norm, 1))
        self.layer2 = nn.Sequential(ResidualBlock(64, 96, norm, 2), ResidualBlock(96, 96, norm, 1))
        self.layer3 = nn.Sequential(ResidualBlock(96, 128, norm, 2), ResidualBlock(128, 128, norm, 1))
        self.conv2 = nn.Conv2d(128, out_dim, 1)

    def forward(self, x):
        x = F.relu(self.norm1(self.conv1(x)))
        return self.conv2(self.layer3(self.layer2(self.layer1(x))))


class MotionEncoder(nn.Module):
    """Correlation features and current flow -> 126 motion channels + the flow itself (128)."""

    def __init__(self):
        super().__init__()
        cor_planes = CORR_LEVELS * (2 * CORR_RADIUS + 1) ** 2
        self.convc1 = nn.Conv2d(cor_planes, 256, 1)
        self.convc2 = nn.Conv2d(256, 192, 3, padding=1)
        self.convf1 = nn.Conv2d(2, 128, 7, padding=3)
        self.convf2 = nn.Conv2d(128, 64, 3, padding=1)
        self.conv = nn.Conv2d(64 + 192, 128 - 2, 3, padding=1)

    def forward(self, flow, corr):
        cor = F.relu(self.convc2(F.relu(self.convc1(corr))))
        flo = F.relu(self.convf2(F.relu(self.convf1(flow))))
        return torch.cat([F.relu(self.conv(torch.cat([cor, flo], 1))), flow], 1)


class SepConvGRU(nn.Module):
    """ConvGRU run twice: with 1x5 kernels (convz1, convr1, convq1), then 5x1 (convz2, ...)."""

    def __init__(self, hidden: int = HIDDEN, inp: int = CONTEXT + 128):
        super().__init__()
        for k, (size, pad) in enumerate((((1, 5), (0, 2)), ((5, 1), (2, 0))), start=1):
            for gate in "zrq":
                setattr(self, f"conv{gate}{k}", nn.Conv2d(hidden + inp, hidden, size, padding=pad))

    def forward(self, h, x):
        for k in (1, 2):
            hx = torch.cat([h, x], 1)
            z = torch.sigmoid(getattr(self, f"convz{k}")(hx))
            r = torch.sigmoid(getattr(self, f"convr{k}")(hx))
            q = torch.tanh(getattr(self, f"convq{k}")(torch.cat([r * h, x], 1)))
            h = (1 - z) * h + z * q
        return h


class FlowHead(nn.Module):
    def __init__(self):
        super().__init__()
        self.conv1 = nn.Conv2d(HIDDEN, 256, 3, padding=1)
        self.conv2 = nn.Conv2d(256, 2, 3, padding=1)

    def forward(self, x):
        return self.conv2(F.relu(self.conv1(x)))


class UpdateBlock(nn.Module):
    """One refinement step: motion encoding, GRU, flow increment and upsampling mask."""

    def __init__(self):
        super().__init__()
        self.encoder = MotionEncoder()
        self.gru = SepConvGRU()
        self.flow_head = FlowHead()
        self.mask = nn.Sequential(nn.Conv2d(HIDDEN, 256, 3, padding=1), nn.ReLU(), nn.Conv2d(256, 64 * 9, 1))

    def forward(self, net, inp, corr, flow):
        net = self.gru(net, torch.cat([inp, self.encoder(flow, corr)], 1))
        return net, 0.25 * self.mask(net), self.flow_head(net)


def correlation_pyramid(fmap1: torch.Tensor, fmap2: torch.Tensor) -> list[torch.Tensor]:
    """All-pairs correlation of (B,C,h,w) maps -> CORR_LEVELS maps (B*h*w, 1, h/2^l, w/2^l)."""
    B, C, h, w = fmap1.shape
    corr = fmap1.flatten(2).transpose(1, 2) @ fmap2.flatten(2) / C ** 0.5  # (B, h*w, h*w)
    corr = corr.reshape(B * h * w, 1, h, w)
    pyramid = [corr]
    for _ in range(CORR_LEVELS - 1):
        corr = F.avg_pool2d(corr, 2, stride=2)
        pyramid.append(corr)
    return pyramid


def lookup(pyramid: list[torch.Tensor], coords: torch.Tensor) -> torch.Tensor:
    """Correlation windows around coords (B,2,h,w) (x, y at 1/8 res) -> (B, levels*(2r+1)^2, h, w).

    Channel order within a level: index a*(2r+1) + b samples offset (x + d_a, y + d_b), d = -r..r
    (the ordering the released weights were trained with).
    """
    B, _, h, w = coords.shape
    d = torch.linspace(-CORR_RADIUS, CORR_RADIUS, 2 * CORR_RADIUS + 1, device=coords.device)
    offsets = torch.stack(torch.meshgrid(d, d, indexing="ij"), dim=-1)  # (2r+1,2r+1,2): (dx_a, dy_b)
    centre = coords.permute(0, 2, 3, 1).reshape(B * h * w, 1, 1, 2)  # (x, y)
    out = []
    for level, corr in enumerate(pyramid):
        xy = centre / 2 ** level + offsets  # (Bhw, 2r+1, 2r+1, 2)
        size = torch.tensor([corr.shape[-1] - 1, corr.shape[-2] - 1], device=xy.device, dtype=xy.dtype)
        grid = 2 * xy / size.clamp(min=1) - 1
        sampled = F.grid_sample(corr, grid, align_corners=True)  # (Bhw, 1, 2r+1, 2r+1)
        out.append(sampled.reshape(B, h, w, -1))
    return torch.cat(out, dim=-1).permute(0, 3, 1, 2).float()


def upsample_flow(flow: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Convex upsampling: flow (B,2,h,w) and mask (B,576,h,w) -> (B,2,8h,8w)."""
    B, _, h, w = flow.shape
    weights = mask.view(B, 1, 9, 8, 8, h, w).softmax(dim=2)
    neighbours = F.unfold(8 * flow, (3, 3), padding=1).view(B, 2, 9, 1, 1, h, w)
    up = (weights * neighbours).sum(dim=2)  # (B,2,8,8,h,w)
    return up.permute(0, 1, 4, 2, 5, 3).reshape(B, 2, 8 * h, 8 * w)


class RAFT(nn.Module):
    """RAFT-large. `forward(img1, img2)` on (B,3,H,W) in [-1,1], H, W multiples of 8 -> (B,2,H,W)."""

    def __init__(self, iters: int = 20):
        super().__init__()
        self.iters = iters
        self.fnet = BasicEncoder(256, "instance")
        self.cnet = BasicEncoder(HIDDEN + CONTEXT, "batch")
        self.update_block = UpdateBlock()

    def context(self, img1: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Initial hidden state tanh(.) and context relu(.) of the first frames, (B,128,H/8,W/8) each."""
        net, inp = self.cnet(img1).split([HIDDEN, CONTEXT], dim=1)
        return torch.tanh(net), F.relu(inp)

    def refine(self, fmap1, fmap2, net, inp) -> torch.Tensor:
        """Iterate the update block from zero flow; returns the upsampled final flow (B,2,H,W)."""
        pyramid = correlation_pyramid(fmap1.float(), fmap2.float())
        B, _, h, w = fmap1.shape
        ys, xs = torch.meshgrid(torch.arange(h, device=fmap1.device), torch.arange(w, device=fmap1.device),
                                indexing="ij")
        coords0 = torch.stack([xs, ys]).float()[None].expand(B, -1, -1, -1)  # (B,2,h,w) (x, y)
        coords1 = coords0.clone()
        for _ in range(self.iters):
            net, mask, delta = self.update_block(net, inp, lookup(pyramid, coords1), coords1 - coords0)
            coords1 = coords1 + delta
        return upsample_flow(coords1 - coords0, mask)

    def forward(self, img1, img2):
        fmap1, fmap2 = self.fnet(torch.cat([img1, img2])).chunk(2)
        return self.refine(fmap1, fmap2, *self.context(img1))


# torchvision raft_large name -> original name (applied in order, first match wins per rule).
_TORCHVISION_RENAMES = [
    (r"^feature_encoder\.", "fnet."), (r"^context_encoder\.", "cnet."),
    (r"^(fnet|cnet)\.convnormrelu\.0\.", r"\1.conv1."), (r"^(fnet|cnet)\.convnormrelu\.1\.", r"\1.norm1."),
    (r"^(fnet|cnet)\.conv\.", r"\1.conv2."),
    (r"\.convnormrelu1\.0\.", ".conv1."), (r"\.convnormrelu1\.1\.", ".norm1."),
    (r"\.convnormrelu2\.0\.", ".conv2."), (r"\.convnormrelu2\.1\.", ".norm2."),
    (r"^update_block\.motion_encoder\.convcorr(\d)\.0\.", r"update_block.encoder.convc\1."),
    (r"^update_block\.motion_encoder\.convflow(\d)\.0\.", r"update_block.encoder.convf\1."),
    (r"^update_block\.motion_encoder\.conv\.0\.", "update_block.encoder.conv."),
    (r"^update_block\.recurrent_block\.convgru(\d)\.conv([zrq])\.", r"update_block.gru.conv\2\1."),
    (r"^mask_predictor\.convrelu\.0\.", "update_block.mask.0."), (r"^mask_predictor\.conv\.", "update_block.mask.2."),
]


def from_torchvision_names(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Rename a torchvision `raft_large` state dict to the original RAFT names (norm3 duplicated)."""
    out = {}
    for key, value in state.items():
        for pattern, repl in _TORCHVISION_RENAMES:
            key = re.sub(pattern, repl, key)
        out[key] = value
        if ".downsample.1." in key:
            out[key.replace(".downsample.1.", ".norm3.")] = value
    return out


def load_raft(path: str | Path, iters: int = 20) -> RAFT:
    """RAFT-large with the weights of a local file (original or torchvision layout), eval mode."""
    state = read_tensor_file(Path(path), "RAFT", WEIGHTS_HINT, "download it again or pass another file")
    if not isinstance(state, dict):
        raise UserError(f"{str(path)!r} is not a RAFT-large checkpoint (a {type(state).__name__}, not a "
                        f"state dict); {WEIGHTS_HINT}")
    state = {k.removeprefix("module."): v for k, v in state.items() if isinstance(v, torch.Tensor)}
    if any(k.startswith("feature_encoder.") for k in state):
        state = from_torchvision_names(state)
    model = RAFT(iters)
    try:
        missing, unexpected = model.load_state_dict(state, strict=False)
    except RuntimeError:  # tensor shapes differ (e.g. RAFT-small)
        missing, unexpected = ["(shapes differ)"], []
    if missing or unexpected:
        raise UserError(f"{str(path)!r} is not a RAFT-large checkpoint (missing {missing[:3]}, unexpected "
                        f"{unexpected[:3]}); {WEIGHTS_HINT} (RAFT-small is not supported)")
    return model.eval()


class RaftFlow:
    """`FlowEstimator` running RAFT on the requested pairs only (c4d_pipeline.flow protocol).

    Feature maps of each frame involved are computed once and reused by every pair using it.
    """

    def __init__(self, path: str | Path, device=None, iters: int = 20, batch_size: int = 4):
        self.device = device_for(device)
        self.model = load_raft(path, iters).to(self.device)
        self.batch_size = batch_size

    @torch.no_grad()
    def flow(self, frames: np.ndarray, pairs: Sequence[tuple[int, int]]) -> np.ndarray:
        """frames uint8 (T,H,W,3), pairs P x (i, j) -> float32 (P,H,W,2) (dx, dy) from i to j."""
        check_flow_inputs(frames, pairs)
        T, H, W = frames.shape[:3]
        if len(pairs) == 0:
            return np.zeros((0, H, W, 2), np.float32)
        # Pad (edge replication, centred) to multiples of 8 and at least 64 pixels, so that the
        # 4-level correlation pyramid keeps at least one cell at its coarsest level.
        pad_h, pad_w = max(-H % 8, 64 - H), max(-W % 8, 64 - W)
        pad = (pad_w // 2, pad_w - pad_w // 2, pad_h // 2, pad_h - pad_h // 2)
        pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        used = np.unique(pairs)
        images = torch.from_numpy(frames[used]).permute(0, 3, 1, 2).float() / 127.5 - 1.0  # (U,3,H,W)
        images = F.pad(images, pad, mode="replicate")
        slot = {int(t): k for k, t in enumerate(used)}
        feats = []
        for start in range(0, len(used), self.batch_size):
            batch = images[start:start + self.batch_size].to(self.device)
            feats.append(self.model.fnet(batch))
        feats = torch.cat(feats)  # (U,256,H/8,W/8)
        out = np.zeros((len(pairs), H, W, 2), np.float32)
        for start in range(0, len(pairs), self.batch_size):
            chunk = pairs[start:start + self.batch_size]
            src = [slot[int(i)] for i in chunk[:, 0]]
            dst = [slot[int(j)] for j in chunk[:, 1]]
            net, inp = self.model.context(images[src].to(self.device))
            flow = self.model.refine(feats[src], feats[dst], net, inp)  # (b,2,H+ph,W+pw)
            flow = flow[:, :, pad[2]:pad[2] + H, pad[0]:pad[0] + W]
            out[start:start + len(chunk)] = flow.permute(0, 2, 3, 1).cpu().numpy()
        return out
