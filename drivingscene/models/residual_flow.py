"""R: the residual flow network. Rigid flow (depth + ego motion) explains the static world; R
predicts the non-rigid residual of independently moving objects, so that total = rigid + residual.

Inputs per camera: the source image warped into the target by the rigid flow, the target image
and the rigid flow. One shared encoder (siamese, the same weights for both images and every
camera) builds a feature pyramid at 1/2 ... 1/16; one light pyramidal decoder per camera slot
refines the residual coarse to fine. At each level the decoder warps the source features by the
current residual, compares them with the target features in a local cost volume (PWC-Net style,
radius r; optionally a larger radius at the coarsest level) and predicts an update from [cost, target features, residual, rigid flow, hidden].

With ``hypotheses`` other than ``(1.0,)`` (a deviation from the paper, see docs/training-notes.md):
in driving, most moving objects travel along the ego's road, so their image motion is close to a
*scaled* rigid flow, ``s * rigid``: s = 1 for a parked car, 0 for a car that keeps pace with the
ego (it barely moves in the image, while the rigid flow, which assumes it static, is large when it
is near), between for slower traffic, above 1 for oncoming traffic. A residual that must cancel a
large rigid flow is out of reach of a search around the rigid flow. So R encodes the source image
itself and, at the coarsest level, correlates the target with it warped by ``s * rigid`` for each
s in ``hypotheses`` (one cost volume each; s = 0 is the unwarped source); with ``scale_flow`` that
level also predicts a per-pixel scale, so that its residual is ``(s - 1) * rigid + delta`` and
"moves with the ego" is one number rather than a large regressed vector. Finer levels warp the
source's features by the current total flow (rigid + residual) and refine as above.

Camera slots: a rig of any size V maps each camera to the decoder whose reference yaw is nearest
to the camera's viewing direction in the ego frame (nuScenes-like rigs: one decoder per camera).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from drivingscene import kernels
from drivingscene.geometry.flow import backward_warp
from drivingscene.models.blocks import conv_input


@dataclass(frozen=True)
class FlowConfig:
    channels: tuple[int, ...] = (16, 32, 64, 96)  # encoder at 1/2, 1/4, 1/8, 1/16
    radius: int = 3  # cost-volume search radius in pixels of each level
    # Search radius at the coarsest level (None: ``radius``). Non-rigid motion between keyframes
    # can be a large part of the image width; the coarsest level is where it must be found.
    coarse_radius: int | None = None
    # Scales s of the rigid flow around which the coarsest level searches (module docstring);
    # (1.0,) is the paper's R: around the rigid flow only, on the rigidly warped source image.
    hypotheses: tuple[float, ...] = (1.0,)
    # The coarsest level also predicts a per-pixel scale of the rigid flow (module docstring).
    scale_flow: bool = False
    hidden: int = 32
    decoder_yaws_deg: tuple[float, ...] = (0.0, -55.0, -110.0, 180.0, 110.0, 55.0)
    flow_norm: float = 0.05  # flows enter the network divided by flow_norm * W

    @property
    def own_source(self) -> bool:
        """R encodes the source image itself (not the rigidly warped one)."""
        return tuple(self.hypotheses) != (1.0,)

    @property
    def level_radii(self) -> list[int]:
        """Cost-volume search radius per pyramid level, finest first."""
        coarse = self.radius if self.coarse_radius is None else self.coarse_radius
        return [self.radius] * (len(self.channels) - 1) + [coarse]


def decoder_slots(cam_to_ego: Tensor, yaws_deg: tuple[float, ...]) -> Tensor:
    """Decoder index ``[V]`` for cameras ``[V, 4, 4]``: the nearest reference yaw (circular)."""
    axis = cam_to_ego[:, :3, 2]
    yaw = torch.atan2(axis[:, 1], axis[:, 0])
    ref = torch.tensor(yaws_deg, dtype=yaw.dtype, device=yaw.device) * (math.pi / 180)
    diff = torch.remainder(yaw[:, None] - ref[None, :] + math.pi, 2 * math.pi) - math.pi
    return diff.abs().argmin(dim=1)


def local_cost_volume(target: Tensor, source: Tensor, radius: int) -> Tensor:
    """Correlation ``[B, (2r+1)^2, h, w]`` of target features with source features shifted by up
    to ``radius`` pixels, averaged over channels.

    Without gradients, float32 CPU tensors go through the compiled kernel
    (`drivingscene.kernels.local_cost_volume`, 2-4x faster; the same values up to float rounding)."""
    if kernels.available(kernels.local_cost_volume, "auto", target, source):
        return kernels.local_cost_volume(target, source, radius)
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
    def __init__(self, feat_ch: int, cost_ch: int, hidden: int, has_prev: bool, out_ch: int = 2):
        super().__init__()
        in_ch = cost_ch + feat_ch + 4 + (hidden if has_prev else 0)
        self.body = nn.Sequential(
            nn.Conv2d(in_ch, 48, 3, padding=1),
            nn.LeakyReLU(0.1, inplace=True),
            nn.Conv2d(48, hidden, 3, padding=1),
            nn.LeakyReLU(0.1, inplace=True),
        )
        self.flow = nn.Conv2d(hidden, out_ch, 3, padding=1)
        nn.init.zeros_(self.flow.weight)
        nn.init.zeros_(self.flow.bias)

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        hidden = self.body(x)
        return self.flow(hidden), hidden


class CameraDecoder(nn.Module):
    """The per-level update networks of one camera slot (run by ``ResidualFlowNet``, which
    batches the warps and cost volumes of all slots)."""

    def __init__(self, config: FlowConfig):
        super().__init__()
        n = len(config.channels)
        radii = config.level_radii
        volumes = [1] * (n - 1) + [len(config.hypotheses)]
        outputs = [2] * (n - 1) + [3 if config.scale_flow else 2]
        self.levels = nn.ModuleList(
            LevelDecoder(config.channels[i], volumes[i] * (2 * radii[i] + 1) ** 2, config.hidden, i < n - 1, outputs[i])
            for i in range(n)
        )


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
        source: Tensor | None = None,  # [B, 3, H, W] the source itself: needed with own_source
        finest_level: int = 0,  # stop refining at this level (0: 1/2 resolution, 1: 1/4, ...)
        all_levels: bool = True,  # False: only the finest computed level's flow
    ) -> list[Tensor]:
        """Residual flows ``[B, 2, H, W]`` in pixels, one per pyramid level from the coarsest to
        ``finest_level`` (finest last), each upsampled to full resolution."""
        if not 0 <= finest_level < len(self.config.channels):
            raise ValueError(f"finest_level: expected 0 .. {len(self.config.channels) - 1}, found {finest_level}")
        size = target.shape[-2:]
        if self.config.own_source:
            if source is None:
                raise ValueError("ResidualFlowNet: these hypotheses need the unwarped source images")
            warped_source = source
        both = self.encoder(torch.cat([target, warped_source], dim=0))
        count = target.shape[0]
        groups = [(slot, (slots == slot).nonzero().squeeze(1)) for slot in slots.unique().tolist()]
        flows = self._decode([f[:count] for f in both], [f[count:] for f in both], rigid_flow, groups, size, finest_level)
        flows = flows if all_levels else flows[-1:]
        return [F.interpolate(flow.float(), size=size, mode="bilinear", align_corners=False) for flow in flows]

    def _decode(
        self,
        tgt_feats: list[Tensor],
        src_feats: list[Tensor],
        rigid: Tensor,
        groups: list,
        size: tuple[int, int],
        finest_level: int = 0,
    ) -> list[Tensor]:
        """Residual flows ``[B, 2, h_l, w_l]`` in full-resolution pixels, coarsest first down to
        ``finest_level``. Warps and cost volumes run on all images at once, each slot's decoder on its images.

        ``src_feats`` are the rigidly warped source's features, or with ``own_source`` the
        source's own."""
        config = self.config
        height, width = size
        norm = config.flow_norm * width
        radii = config.level_radii
        flow = hidden = None
        flows = []
        for i in range(len(tgt_feats) - 1, finest_level - 1, -1):
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
            if config.own_source:
                shifts = [s * rigid_l for s in config.hypotheses] if coarsest else [rigid_l + flow]
                costs = []
                for shift in shifts:
                    moved = fs if not shift.any() else backward_warp(fs, (shift * to_level).permute(0, 2, 3, 1))[0]
                    costs.append(local_cost_volume(ft, moved, radii[i]))
                cost = torch.cat(costs, dim=1)
            else:
                if not coarsest:
                    fs, _ = backward_warp(fs, (flow * to_level).permute(0, 2, 3, 1))
                cost = local_cost_volume(ft, fs, radii[i])
            cost = F.leaky_relu(cost, 0.1)
            parts = conv_input([cost, ft, flow / norm, rigid_l / norm] + ([hidden] if hidden is not None else []))
            delta = hidden = None
            for slot, idx in groups:
                d, hid = self.decoders[slot].levels[i](parts if len(groups) == 1 else parts[idx])
                if delta is None:
                    delta = d.new_zeros(parts.shape[0], *d.shape[1:])
                    hidden = hid.new_zeros(parts.shape[0], *hid.shape[1:])
                delta, hidden = delta.index_copy(0, idx, d), hidden.index_copy(0, idx, hid)
            if delta.shape[1] == 3:  # a scale of the rigid flow, then an update on top
                flow = flow + delta[:, 2:] * rigid_l
                delta = delta[:, :2]
            flow = flow + delta / to_level  # the update is predicted in this level's pixels
            flows.append(flow)
        return flows
