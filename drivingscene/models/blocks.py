"""Small building blocks shared by the networks (monodepth2/ResNet style)."""

from __future__ import annotations

import functools
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def conv3x3(in_ch: int, out_ch: int, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(in_ch, out_ch, 3, stride=stride, padding=1, bias=False)


class BasicBlock(nn.Module):
    """ResNet basic block: two 3x3 convs with batch norm and a projected shortcut when needed."""

    def __init__(self, in_ch: int, out_ch: int, stride: int = 1):
        super().__init__()
        self.conv1 = conv3x3(in_ch, out_ch, stride)
        self.bn1 = nn.BatchNorm2d(out_ch)
        self.conv2 = conv3x3(out_ch, out_ch)
        self.bn2 = nn.BatchNorm2d(out_ch)
        self.shortcut = (
            nn.Sequential(nn.Conv2d(in_ch, out_ch, 1, stride=stride, bias=False), nn.BatchNorm2d(out_ch))
            if stride != 1 or in_ch != out_ch
            else nn.Identity()
        )

    def forward(self, x: Tensor) -> Tensor:
        out = F.relu(self.bn1(self.conv1(x)), inplace=True)
        out = self.bn2(self.conv2(out))
        return F.relu(out + self.shortcut(x), inplace=True)


class ConvELU(nn.Module):
    """3x3 conv + ELU, the decoder block of monodepth2 (replicate padding avoids zero-border artefacts and works on 1-pixel maps)."""

    def __init__(self, in_ch: int, out_ch: int):
        super().__init__()
        self.conv = ReplicateConv3x3(in_ch, out_ch)

    def forward(self, x: Tensor) -> Tensor:
        return F.elu(self.conv(x), inplace=True)


class ReplicateConv3x3(nn.Conv2d):
    """``nn.Conv2d(in_ch, out_ch, 3, padding=1, padding_mode="replicate")`` (the same parameters
    and results) with its padding done by `replicate_pad1`."""

    def __init__(self, in_ch: int, out_ch: int):
        super().__init__(in_ch, out_ch, 3, padding=1, padding_mode="replicate")

    def forward(self, x: Tensor) -> Tensor:
        return F.conv2d(replicate_pad1(x), self.weight, self.bias, self.stride, 0, self.dilation, self.groups)


def replicate_pad1(x: Tensor) -> Tensor:
    """``F.pad(x, (1, 1, 1, 1), mode="replicate")`` for ``[B, C, H, W]``: the same values, written
    into one preallocated tensor of ``x``'s memory format (one copy of the interior, then the edge
    rows and columns). On CPU torch's replication pad takes a slow path for channels-last float32
    input (30 ms for a 12 x 32 x 96 x 176 map), and concatenating edges copies the map twice."""
    channels_last = x.dim() == 4 and x.is_contiguous(memory_format=torch.channels_last) and not x.is_contiguous()
    memory_format = torch.channels_last if channels_last else torch.contiguous_format
    out = torch.empty(
        (*x.shape[:-2], x.shape[-2] + 2, x.shape[-1] + 2), dtype=x.dtype, device=x.device, memory_format=memory_format
    )
    out[..., 1:-1, 1:-1] = x
    out[..., 0, 1:-1] = x[..., 0, :]
    out[..., -1, 1:-1] = x[..., -1, :]
    out[..., :, 0] = out[..., :, 1]
    out[..., :, -1] = out[..., :, -2]
    return out


def conv_input(parts: Sequence[Tensor]) -> Tensor:
    """``torch.cat(parts, dim=1)`` laid out for the convolution that reads it: channels-last, in
    the dtype that convolution computes in (autocast's where autocast is on; else the parts'
    promoted dtype). Each part is cast as it is copied in, so where the convolution would have cast
    a float32 input to bf16 itself it gets the same values, without the extra pass; on CPU oneDNN
    also reorders an NCHW or float32 input first, which made a 36-channel 3x3 convolution at
    96 x 176 cost 15 ms instead of 6 (mixed-dtype or mixed-layout concatenations fall back to NCHW
    float32)."""
    first = parts[0]
    device = first.device.type
    if torch.is_autocast_enabled(device) and all(p.is_floating_point() for p in parts):
        dtype = torch.get_autocast_dtype(device)
    else:
        dtype = functools.reduce(torch.promote_types, (p.dtype for p in parts))
    batch, _, height, width = first.shape
    channels = sum(p.shape[1] for p in parts)
    out = torch.empty((batch, channels, height, width), dtype=dtype, device=first.device, memory_format=torch.channels_last)
    start = 0
    for part in parts:
        out[:, start : start + part.shape[1]] = part
        start += part.shape[1]
    return out


def upsample_to(x: Tensor, like: Tensor, mode: str = "nearest") -> Tensor:
    """Resize ``x`` to the spatial size of ``like`` (sizes need not be powers of two)."""
    if x.shape[-2:] == like.shape[-2:]:
        return x
    kwargs = {} if mode == "nearest" else {"align_corners": False}
    return F.interpolate(x, size=like.shape[-2:], mode=mode, **kwargs)


class ResNetEncoder(nn.Module):
    """ResNet-18 layout at a configurable width; returns features at 1/2, 1/4, 1/8, 1/16, 1/32.

    Channels are (w, w, 2w, 4w, 8w) for width w (w = 64 is ResNet-18).
    """

    def __init__(self, in_ch: int = 3, width: int = 32, blocks: tuple[int, ...] = (2, 2, 2, 2)):
        super().__init__()
        self.channels = (width, width, 2 * width, 4 * width, 8 * width)
        self.stem = nn.Sequential(
            nn.Conv2d(in_ch, width, 7, stride=2, padding=3, bias=False), nn.BatchNorm2d(width), nn.ReLU(inplace=True)
        )
        self.pool = nn.MaxPool2d(3, stride=2, padding=1)
        layers = []
        in_c = width
        for i, (out_c, n) in enumerate(zip(self.channels[1:], blocks)):
            stride = 1 if i == 0 else 2
            layers.append(nn.Sequential(BasicBlock(in_c, out_c, stride), *[BasicBlock(out_c, out_c) for _ in range(n - 1)]))
            in_c = out_c
        self.layers = nn.ModuleList(layers)

    def forward(self, x: Tensor) -> list[Tensor]:
        feats = [self.stem(x)]
        x = self.pool(feats[0])
        for layer in self.layers:
            x = layer(x)
            feats.append(x)
        return feats
