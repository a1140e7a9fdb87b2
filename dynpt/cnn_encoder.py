"""The CNN feature encoder (CoTracker3's BasicEncoder design): stride-4 features from 4 fused scales."""

from __future__ import annotations

from typing import Sequence

import torch
import torch.nn.functional as F
from torch import nn


class ResidualBlock(nn.Module):
    """Two 3x3 convs with instance norm (no affine) and ReLU; a strided 1x1 conv on the skip path."""

    def __init__(self, in_ch: int, out_ch: int, stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(in_ch, out_ch, 3, stride=stride, padding=1, padding_mode="zeros")
        self.conv2 = nn.Conv2d(out_ch, out_ch, 3, padding=1, padding_mode="zeros")
        self.norm1 = nn.InstanceNorm2d(out_ch)
        self.norm2 = nn.InstanceNorm2d(out_ch)
        self.downsample = None
        if stride != 1 or in_ch != out_ch:
            self.downsample = nn.Sequential(
                nn.Conv2d(in_ch, out_ch, 1, stride=stride), nn.InstanceNorm2d(out_ch)
            )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu(self.norm1(self.conv1(x)), inplace=True)
        y = F.relu(self.norm2(self.conv2(y)), inplace=True)
        skip = x if self.downsample is None else self.downsample(x)
        return F.relu(skip + y, inplace=True)


class CNNEncoder(nn.Module):
    """Images (B,3,H,W) in [-1,1] -> features (B,out_dim,H/4,W/4), not yet L2-normalised.

    A 7x7 stride-2 stem, then four stages of two residual blocks at strides 2, 4, 8, 16 (widths
    `widths`); all four stage outputs are resized to stride 4, concatenated and fused by a 3x3 conv
    (to 2*out_dim, instance norm, ReLU) and a 1x1 conv (to out_dim). H and W must be multiples of 16.
    `align_corners` is the resize convention (True in CoTracker3, for its weights).
    """

    stride = 4

    def __init__(self, widths: Sequence[int] = (64, 96, 128, 128), out_dim: int = 128,
                 align_corners: bool = False):
        super().__init__()
        self.align_corners = align_corners
        w0, w1, w2, w3 = widths
        self.conv1 = nn.Conv2d(3, w0, 7, stride=2, padding=3)
        self.norm1 = nn.InstanceNorm2d(w0)
        self.layer1 = self._stage(w0, w0, stride=1)
        self.layer2 = self._stage(w0, w1, stride=2)
        self.layer3 = self._stage(w1, w2, stride=2)
        self.layer4 = self._stage(w2, w3, stride=2)
        self.conv2 = nn.Conv2d(w0 + w1 + w2 + w3, 2 * out_dim, 3, padding=1)
        self.norm2 = nn.InstanceNorm2d(2 * out_dim)
        self.conv3 = nn.Conv2d(2 * out_dim, out_dim, 1)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
                nn.init.zeros_(m.bias)

    @staticmethod
    def _stage(in_ch: int, out_ch: int, stride: int) -> nn.Sequential:
        return nn.Sequential(ResidualBlock(in_ch, out_ch, stride), ResidualBlock(out_ch, out_ch, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        size = (x.shape[-2] // 4, x.shape[-1] // 4)
        x = F.relu(self.norm1(self.conv1(x)), inplace=True)  # (B,w0,H/2,W/2)
        a = self.layer1(x)  # stride 2
        b = self.layer2(a)  # stride 4
        c = self.layer3(b)  # stride 8
        d = self.layer4(c)  # stride 16
        resize = lambda f: F.interpolate(f, size=size, mode="bilinear", align_corners=self.align_corners)
        x = torch.cat([resize(a), b, resize(c), resize(d)], dim=1)  # (B,sum(widths),H/4,W/4)
        x = F.relu(self.norm2(self.conv2(x)), inplace=True)
        return self.conv3(x)  # (B,out_dim,H/4,W/4)
