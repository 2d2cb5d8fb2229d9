"""D: the depth network. A ResNet encoder and a monodepth2-style decoder with multi-scale sigmoid
disparities, turned into metric depth with intrinsics-aware scaling, corrected by depth from
matching across time and cameras where that is informative (models/matching.py).

Metric depth (DrivingForward, Tian et al. 2024): the decoder predicts a disparity
``sigma in (0, 1)`` mapped to depth in [min_depth, max_depth] as in monodepth2,

    depth_ref = 1 / (1 / max_depth + (1 / min_depth - 1 / max_depth) * sigma),

which is correct for a camera of the reference focal length; a camera with normalised focal
length f = fx / W sees the same object larger, so depth = depth_ref * f / f_ref. Using fx / W
rather than fx in pixels keeps one trained network valid across image resolutions.

Road prior (``road_prior``): two extra input channels from the rig's geometry, so that one network
serves cameras at any mounting height, pitch and roll: the inverse depth at which the pixel's ray
meets the ego frame's z = 0 plane (the road under the car in nuScenes and DDAD), in the reference
units above (0 where the ray points above the horizon), and the sine of the ray's elevation.

Matching (``match_planes > 0``): the monocular depths of every scale are multiplied by a smooth
correction field computed at 1/2 of the input,

    log depth_s = log mono_s + up(g * (log match - log mono_1/2)),

with the matching depth and the gate g of `MatchingHead`. Where no source sweeps across its image
(ego stopped, no overlap) g = 0 and the depth is the monocular one exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from drivingscene.models.blocks import ConvELU, ReplicateConv3x3, ResNetEncoder, upsample_to
from drivingscene.models.matching import MatchingHead, MatchingOutput, ViewGeometry

INITIAL_DISPARITY_LOGIT = -3.0
# Road prior: inverse road depth is given in units of 1 / ROAD_UNIT metres (reference focal length);
# cameras mounted less than ROAD_MIN_HEIGHT above the ego frame's z = 0 get no road channel (the
# ego origin is then not on the road).
ROAD_UNIT = 2.0
ROAD_MIN_HEIGHT = 0.3


@dataclass(frozen=True)
class DepthConfig:
    width: int = 32  # encoder width (64 = ResNet-18)
    decoder_channels: tuple[int, ...] = (16, 32, 64, 128, 256)  # full, 1/2, 1/4, 1/8, 1/16 resolution
    min_depth: float = 0.5  # metres, for the reference focal length
    max_depth: float = 120.0
    ref_focal: float = 1266.0 / 1600.0  # fx / W of nuScenes' front cameras
    num_scales: int = 4  # disparities at full, 1/2, 1/4, 1/8
    road_prior: bool = True  # two input channels from the rig geometry (module docstring)
    # Plane-sweep matching (models/matching.py); 0 planes: monocular only. Planes are spaced in
    # inverse depth over [match_near, match_far] metres, at 1/2 of the network input.
    match_planes: int = 32
    match_near: float = 1.0
    match_far: float = 80.0
    match_channels: int = 16
    # Source pixels the sweep must cover for a slot to count (at the matching resolution).
    match_min_parallax: float = 0.5


@dataclass
class DepthOutput:
    """Depth network outputs for a batch of B images of H x W."""

    depth: Tensor  # [B, H, W] metric z-depth from the finest scale
    depths: list[Tensor]  # per scale, [B, H, W] metric depth upsampled to full resolution
    disparities: list[Tensor]  # per scale, [B, 1, H_s, W_s] sigmoid outputs
    features: list[Tensor]  # encoder features at 1/2 ... 1/32
    decoder_features: Tensor  # [B, C, H, W] last decoder features (full resolution)
    mono_depths: list[Tensor] | None = None  # per scale, [B, H, W]: before the matching correction
    matching: MatchingOutput | None = None  # at 1/2 resolution

    @property
    def match_depth(self) -> Tensor | None:
        """``[B, H, W]`` the matching depth alone, upsampled to the input (None without matching)."""
        if self.matching is None:
            return None
        size = self.depth.shape[-2:]
        inverse = nn.functional.interpolate(self.matching.inverse_depth, size=size, mode="bilinear", align_corners=False)
        return 1.0 / inverse[:, 0].clamp(min=1e-4)

    @property
    def gate(self) -> Tensor | None:
        """``[B, H, W]`` the matching gate upsampled to the input (None without matching)."""
        if self.matching is None:
            return None
        size = self.depth.shape[-2:]
        return nn.functional.interpolate(self.matching.gate, size=size, mode="bilinear", align_corners=False)[:, 0]


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
        self.heads = nn.ModuleList(ReplicateConv3x3(dec_channels[s], 1) for s in range(num_scales))
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
        self.encoder = ResNetEncoder(5 if config.road_prior else 3, config.width)
        self.decoder = DepthDecoder(self.encoder.channels, config.decoder_channels, config.num_scales)
        self.matching = (
            MatchingHead(
                self.encoder.channels,
                config.match_planes,
                config.match_near,
                config.match_far,
                config.match_channels,
                config.match_min_parallax,
            )
            if config.match_planes > 0
            else None
        )
        # ImageNet-style input normalisation as a buffer, not a parameter.
        # constants, on the CPU also when the model is built on the meta device (`load_model`)
        self.register_buffer("mean", torch.tensor([0.45, 0.45, 0.45], device="cpu").view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor([0.225, 0.225, 0.225], device="cpu").view(1, 3, 1, 1), persistent=False)

    def disparity_to_depth(self, disp: Tensor, intrinsics: Tensor, width: int) -> Tensor:
        """Sigmoid disparity ``[B, 1, h, w]`` -> metric depth ``[B, 1, h, w]`` (module docstring)."""
        cfg = self.config
        lo, hi = 1.0 / cfg.max_depth, 1.0 / cfg.min_depth
        depth_ref = 1.0 / (lo + (hi - lo) * disp)
        focal = intrinsics[:, 0, 0] / width
        return depth_ref * (focal / cfg.ref_focal).view(-1, 1, 1, 1)

    def road_prior(self, intrinsics: Tensor, cam_to_ego: Tensor, height: int, width: int) -> Tensor:
        """``[B, 2, H, W]``: road inverse depth in reference units and the ray's elevation sine."""
        from drivingscene.models.matching import target_rays

        rays = target_rays(intrinsics.float(), height, width)  # [B, H, W, 3], z = 1
        ego_rays = torch.einsum("bij,bhwj->bhwi", cam_to_ego[:, :3, :3].float(), rays)
        mount = cam_to_ego[:, 2, 3].float()  # camera height above the ego frame's z = 0
        focal = intrinsics[:, 0, 0].float() / width / self.config.ref_focal
        scale = torch.where(
            mount > ROAD_MIN_HEIGHT, ROAD_UNIT * focal / mount.clamp(min=ROAD_MIN_HEIGHT), torch.zeros_like(mount)
        )
        road = (-ego_rays[..., 2]).clamp(min=0) * scale.view(-1, 1, 1)
        elevation = ego_rays[..., 2] * torch.rsqrt(ego_rays.square().sum(-1))
        return torch.stack([road, elevation], dim=1)

    def forward(self, images: Tensor, intrinsics: Tensor, geometry: ViewGeometry | None = None) -> DepthOutput:
        """images ``[B, 3, H, W]`` in [0, 1]; intrinsics ``[B, 3, 3]`` in pixels of this size;
        ``geometry`` where the images were taken (the road prior and matching need it: without it
        the prior channels are 0 and there is no matching)."""
        height, width = images.shape[-2:]
        x = (images - self.mean) / self.std
        if self.config.road_prior:
            if geometry is None:
                prior = x.new_zeros(x.shape[0], 2, height, width)
            else:
                prior = self.road_prior(intrinsics, geometry.cam_to_ego, height, width).to(x.dtype)
            channels_last = x.is_contiguous(memory_format=torch.channels_last)
            x = torch.cat([x, prior], dim=1)
            x = x.contiguous(memory_format=torch.channels_last) if channels_last else x
        feats = self.encoder(x)
        disps, dec_feats = self.decoder(feats, (height, width))
        depths = []
        for disp in disps:
            up = nn.functional.interpolate(disp.float(), size=(height, width), mode="bilinear", align_corners=False)
            depths.append(self.disparity_to_depth(up, intrinsics.float(), width)[:, 0])
        if self.matching is None or geometry is None:
            return DepthOutput(depth=depths[0], depths=depths, disparities=disps, features=feats, decoder_features=dec_feats)
        matching = self.matching(feats, images, intrinsics, geometry)
        half = matching.inverse_depth.shape[-2:]
        mono_half = self.disparity_to_depth(
            nn.functional.interpolate(disps[1].float(), size=half, mode="bilinear", align_corners=False),
            intrinsics.float(),
            width,
        )
        log_match = -torch.log(matching.inverse_depth.clamp(min=1e-4))
        correction = matching.gate * (log_match - torch.log(mono_half))  # [B, 1, h, w]
        correction = nn.functional.interpolate(correction, size=(height, width), mode="bilinear", align_corners=False)[:, 0]
        fused = [d * torch.exp(correction) for d in depths]
        return DepthOutput(
            depth=fused[0],
            depths=fused,
            disparities=disps,
            features=feats,
            decoder_features=dec_feats,
            mono_depths=depths,
            matching=matching,
        )
