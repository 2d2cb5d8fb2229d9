"""The DrivingScene model: the composition root of D (depth), P (Gaussian head) and R (residual flow).

Stage 1 trains D and P (static prior); stage 2 freezes them and trains R (dynamics). The model holds
no state about a particular rig: intrinsics and camera slots are inputs.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from torch import Tensor, nn

from drivingscene.models.depth import DepthConfig, DepthNet, DepthOutput
from drivingscene.models.gaussian_head import GaussianHead, GaussianHeadConfig, PixelGaussians
from drivingscene.models.matching import ViewGeometry
from drivingscene.models.residual_flow import FlowConfig, ResidualFlowNet, decoder_slots


@dataclass(frozen=True)
class ModelConfig:
    depth: DepthConfig = field(default_factory=DepthConfig)
    gaussians: GaussianHeadConfig = field(default_factory=GaussianHeadConfig)
    flow: FlowConfig = field(default_factory=FlowConfig)
    # (H, W) the networks were trained at (set by the trainer from its data). Convolutional depth
    # networks do not transfer across image scales, so inputs of another size are resized to this
    # for the networks, and depth, Gaussian attributes and flow are resized back
    # (models/pipeline.py). None: run the networks at the input size.
    input_size: tuple[int, int] | None = None

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> ModelConfig:
        def tuples(d: dict) -> dict:
            return {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}

        size = data.get("input_size")
        # configs written before these FlowConfig fields existed describe the network without them
        flow = {"coarse_radius": None, "hypotheses": (1.0,), "scale_flow": False, **data.get("flow", {})}
        # and before D had the road prior and matching: a monocular D
        depth = {"road_prior": False, "match_planes": 0, **data.get("depth", {})}
        return cls(
            depth=DepthConfig(**tuples(depth)),
            gaussians=GaussianHeadConfig(**tuples(data.get("gaussians", {}))),
            flow=FlowConfig(**tuples(flow)),
            input_size=None if size is None else (int(size[0]), int(size[1])),
        )


class DrivingSceneModel(nn.Module):
    """D + P + R. See ``drivingscene.models.pipeline`` for how they are chained on a frame pair."""

    def __init__(self, config: ModelConfig = ModelConfig()):
        super().__init__()
        self.config = config
        self.depth_net = DepthNet(config.depth)
        self.gaussian_head = GaussianHead(self.depth_net.encoder.channels, config.depth.decoder_channels[0], config.gaussians)
        self.flow_net = ResidualFlowNet(config.flow)

    def static(
        self, images: Tensor, intrinsics: Tensor, geometry: ViewGeometry | None = None, depth_images: Tensor | None = None
    ) -> tuple[DepthOutput, PixelGaussians]:
        """Stage-1 networks on images ``[B, 3, H, W]`` with intrinsics ``[B, 3, 3]`` taken as
        ``geometry`` says (D's road prior and matching need it). With ``depth_images`` (the same
        shape), D reads them instead and P still reads ``images`` (training's input jitter)."""
        depth = self.depth_net(images if depth_images is None else depth_images, intrinsics, geometry)
        params = self.gaussian_head(images, depth.depth, intrinsics, depth.features, depth.decoder_features)
        return depth, params

    def static_raw(self, images: Tensor, intrinsics: Tensor, geometry: ViewGeometry | None = None) -> tuple[DepthOutput, Tensor]:
        """D and P's raw outputs ``[B, H, W, C]`` (to be resized, then ``gaussian_head.activate``)."""
        depth = self.depth_net(images, intrinsics, geometry)
        raw = self.gaussian_head.predict_raw(images, depth.depth, depth.features, depth.decoder_features)
        return depth, raw

    def residual_flow(
        self,
        warped_source: Tensor,
        target: Tensor,
        rigid_flow: Tensor,
        slots: Tensor,
        source: Tensor | None = None,
        finest_level: int = 0,
        all_levels: bool = True,
    ) -> list[Tensor]:
        """Stage-2 network: residual flows ``[B, 2, H, W]`` per pyramid level, finest last
        (`ResidualFlowNet.forward`)."""
        return self.flow_net(warped_source, target, rigid_flow, slots, source, finest_level, all_levels)

    def camera_slots(self, cam_to_ego: Tensor) -> Tensor:
        """Residual-flow decoder index ``[V]`` for a rig ``[V, 4, 4]``."""
        return decoder_slots(cam_to_ego, self.config.flow.decoder_yaws_deg)

    def parameter_counts(self) -> dict[str, int]:
        return {
            name: sum(p.numel() for p in module.parameters())
            for name, module in (("depth", self.depth_net), ("gaussians", self.gaussian_head), ("flow", self.flow_net))
        }
