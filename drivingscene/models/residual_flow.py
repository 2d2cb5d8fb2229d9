"""R: the residual flow network. Rigid flow (depth + ego motion) explains the static world; R
predicts the non-rigid residual of independently moving objects, so that total = rigid + residual.

Inputs per camera: the source image warped into the target by the rigid flow, the target image
and the rigid flow. One shared encoder (siamese, the same weights for both images and every
camera) builds a feature pyramid at 1/2 ... 1/16; one light pyramidal decoder per camera slot
refines the residual coarse to fine. At each level the decoder warps the source features by the
current residual, compares them with the target features in a local cost volume (PWC-Net style,
radius r; optionally a larger radius at the coarsest level) and predicts an update from [cost, target features, residual, rigid flow, hidden].

With ``search_zero`` (a deviation from the paper's input, documented in docs/training-notes.md):
an object that keeps pace with the ego barely moves in the image, while the rigid flow, which
assumes it static, is large for a near one (a car ahead, 5 m away, while the ego drives 5 m). The
residual must then cancel the rigid flow, and a search around it never sees the object. So R
encodes the source image itself, warps its features by the current total flow (rigid + residual)
at each level, and at the coarsest level also compares them unwarped: a second cost volume
centred on total flow 0. The decoder picks between the hypotheses.

Camera slots: a rig of any size V maps each camera to the decoder whose reference yaw is nearest
to the camera's viewing direction in the ego frame (nuScenes-like rigs: one decoder per camera).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from drivingscene.geometry.flow import backward_warp


@dataclass(frozen=True)
class FlowConfig:
    channels: tuple[int, ...] = (16, 32, 64, 96)  # encoder at 1/2, 1/4, 1/8, 1/16
    radius: int = 3  # cost-volume search radius in pixels of each level
    # Search radius at the coarsest level (None: ``radius``). Non-rigid motion between keyframes
    # can be a large part of the image width; the coarsest level is where it must be found.
    coarse_radius: int | None = None
    # Search around "moves with the ego" as well as around "static" (see the module docstring):
    # the source's features (not the rigidly warped image's) are warped by rigid + residual at every
    # level, and the coarsest level also correlates them unwarped (total flow 0).
    search_zero: bool = False
    hidden: int = 32
    decoder_yaws_deg: tuple[float, ...] = (0.0, -55.0, -110.0, 180.0, 110.0, 55.0)
    flow_norm: float = 0.05  # flows enter the network divided by flow_norm * W


def decoder_slots(cam_to_ego: Tensor, yaws_deg: tuple[float, ...]) -> Tensor:
    """Decoder index ``[V]`` for cameras ``[V, 4, 4]``: the nearest reference yaw (circular)."""
    axis = cam_to_ego[:, :3, 2]
    yaw = torch.atan2(axis[:, 1], axis[:, 0])
    ref = torch.tensor(yaws_deg, dtype=yaw.dtype, device=yaw.device) * (math.pi / 180)
    diff = torch.remainder(yaw[:, None] - ref[None, :] + math.pi, 2 * math.pi) - math.pi
    return diff.abs().argmin(dim=1)


def local_cost_volume(target: Tensor, source: Tensor, radius: int) -> Tensor:
    """Correlation ``[B, (2r+1)^2, h, w]`` of target features with source features shifted by up
    to ``radius`` pixels, averaged over channels."""
    height, width = target.shape[-2:]
    padded = F.pad(source, (radius, radius, radius, radius))
    costs = []
    for dy in range(2 * radius + 1):
        for dx in range(2 * radius + 1):
            costs.append((target * padded[..., dy : dy + height, dx : dx + width]).mean(dim=1))
    return torch.stack(costs, dim=1)


class PyramidEncoder(nn.Module):
    def __init__(self, channels: tuple[int, ...]):
        super().__init__()
        layers = []
        in_ch = 3
        for ch in channels:
            layers.append(
                nn.Sequential(
                    nn.Conv2d(in_ch, ch, 3, stride=2, padding=1),
                    nn.LeakyReLU(0.1, inplace=True),
                    nn.Conv2d(ch, ch, 3, padding=1),
                    nn.LeakyReLU(0.1, inplace=True),
                )
            )
            in_ch = ch
        self.levels = nn.ModuleList(layers)

    def forward(self, x: Tensor) -> list[Tensor]:
        feats = []
        for level in self.levels:
            x = level(x)
            feats.append(x)
        return feats


class LevelDecoder(nn.Module):
    def __init__(self, feat_ch: int, cost_ch: int, hidden: int, has_prev: bool):
        super().__init__()
        in_ch = cost_ch + feat_ch + 4 + (hidden if has_prev else 0)
        self.body = nn.Sequential(
            nn.Conv2d(in_ch, 48, 3, padding=1),
            nn.LeakyReLU(0.1, inplace=True),
            nn.Conv2d(48, hidden, 3, padding=1),
            nn.LeakyReLU(0.1, inplace=True),
        )
        self.flow = nn.Conv2d(hidden, 2, 3, padding=1)
        nn.init.zeros_(self.flow.weight)
        nn.init.zeros_(self.flow.bias)

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        hidden = self.body(x)
        return self.flow(hidden), hidden


class CameraDecoder(nn.Module):
    """Coarse-to-fine residual flow for one camera slot."""

    def __init__(self, config: FlowConfig):
        super().__init__()
        self.config = config
        n = len(config.channels)
        coarse = config.radius if config.coarse_radius is None else config.coarse_radius
        self.radii = [config.radius] * (n - 1) + [coarse]
        volumes = [1] * (n - 1) + [2 if config.search_zero else 1]
        self.levels = nn.ModuleList(
            LevelDecoder(config.channels[i], volumes[i] * (2 * self.radii[i] + 1) ** 2, config.hidden, has_prev=i < n - 1)
            for i in range(n)
        )

    def forward(self, tgt_feats: list[Tensor], src_feats: list[Tensor], rigid: Tensor, size: tuple[int, int]) -> list[Tensor]:
        """Residual flows ``[b, 2, h_l, w_l]`` in full-resolution pixels, coarsest first.

        ``src_feats`` are the rigidly warped source's features, or with ``search_zero`` the
        source's own."""
        height, width = size
        norm = self.config.flow_norm * width
        flow = hidden = None
        flows = []
        for i in range(len(tgt_feats) - 1, -1, -1):
            ft, fs = tgt_feats[i], src_feats[i]
            h, w = ft.shape[-2:]
            to_level = ft.new_tensor([w / width, h / height]).view(1, 2, 1, 1)
            rigid_l = F.interpolate(rigid, size=(h, w), mode="bilinear", align_corners=False)
            coarsest = flow is None
            if coarsest:
                flow = ft.new_zeros(ft.shape[0], 2, h, w)
            else:
                flow = F.interpolate(flow, size=(h, w), mode="bilinear", align_corners=False)
                hidden = F.interpolate(hidden, size=(h, w), mode="bilinear", align_corners=False)
            radius = self.radii[i]
            if self.config.search_zero:
                warped, _ = backward_warp(fs, ((rigid_l + flow) * to_level).permute(0, 2, 3, 1))
                costs = [local_cost_volume(ft, warped, radius)]
                if coarsest:  # the other hypothesis: total flow 0, the object moves with the ego
                    costs.append(local_cost_volume(ft, fs, radius))
                cost = torch.cat(costs, dim=1)
            else:
                if not coarsest:
                    fs, _ = backward_warp(fs, (flow * to_level).permute(0, 2, 3, 1))
                cost = local_cost_volume(ft, fs, radius)
            cost = F.leaky_relu(cost, 0.1)
            parts = [cost, ft, flow / norm, rigid_l / norm] + ([hidden] if hidden is not None else [])
            delta, hidden = self.levels[i](torch.cat(parts, dim=1))
            flow = flow + delta / to_level  # the update is predicted in this level's pixels
            flows.append(flow)
        return flows


class ResidualFlowNet(nn.Module):
    """R: (warped source, target, rigid flow) -> residual flow, per camera slot."""

    def __init__(self, config: FlowConfig = FlowConfig()):
        super().__init__()
        self.config = config
        self.encoder = PyramidEncoder(config.channels)
        self.decoders = nn.ModuleList(CameraDecoder(config) for _ in config.decoder_yaws_deg)

    def forward(
        self,
        warped_source: Tensor,  # [B, 3, H, W] source image warped into the target by rigid flow
        target: Tensor,  # [B, 3, H, W]
        rigid_flow: Tensor,  # [B, 2, H, W] pixels
        slots: Tensor,  # [B] decoder index per image
        source: Tensor | None = None,  # [B, 3, H, W] the source itself: needed with search_zero
    ) -> list[Tensor]:
        """Residual flows ``[B, 2, H, W]`` in pixels, one per pyramid level (finest last), each
        upsampled to full resolution."""
        size = target.shape[-2:]
        if self.config.search_zero:
            if source is None:
                raise ValueError("ResidualFlowNet: search_zero needs the unwarped source images")
            warped_source = source
        both = self.encoder(torch.cat([target, warped_source], dim=0))
        tgt_feats = [f[: target.shape[0]] for f in both]
        src_feats = [f[target.shape[0] :] for f in both]
        levels = len(tgt_feats)
        out = [target.new_zeros(target.shape[0], 2, *size) for _ in range(levels)]
        for slot in slots.unique().tolist():
            idx = (slots == slot).nonzero().squeeze(1)
            flows = self.decoders[slot]([f[idx] for f in tgt_feats], [f[idx] for f in src_feats], rigid_flow[idx], size)
            for level, flow in enumerate(flows):
                full = F.interpolate(flow.float(), size=size, mode="bilinear", align_corners=False)
                out[level] = out[level].index_copy(0, idx, full)
        return out
