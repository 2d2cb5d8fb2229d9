"""Learned perceptual distance: LPIPS v0.1 and shift-tolerant LPIPS, with our own network code.

LPIPS (Zhang et al., "The Unreasonable Effectiveness of Deep Features as a Perceptual Metric",
CVPR 2018), eq. 1:

    d(x, y) = sum_l 1 / (H_l W_l) sum_{h,w} || w_l * (f^l_hw(x) - f^l_hw(y)) ||^2

with f^l the trunk activations at five ReLU layers, unit-normalised along channels, and w_l a
learned non-negative per-channel weight (a 1x1 convolution without bias). Inputs go from [0, 1]
to [-1, 1] and then through the fixed ImageNet "scaling layer" (x - shift) / scale.

Two weight sets (``.name`` says which; report it beside every number, they are not comparable):

- ``"ST-LPIPS (alex|vgg)"``: shift-tolerant LPIPS (Ghildyal & Liu, ECCV 2022), anti-aliased trunk
  (``backbones.py``) trained end to end. Ships complete with the ``stlpips-pytorch`` wheel, so it
  always works here. Not numerically the original LPIPS.
- ``"LPIPS (alex|vgg)"``: the original LPIPS v0.1, used when the torchvision trunk and the LPIPS
  heads are on disk (``lpips_weights.py`` lists where they are searched).

Differences from the reference code, all numerically neutral (< 2e-6) or intended: x and y go
through the trunk in separate passes (backward then skips the target's input gradient) in
channels_last layout; features are normalised and compared in float32 even under bf16
autocast; no dropout module (the reference's is inactive in eval mode).

Verified against the stlpips_pytorch 0.0.2 reference (alex and vgg, two image sizes, 4 pairs,
values and spatial maps agree to 2e-6): ``tests/eval/test_lpips.py``.

Cost (ST-LPIPS, distance of a batch 6x3x96x176 to a fixed target, gradient w.r.t. the
prediction, 2 CPU cores shared with other jobs, best of 10 runs, seconds):

    ======================  ========  ============  ========  ============
    trunk (machine load)    fwd fp32  fwd+bwd fp32  fwd bf16  fwd+bwd bf16
    ======================  ========  ============  ========  ============
    alex (load ~2)          0.10      0.20          0.064     0.17
    alex (load ~6)          0.29      0.73          0.24      0.42
    vgg  (load ~6)          1.9       3.2           1.2       2.5
    ======================  ========  ============  ========  ============

Medians were 2-5x the best under load. bf16 autocast (``torch.autocast("cpu", torch.bfloat16)``)
changes the distance by 0.1-0.2% on textured images.
"""

from __future__ import annotations

import functools
import logging
import os
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from drivingscene.errors import DrivingSceneError, InputError
from drivingscene.eval.backbones import NETS, make_trunk
from drivingscene.eval.lpips_weights import (
    ENV_DIR,
    WeightFiles,
    check_state,
    lpips_files,
    lpips_state,
    stlpips_files,
    stlpips_state,
)

log = logging.getLogger(__name__)

KINDS = ("lpips", "stlpips")
MIN_SIZE = 32  # smallest H and W for which every trunk still has a non-empty last layer

# ImageNet statistics in the [-1, 1] input range, as in LPIPS's ScalingLayer.
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)
_LABELS = {"lpips": "LPIPS", "stlpips": "ST-LPIPS"}


@dataclass(frozen=True)
class PerceptualConfig:
    kind: str = "stlpips"  # "lpips" (original v0.1) | "stlpips" (shift-tolerant)
    net: str = "alex"  # "alex" | "vgg"


def _unit_normalise(features: Tensor, eps: float = 1e-10) -> Tensor:
    """Divide each pixel's feature vector ``[B, C, h, w]`` by its L2 norm (LPIPS's eps)."""
    return features / (features.square().sum(dim=1, keepdim=True).sqrt() + eps)


class PerceptualMetric(nn.Module):
    """A frozen LPIPS-family distance, differentiable with respect to both images.

    Build with :func:`load_perceptual`; the constructor makes an uninitialised network.
    Parameters never require grad and the network has no train-time behaviour (no dropout or
    batch norm), so ``.train()`` changes nothing. Inputs are cast to the weights' dtype, so
    ``.double()`` gives a float64 evaluation.
    """

    def __init__(self, config: PerceptualConfig):
        super().__init__()
        if config.kind not in KINDS:
            raise InputError(f"kind: expected one of {KINDS}, found {config.kind!r}")
        if config.net not in NETS:
            raise InputError(f"net: expected one of {NETS}, found {config.net!r}")
        self.config = config
        self.name = f"{_LABELS[config.kind]} ({config.net})"
        trunk = make_trunk(config.net, shift_tolerant=config.kind == "stlpips")
        self.features = trunk.features
        self.taps = trunk.taps
        self.heads = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in trunk.channels)
        self.register_buffer("shift", torch.tensor(_SHIFT)[None, :, None, None])
        self.register_buffer("scale", torch.tensor(_SCALE)[None, :, None, None])
        self.requires_grad_(False)
        self.eval()

    def load_files(self, files: WeightFiles) -> PerceptualMetric:
        """Load the weights of ``files`` with a strict key mapping; returns ``self``."""
        expected = self.state_dict()
        if files.kind != self.config.kind or files.net != self.config.net:
            raise DrivingSceneError(f"{files.trunk}: weights for {files.kind}/{files.net}, network is {self.name}")
        if files.heads is None:
            state = stlpips_state(files.trunk, self.taps)
            described = str(files.trunk)
        else:
            state = lpips_state(files.trunk, files.heads)
            state |= {"shift": expected["shift"], "scale": expected["scale"]}
            described = f"{files.trunk} + {files.heads}"
        check_state(described, expected, state)
        self.load_state_dict(state, strict=True)
        return self

    def _check(self, x: Tensor, y: Tensor) -> None:
        if x.ndim != 4 or x.shape[1] != 3:
            raise InputError(f"x: expected shape [B, 3, H, W], found {list(x.shape)}")
        if y.shape != x.shape:
            raise InputError(f"y: expected shape {list(x.shape)} (as x), found {list(y.shape)}")
        if min(x.shape[-2:]) < MIN_SIZE:
            raise InputError(f"x: expected H, W >= {MIN_SIZE}, found {list(x.shape)}")

    def trunk_features(self, image: Tensor) -> list[Tensor]:  # [B, 3, H, W] in [0, 1]
        """Unit-normalised activations at the taps, ``[B, C_l, h_l, w_l]`` each (float32 under bf16)."""
        h = (2.0 * image.to(self.shift.dtype) - 1.0 - self.shift) / self.scale
        # channels_last: oneDNN's fast path for these convolutions and pools on CPU (~1.3x).
        h = h.contiguous(memory_format=torch.channels_last)
        features = []
        for index, layer in enumerate(self.features):
            h = layer(h)
            if index in self.taps:
                features.append(_unit_normalise(h.float() if h.dtype in (torch.bfloat16, torch.float16) else h))
        return features

    def layer_distances(
        self,
        x: Tensor,  # [B, 3, H, W] in [0, 1]
        y: Tensor,  # [B, 3, H, W] in [0, 1]
    ) -> list[Tensor]:
        """Per-layer weighted squared feature differences, ``[B, 1, h_l, w_l]`` each."""
        self._check(x, y)
        # Two passes rather than one on cat([x, y]): backward then skips the input gradient of
        # whichever image does not require grad (the target, in training), half the backward cost.
        distances = []
        for head, fx, fy in zip(self.heads, self.trunk_features(x), self.trunk_features(y)):
            diff = (fx - fy).square()
            distances.append((diff * head.weight.to(diff.dtype)).sum(dim=1, keepdim=True))
        return distances

    def forward(
        self,
        x: Tensor,  # [B, 3, H, W] in [0, 1]
        y: Tensor,  # [B, 3, H, W] in [0, 1]
    ) -> Tensor:
        """The distance, ``[B]`` (0 for identical images; larger is more different)."""
        return sum(d.mean(dim=(1, 2, 3)) for d in self.layer_distances(x, y))

    def spatial_map(
        self,
        x: Tensor,  # [B, 3, H, W] in [0, 1]
        y: Tensor,  # [B, 3, H, W] in [0, 1]
    ) -> Tensor:
        """Per-pixel distance ``[B, H, W]``: each layer's map upsampled bilinearly to the image
        size (align_corners=False), then summed (LPIPS's ``spatial=True``). Its image mean is close
        to, but not exactly, :meth:`forward` (upsampling does not preserve the mean at borders)."""
        size = x.shape[-2:]
        maps = [F.interpolate(d, size=size, mode="bilinear", align_corners=False) for d in self.layer_distances(x, y)]
        return sum(maps)[:, 0]


@functools.lru_cache(maxsize=8)
def _load_cached(files: WeightFiles) -> PerceptualMetric:
    metric = PerceptualMetric(PerceptualConfig(files.kind, files.net)).load_files(files)
    log.info("perceptual metric %s from %s", metric.name, files.trunk)
    return metric


def load_perceptual(
    kind: str = "auto",
    net: str = "alex",
    lpips_dir: str | os.PathLike | None = None,
) -> PerceptualMetric:
    """The perceptual metric, loaded once per weight files and shared (do not modify it).

    Args:
        kind: ``"lpips"`` (original LPIPS v0.1, needs its files on disk), ``"stlpips"``
            (shift-tolerant, from the ``stlpips-pytorch`` wheel), or ``"auto"``: LPIPS when its
            files are found, ST-LPIPS otherwise. Check ``.name`` to see which one you got.
        net: ``"alex"`` or ``"vgg"``.
        lpips_dir: a folder searched first for the original LPIPS files (``alex.pth`` heads and
            ``alexnet-owt-7be5be79.pth`` trunk, or the vgg ones); also ``$DRIVINGSCENE_LPIPS_DIR``.
    """
    if kind not in KINDS + ("auto",):
        raise InputError(f"kind: expected one of {KINDS + ('auto',)}, found {kind!r}")
    if net not in NETS:
        raise InputError(f"net: expected one of {NETS}, found {net!r}")
    files = lpips_files(net, lpips_dir) if kind in ("lpips", "auto") else None
    if files is None and kind == "lpips":
        raise DrivingSceneError(
            f"original LPIPS ({net}) weights not found: put {net}.pth (LPIPS v0.1 heads) and the torchvision "
            f"trunk in ${ENV_DIR} or the torch hub cache, or use kind='stlpips'"
        )
    if files is None:
        files = stlpips_files(net)
        if files is None:
            raise DrivingSceneError(f"ST-LPIPS ({net}) weights not found: install stlpips-pytorch==0.0.2")
    return _load_cached(files)
