"""Training configuration: frozen dataclasses, saved as JSON beside every checkpoint."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, fields, replace

from drivingscene.models.model import ModelConfig

STAGES = ("static", "dynamic", "joint", "gaussians", "depth")
# What L_render renders (TrainStep.render_term), in turn: the intermediate frame (when the pair has
# one), the other keyframe from one keyframe's Gaussians ("cross"), and a keyframe's own input
# views from both keyframes' Gaussians ("input").
RENDER_VIEWS = ("eval", "cross", "input")
# Runs saved before these settings existed rendered the first two, blending "all".
LEGACY_RENDER = {"render_views": ("eval", "cross"), "render_blend": "all"}


@dataclass(frozen=True)
class LossWeights:
    """The paper's weights. Stage 1: 0.1 L_loc + 0.001 L_smooth + 0.01 L_render;
    stage 2: 0.02 L_warp + 1e-5 L_consist + 0.01 L_render."""

    loc: float = 0.1
    smooth: float = 0.001
    render: float = 0.01
    warp: float = 0.02
    consist: float = 1e-5
    render_lpips: float = 0.05  # inside L_render: L2 + 0.05 LPIPS
    warp_ssim: float = 0.1  # inside L_warp: L1 + 0.1 SSIM + 0.05 LPIPS
    warp_lpips: float = 0.05
    # Not in the paper (0 = its recipe): L1 of the total flow against a synthetic pair's exact
    # ground-truth flow, for pre-training R on the procedural benchmark (``--flow-supervision``).
    flow_sup: float = 0.0
    # Not in the paper (0 = its recipe): L1 of log depth against a synthetic pair's exact depth
    # (``--depth-supervision``), for the depth of moving objects that L_loc cannot teach.
    depth_sup: float = 0.0
    # Not in the paper (0 = its recipe): L1 of R's flow against the search along the rigid flow
    # (`search_motion`, no gradient) where the search overrides R and its flow is forward/backward
    # consistent (``--search-supervision``). Self-supervised: needs no ground truth.
    search_sup: float = 0.0


@dataclass(frozen=True)
class TrainConfig:
    stage: str = "static"
    data: str = ""  # folder of pair_*.npz (drivingscene synth --split train); several: comma-separated
    val_data: str = ""  # folder(s) for periodic validation ("" = none), as ``data``
    out: str = "runs/static"
    init: str = ""  # weights to start from (stage 2 starts from stage 1's)
    steps: int = 10000
    lr: float = 1e-4
    # R's learning rate (None: ``lr``). The paper trains everything at 1e-4; our CPU budget gives
    # stage 2 a few thousand steps, and R at 5e-4 lowers the flow error ~3x faster there.
    flow_lr: float | None = None
    batch_pairs: int = 1  # frame pairs per step and process (the paper: batch 1)
    seed: int = 0
    threads: int = 2
    # bf16 autocast for the networks (the rasterizer stays float32). None: where the CPU does bf16
    # natively (drivingscene.precision), True/False: forced. `train` resolves it; the run's
    # config.json records the choice made and, in ``amp_auto``, whether it was the machine's.
    amp: bool | None = None
    amp_auto: bool = False  # set by `resolve_precision`: ``amp`` was decided for the machine, not forced
    lpips: str = "auto"  # perceptual metric: auto | lpips | stlpips
    render_every: int = 1  # L_render on every n-th step (it is the most expensive term)
    # Photometric jitter of D's input (`train.augment`; the losses compare the original images)
    # at this strength in stages that train D (static, depth, joint); 0: none.
    input_jitter: float = 0.0
    # L_render's targets (RENDER_VIEWS), rendered in turn, and how both keyframes' Gaussians combine
    # in them: "layers", as every rendered view at inference, or "all" (Gaussians.time_weights).
    render_views: tuple[str, ...] = RENDER_VIEWS
    render_blend: str = "layers"
    log_every: int = 10
    val_every: int = 500
    val_pairs: int = 8
    ckpt_every: int = 100
    keep_checkpoints: int = 2
    weights: LossWeights = field(default_factory=LossWeights)
    model: ModelConfig = field(default_factory=ModelConfig)

    def __post_init__(self):
        if self.stage not in STAGES:
            raise ValueError(f"stage: expected one of {STAGES}, found {self.stage!r}")
        object.__setattr__(self, "render_views", tuple(self.render_views))
        unknown = [v for v in self.render_views if v not in RENDER_VIEWS]
        if unknown or not self.render_views:
            raise ValueError(f"render_views: expected some of {RENDER_VIEWS}, found {list(self.render_views)}")
        if not (self.input_jitter >= 0.0 and self.input_jitter <= 2.0):
            raise ValueError(f"input_jitter: expected a strength in [0, 2], found {self.input_jitter}")
        if self.render_blend not in ("all", "layers"):
            raise ValueError(f"render_blend: expected 'all' or 'layers', found {self.render_blend!r}")

    def to_dict(self) -> dict:
        return asdict(self)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=True)

    @classmethod
    def from_dict(cls, data: dict) -> TrainConfig:
        data = dict(data)
        weights = LossWeights(**data.pop("weights", {}))
        model = ModelConfig.from_dict(data.pop("model", {}))
        if "amp_auto" in data:  # a resolved config: an automatic choice is made again where it is loaded
            data["amp"] = None if data.pop("amp_auto") else data.get("amp")
        elif data.get("amp") is True:  # saved before the choice was automatic: True was the default
            data["amp"] = None
        for key, value in LEGACY_RENDER.items():
            data.setdefault(key, value)
        known = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in known}, weights=weights, model=model)

    def with_overrides(self, **kwargs) -> TrainConfig:
        return replace(self, **{k: v for k, v in kwargs.items() if v is not None})

    def resolve_precision(self) -> TrainConfig:
        """The config with ``amp`` decided for this machine's CPU where it is None (auto)."""
        if self.amp is not None and not self.amp_auto:
            return self
        from drivingscene.precision import auto_amp, env_amp

        forced = env_amp()  # DRIVINGSCENE_AMP
        if forced is not None:
            return replace(self, amp=forced, amp_auto=False)
        return replace(self, amp=auto_amp("cpu"), amp_auto=True)
