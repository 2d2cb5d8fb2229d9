"""P: the Gaussian-parameter network. From image features (D's encoder, shared) and depth features
(D's decoder output and the depth itself) it predicts, per pixel, the attributes that depth does
not give: scale, rotation, opacity and colour.

Each attribute is predicted as a bounded change to a sensible default, and the output layer starts
at zero, so an untrained head already gives the assembly's default surfels (flat Gaussians lying in
the surface of the predicted depth, one pixel footprint wide; ``gaussians.assembly.surfel_frames``),
with the pixel's colour and high opacity:

    log_scale = log(surfel scales(depth)) + 2 tanh(raw / 2)      (x0.14 .. x7.4)
    quat      = surfel rotation(depth) * normalise((1, 0, 0, 0) + raw)   (camera axes)
    opacity   = sigmoid(raw + 3)
    colour    = pixel RGB + 0.5 tanh(raw)  -> SH DC; higher SH degrees start at zero
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from drivingscene import kernels
from drivingscene.gaussians.assembly import FOOTPRINT, MIN_COS, THICKNESS, surfel_frames
from drivingscene.gaussians.core import SH_C0, num_sh_coeffs, rgb_to_sh0
from drivingscene.geometry.se3 import quat_multiply
from drivingscene.models.blocks import ConvELU, ReplicateConv3x3, conv_input, upsample_to

OPACITY_BIAS = 3.0


@dataclass(frozen=True)
class GaussianHeadConfig:
    channels: tuple[int, ...] = (16, 16, 32, 64)  # full, 1/2, 1/4, 1/8 resolution
    sh_degree: int = 0


@dataclass
class PixelGaussians:
    """Per-pixel Gaussian attributes for B images (camera axes)."""

    log_scales: Tensor  # [B, H, W, 3]
    quats: Tensor  # [B, H, W, 4] w, x, y, z, unit, camera axes
    opacity_logits: Tensor  # [B, H, W]
    sh: Tensor  # [B, H, W, K, 3]


class GaussianHead(nn.Module):
    def __init__(self, enc_channels: tuple[int, ...], depth_channels: int, config: GaussianHeadConfig = GaussianHeadConfig()):
        super().__init__()
        self.config = config
        ch = config.channels
        # Coarse-to-fine over D's encoder features at 1/8, 1/4, 1/2.
        self.lateral = nn.ModuleList(ConvELU(enc_channels[i], ch[i + 1]) for i in range(3))
        self.fuse = nn.ModuleList(ConvELU(ch[i + 1] + (ch[i + 2] if i < 2 else 0), ch[i + 1]) for i in range(3))
        full_in = ch[1] + depth_channels + 3 + 1  # upsampled features, depth features, image, log depth
        self.full = nn.Sequential(ConvELU(full_in, ch[0]), ConvELU(ch[0], ch[0]))
        k = num_sh_coeffs(config.sh_degree)
        self.num_out = 3 + 4 + 1 + 3 * k
        self.out = ReplicateConv3x3(ch[0], self.num_out)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def forward(
        self,
        images: Tensor,  # [B, 3, H, W] in [0, 1]
        depth: Tensor,  # [B, H, W] metric
        intrinsics: Tensor,  # [B, 3, 3]
        enc_features: list[Tensor],  # D's encoder features at 1/2 ... 1/32
        depth_features: Tensor,  # [B, C, H, W] D's last decoder features
    ) -> PixelGaussians:
        raw = self.predict_raw(images, depth, enc_features, depth_features)
        return self.activate(raw, images, depth, intrinsics)

    def predict_raw(self, images: Tensor, depth: Tensor, enc_features: list[Tensor], depth_features: Tensor) -> Tensor:
        """The network's raw per-pixel outputs ``[B, H, W, C]`` before :meth:`activate` (they can be
        resized to another image size and activated there)."""
        x = None
        for i in (2, 1, 0):  # 1/8, 1/4, 1/2
            lat = self.lateral[i](enc_features[i])
            x = self.fuse[i](lat if x is None else torch.cat([lat, upsample_to(x, lat)], dim=1))
        log_depth = torch.log(depth.clamp(min=1e-3))[:, None]
        x = conv_input([upsample_to(x, images), depth_features, images, (log_depth - 2.5) / 1.5])
        return self.out(self.full(x)).float().permute(0, 2, 3, 1)  # [B, H, W, C]

    def activate(self, raw: Tensor, images: Tensor, depth: Tensor, intrinsics: Tensor) -> PixelGaussians:
        """Attributes from raw outputs ``[B, H, W, C]``, the image, depth and intrinsics (module docstring).

        Geometry stays float32 even inside a bf16 autocast region (the surfel covariances need it)."""
        with torch.autocast(raw.device.type, enabled=False):
            # raw is often a channels-last view of an NCHW tensor: per-pixel math on its strided
            # last dimension is several times slower than one contiguous copy.
            raw, images, depth, intrinsics = raw.float().contiguous(), images.float(), depth.float(), intrinsics.float()
            # the same arithmetic in one compiled pass (~2x faster), inference only
            if kernels.available(kernels.activate_surfels, "auto", raw, images, depth):
                log_scales, quats, opacity_logits, sh = kernels.activate_surfels(
                    depth.detach(), intrinsics, raw, images, FOOTPRINT, THICKNESS, MIN_COS, OPACITY_BIAS, SH_C0
                )
                return PixelGaussians(log_scales=log_scales, quats=quats, opacity_logits=opacity_logits, sh=sh)
            return self._activate(raw, images, depth, intrinsics)

    def _activate(self, raw: Tensor, images: Tensor, depth: Tensor, intrinsics: Tensor) -> PixelGaussians:
        k = num_sh_coeffs(self.config.sh_degree)
        base_quats, base_log_scales = surfel_frames(depth.detach().float(), intrinsics.float())
        log_scales = base_log_scales + 2.0 * torch.tanh(raw[..., 0:3] / 2.0)
        identity = raw.new_tensor([1.0, 0.0, 0.0, 0.0])
        quats = quat_multiply(base_quats, nn.functional.normalize(identity + raw[..., 3:7], dim=-1))
        opacity_logits = raw[..., 7] + OPACITY_BIAS
        rgb = images.float().permute(0, 2, 3, 1) + 0.5 * torch.tanh(raw[..., 8:11])
        sh_rest = raw[..., 11:].reshape(*raw.shape[:3], k - 1, 3)
        sh = torch.cat([rgb_to_sh0(rgb)[..., None, :], sh_rest], dim=-2)
        return PixelGaussians(log_scales=log_scales, quats=quats, opacity_logits=opacity_logits, sh=sh)
