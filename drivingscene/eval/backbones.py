"""Feature trunks of the perceptual metrics: AlexNet and VGG16, original and shift-tolerant.

Every trunk is one ``nn.Sequential`` named ``features`` whose layer indices are the indices of the
published networks (torchvision's ``alexnet().features`` / ``vgg16().features``, and the
``features`` of ST-LPIPS's ``invariant_networks``), so weight keys map one to one. The metric
reads the activations after the layers listed in ``taps`` (five ReLU outputs).

The shift-tolerant variants (Ghildyal & Liu, "Shift-tolerant Perceptual Similarity Metric",
ECCV 2022) replace every strided convolution and max-pool by its stride-1 version followed by a
blur-pool (Zhang, "Making Convolutional Networks Shift-Invariant Again", ICML 2019): reflection
padding by 2, a 3x3 binomial filter ([1, 2, 1] outer [1, 2, 1]) / 16 per channel, stride 2.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

NETS = ("alex", "vgg")


class BlurPool2d(nn.Module):
    """Anti-aliased stride-2 downsampling: reflect-pad by 2, 3x3 binomial blur, keep every other pixel.

    The padding of 2 (``filt_size - 1``, ST-LPIPS's ``pad_more=True``) rather than 1 is what the
    shift-tolerant weights were trained with; it makes the output one pixel larger than a
    "same" blur-pool would.
    """

    def __init__(self, channels: int):
        super().__init__()
        taps = torch.tensor([1.0, 2.0, 1.0])
        kernel = taps[:, None] * taps[None, :]
        # Stored in the ST-LPIPS files too (key ``filt``); loaded from there and compared.
        self.register_buffer("filt", (kernel / kernel.sum()).expand(channels, 1, 3, 3).clone())

    def forward(self, x: Tensor) -> Tensor:  # [B, C, H, W] -> [B, C, (H + 1) // 2 + 1, (W + 1) // 2 + 1]
        padded = F.pad(x, (2, 2, 2, 2), mode="reflect")
        return F.conv2d(padded, self.filt.to(x.dtype), stride=2, groups=x.shape[1])


@dataclass(frozen=True)
class Trunk:
    """A feature extractor: the layers, the indices whose outputs are tapped, and their widths."""

    features: nn.Sequential
    taps: tuple[int, ...]  # indices into ``features``; the output after each is one LPIPS layer
    channels: tuple[int, ...]  # channels at each tap


def _conv(c_in: int, c_out: int, kernel: int, stride: int = 1, padding: int = 0) -> nn.Conv2d:
    return nn.Conv2d(c_in, c_out, kernel, stride=stride, padding=padding)


def _relu() -> nn.ReLU:
    return nn.ReLU(inplace=True)  # always right after a conv or a blur, whose backward needs no output


def alexnet_original() -> Trunk:
    """torchvision AlexNet ``features[:12]``; taps relu1..relu5 (as LPIPS v0.1)."""
    layers = [
        _conv(3, 64, 11, stride=4, padding=2), _relu(),  # 0, 1
        nn.MaxPool2d(3, stride=2), _conv(64, 192, 5, padding=2), _relu(),  # 2-4
        nn.MaxPool2d(3, stride=2), _conv(192, 384, 3, padding=1), _relu(),  # 5-7
        _conv(384, 256, 3, padding=1), _relu(),  # 8, 9
        _conv(256, 256, 3, padding=1), _relu(),  # 10, 11
    ]  # fmt: skip
    return Trunk(nn.Sequential(*layers), taps=(1, 4, 7, 9, 11), channels=(64, 192, 384, 256, 256))


def alexnet_shift_tolerant() -> Trunk:
    """ST-LPIPS AlexNet (``variant="shift_tolerant"``, blur filter 3): stride-1 conv1, blur-pools."""
    layers = [
        _conv(3, 64, 11, padding=2), BlurPool2d(64), _relu(),  # 0-2
        nn.MaxPool2d(3, stride=1), BlurPool2d(64), _conv(64, 192, 5, padding=2), _relu(),  # 3-6
        nn.MaxPool2d(3, stride=1), BlurPool2d(192), _conv(192, 384, 3, padding=1), _relu(),  # 7-10
        _conv(384, 256, 3, padding=1), _relu(),  # 11, 12
        _conv(256, 256, 3, padding=1), _relu(),  # 13, 14
    ]  # fmt: skip
    return Trunk(nn.Sequential(*layers), taps=(2, 6, 10, 12, 14), channels=(64, 192, 384, 256, 256))


_VGG16_WIDTHS = ((64, 64), (128, 128), (256, 256, 256), (512, 512, 512), (512, 512, 512))


def _vgg16(shift_tolerant: bool) -> Trunk:
    """VGG16 conv layers up to relu5_3; between blocks a 2x2 max-pool (original: stride 2;
    shift-tolerant: stride 1 then a blur-pool)."""
    layers: list[nn.Module] = []
    taps = []
    c_in = 3
    for block, widths in enumerate(_VGG16_WIDTHS):
        if block > 0:
            if shift_tolerant:
                layers += [nn.MaxPool2d(2, stride=1), BlurPool2d(c_in)]
            else:
                layers.append(nn.MaxPool2d(2, stride=2))
        for width in widths:
            layers += [_conv(c_in, width, 3, padding=1), _relu()]
            c_in = width
        taps.append(len(layers) - 1)
    channels = tuple(widths[-1] for widths in _VGG16_WIDTHS)
    return Trunk(nn.Sequential(*layers), taps=tuple(taps), channels=channels)


def make_trunk(net: str, shift_tolerant: bool) -> Trunk:
    """The trunk for ``net`` in :data:`NETS`."""
    if net == "alex":
        return alexnet_shift_tolerant() if shift_tolerant else alexnet_original()
    if net == "vgg":
        return _vgg16(shift_tolerant)
    raise ValueError(f"net: expected one of {NETS}, found {net!r}")
