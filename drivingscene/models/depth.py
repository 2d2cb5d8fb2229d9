"""D: the depth network. A ResNet encoder and a monodepth2-style decoder with multi-scale sigmoid
disparities, turned into metric depth with intrinsics-aware scaling.

Metric depth (DrivingForward, Tian et al. 2024): the decoder predicts a disparity
``sigma in (0, 1)`` mapped to depth in [min_depth, max_depth] as in monodepth2,

    depth_ref = 1 / (1 / max_depth + (1 / min_depth - 1 / max_depth) * sigma),

which is correct for a camera of the reference focal length; a camera with normalised focal
length f = fx / W sees the same object larger, so depth = depth_ref * f / f_ref. Using fx / W
rather than fx in pixels keeps one trained network valid across image resolutions.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from drivingscene.models.blocks import ConvELU, ReplicateConv3x3, ResNetEncoder, upsample_to

INITIAL_DISPARITY_LOGIT = -3.0


@dataclass(frozen=True)
class DepthConfig:
    width: int = 32  # encoder width (64 = ResNet-18)
    decoder_channels: tuple[int, ...] = (16, 32, 64, 128, 256)  # full, 1/2, 1/4, 1/8, 1/16 resolution
    min_depth: float = 0.5  # metres, for the reference focal length
    max_depth: float = 120.0
    ref_focal: float = 1266.0 / 1600.0  # fx / W of nuScenes' front cameras
    num_scales: int = 4  # disparities at full, 1/2, 1/4, 1/8


@dataclass
class DepthOutput:
    """Depth network outputs for a batch of B images of H x W."""

    depth: Tensor  # [B, H, W] metric z-depth from the finest scale
    depths: list[Tensor]  # per scale, [B, H, W] metric depth upsampled to full resolution
    disparities: list[Tensor]  # per scale, [B, 1, H_s, W_s] sigmoid outputs
    features: list[Tensor]  # encoder features at 1/2 ... 1/32
    decoder_features: Tensor  # [B, C, H, W] last decoder features (full resolution)


class DepthDecoder(nn.Module):
    def __init__(self, enc_channels: tuple[int, ...], dec_channels: tuple[int, ...], num_scales: int):
        super().__init__()
        self.num_scales = num_scales
        self.up0 = nn.ModuleList()
        self.up1 = nn.ModuleList()
        in_ch = enc_channels[-1]
        for i in range(4, -1, -1):
            self.up0.append(ConvELU(in_ch, dec_channels[i]))
            skip = enc_channels[i - 1] if i > 0 else 0
            self.up1.append(ConvELU(dec_channels[i] + skip, dec_channels[i]))
            in_ch = dec_channels[i]
        self.heads = nn.ModuleList(
            ReplicateConv3x3(dec_channels[s], 1) for s in range(num_scales)
        )
        for head in self.heads:  # start near 10 m (sigmoid(-3) ~ 0.047), a street's typical depth
            nn.init.constant_(head.bias, INITIAL_DISPARITY_LOGIT)

    def forward(self, feats: list[Tensor], out_size: tuple[int, int]) -> tuple[list[Tensor], Tensor]:
        """Returns sigmoid disparities finest first and the full-resolution features."""
        x = feats[-1]
        disps: dict[int, Tensor] = {}
        for step, i in enumerate(range(4, -1, -1)):
            x = self.up0[step](x)
            if i > 0:
                x = self.up1[step](torch.cat([upsample_to(x, feats[i - 1]), feats[i - 1]], dim=1))
            else:
                x = self.up1[step](nn.functional.interpolate(x, size=out_size, mode="nearest"))
            if i < self.num_scales:
                disps[i] = torch.sigmoid(self.heads[i](x))
        return [disps[s] for s in range(self.num_scales)], x


class DepthNet(nn.Module):
    """D: images -> metric depth (multi-scale) and the features the Gaussian head reuses."""

    def __init__(self, config: DepthConfig = DepthConfig()):
        super().__init__()
        self.config = config
        self.encoder = ResNetEncoder(3, config.width)
        self.decoder = DepthDecoder(self.encoder.channels, config.decoder_channels, config.num_scales)
        # ImageNet-style input normalisation as a buffer, not a parameter.
        self.register_buffer("mean", torch.tensor([0.45, 0.45, 0.45]).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor([0.225, 0.225, 0.225]).view(1, 3, 1, 1), persistent=False)

    def disparity_to_depth(self, disp: Tensor, intrinsics: Tensor, width: int) -> Tensor:
        """Sigmoid disparity ``[B, 1, h, w]`` -> metric depth ``[B, 1, h, w]`` (module docstring)."""
        cfg = self.config
        lo, hi = 1.0 / cfg.max_depth, 1.0 / cfg.min_depth
        depth_ref = 1.0 / (lo + (hi - lo) * disp)
        focal = intrinsics[:, 0, 0] / width
        return depth_ref * (focal / cfg.ref_focal).view(-1, 1, 1, 1)

    def forward(self, images: Tensor, intrinsics: Tensor) -> DepthOutput:
        """images ``[B, 3, H, W]`` in [0, 1]; intrinsics ``[B, 3, 3]`` in pixels of this size."""
        height, width = images.shape[-2:]
        feats = self.encoder((images - self.mean) / self.std)
        disps, dec_feats = self.decoder(feats, (height, width))
        depths = []
        for disp in disps:
            up = nn.functional.interpolate(disp.float(), size=(height, width), mode="bilinear", align_corners=False)
            depths.append(self.disparity_to_depth(up, intrinsics.float(), width)[:, 0])
        return DepthOutput(depth=depths[0], depths=depths, disparities=disps, features=feats, decoder_features=dec_feats)
