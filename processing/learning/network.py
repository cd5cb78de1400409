"""The crack segmentation network (PyTorch): a small U-Net that runs on a CPU.

The image enters at half resolution as four phase channels (a lossless space-to-depth),
so no layer runs at full resolution; the head predicts four logits per half-resolution
pixel, rearranged back to full resolution (depth-to-space), which keeps one-pixel cracks
one pixel wide. Five scales (1/2 … 1/32) give a receptive field of a few hundred pixels,
enough to tell a crack from texture. About 0.5 M parameters.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn


@dataclass(frozen=True)
class NetworkParams:
    """Channels per scale, from 1/2 resolution down."""

    channels: tuple[int, ...] = (8, 24, 48, 128, 320)


def _conv(c_in: int, c_out: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(c_in, c_out, 3, stride, 1, bias=False),
        nn.BatchNorm2d(c_out),
        nn.ReLU(inplace=True),
    )


class CrackNet(nn.Module):
    """(B, 1, H, W) grey in [0, 1], H and W even → (B, 1, H, W) crack logits."""

    def __init__(self, params: NetworkParams = NetworkParams()) -> None:
        super().__init__()
        c = params.channels
        self.stem = nn.Sequential(_conv(4, c[0]), _conv(c[0], c[0]))
        self.down = nn.ModuleList(
            nn.Sequential(_conv(c[k], c[k + 1], 2), _conv(c[k + 1], c[k + 1]))
            for k in range(len(c) - 1)
        )
        self.up = nn.ModuleList(
            nn.Sequential(_conv(c[k + 1] + c[k], c[k]), _conv(c[k], c[k]))
            for k in reversed(range(len(c) - 1))
        )
        self.head = nn.Conv2d(c[0] + 4, 4, 3, 1, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.pixel_unshuffle(x - 0.5, 2)
        skips = [self.stem(x)]
        for block in self.down:
            skips.append(block(skips[-1]))
        y = skips.pop()
        for block in self.up:
            s = skips.pop()
            y = F.interpolate(y, size=s.shape[-2:], mode="bilinear", align_corners=False)
            y = block(torch.cat([y, s], 1))
        return F.pixel_shuffle(self.head(torch.cat([y, x], 1)), 2)


def parameter_count(model: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)
