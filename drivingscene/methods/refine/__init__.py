"""Test-time refinement: accuracy for time (docs/refinement.md). The package: this entry point
and its config, `threads` (each phase's threads, by timing), `inputs` (what it reads of the pair),
`params` (what it optimises), `render` (its losses' renders), `adapt` (D adapted to the pair) and
`loop` (the phases in order).

    refine(model_or_none, pair, recon, config, progress, should_stop) -> Reconstruction

From a feed-forward reconstruction, within a budget of seconds:

1. (where the model is given; ``adapt_steps``, by default `DEFAULT_ADAPT_STEPS` without LiDAR) a
   copy of D is adapted to the pair for K self-supervised steps (L_loc + L_smooth at
   ``adapt_scale`` of the image size, `refine.adapt`) and the pair is reconstructed again, both
   within ``adapt_share`` of the budget;
2. (``sweep``, before ``sweep_share`` of the budget, and only where D was not adapted) the depth of every pixel is corrected by a plane sweep over depth, checked across
   images, and LiDAR with ``lidar`` (`depth_sweep`): the Gaussians slide along their rays, and the
   dynamic ones' flows are lifted again with the corrected depth;
3. Adam on the Gaussians' depth along their rays, colours, opacities, scales and the dynamic
   Gaussians' flow, against the input images with L2 (``lpips_weight`` adds the paper's LPIPS term)
   and, with ``lidar``, rendered depth against LiDAR (`refine.render`). Each step renders a few
   input views (all Gaussians, both keyframes) at one image scale, in the blend the output is
   shown with (``blend``).

Anytime: the budget, ``should_stop()`` or ``max_steps`` end it after any step, and what comes back
is a valid reconstruction of the last step whose values were all finite. The held-out frames
(``eval_*``) are never read (`refine.inputs`).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import torch

from drivingscene.data.frame_pair import FramePair
from drivingscene.errors import InputError
from drivingscene.gaussians.recon import Reconstruction
from drivingscene.gaussians.timing import BLEND_MODES, DEFAULT_BLEND
from drivingscene.methods.depth_sweep import SweepConfig
from drivingscene.methods.memory import check_reconstruct_memory
from drivingscene.methods.refine.inputs import refine_inputs
from drivingscene.methods.refine.params import GROUPS, RefineParams, gaussian_rays
from drivingscene.methods.refine.threads import ThreadChoice, typical_step  # noqa: F401 (the package's names)

log = logging.getLogger(__name__)

Progress = Callable[[float | None, str], None]  # (fraction of the budget or None, message), as the viewer's loader


# Steps of test-time adaptation of D where the model is given and no LiDAR is fitted: at a 30 s
# budget 15 beat 5 and none in in-between PSNR, SSIM, ST-LPIPS and depth on two procedural
# validation sets; with LiDAR the gradient steps it leaves no room for are worth more
# (docs/refinement.md, *Adapting D first*).
DEFAULT_ADAPT_STEPS = 15
# The adaptation's share of the budget and the image scale of its losses: at 30 s, half of the
# budget with the losses at half size (about 10 of the 15 steps, each 35-40 % cheaper, then 3-4
# gradient steps) beat the whole budget at full size (15 steps, at most one gradient step) in
# in-between PSNR, SSIM and ST-LPIPS on two procedural validation sets; depth AbsRel equal on one,
# 0.022 worse on the other (docs/refinement.md, *Sharing the budget*).
ADAPT_SHARE = 0.5
ADAPT_SCALE = 0.5


@dataclass(frozen=True)
class RefineConfig:
    seconds: float = 30.0  # wall-clock budget, everything included
    max_steps: int | None = None  # gradient steps at most (None: until the budget ends)
    groups: tuple[str, ...] = GROUPS  # what the gradient steps optimise
    # Adam learning rates per group: log depth, SH colour, opacity logit, log scale, flow (metres)
    lr: tuple[tuple[str, float], ...] = (
        ("depth", 0.005),
        ("color", 0.025),
        ("opacity", 0.05),
        ("scale", 0.005),
        ("flow", 0.01),
    )
    decay: bool = False  # True: learning rates follow a cosine from 1x to 0.1x over the budget (or max_steps)
    views_per_step: int = 3  # cameras of one keyframe rendered per step (keyframes alternate)
    # (fraction of the budget from which it applies, image scale): coarse to fine
    scales: tuple[tuple[float, float], ...] = ((0.0, 1.0),)
    max_layers: int = 16  # Gaussians composited per pixel while refining (rendering uses 32)
    # How the steps combine the Gaussians into an image: the blend the reconstruction is shown with
    # (`DEFAULT_BLEND`, one layer per input image), so that they fit what the user sees. "all" (one
    # layer) was the rule before 2026-11-27 and fitted a rendering no output used (docs/refinement.md).
    blend: str = DEFAULT_BLEND
    # The steps' loss: L2 alone; the paper's rendering loss adds 0.05 LPIPS, which with the cameras
    # blend raised ST-LPIPS and lowered SSIM of the in-between frame on both procedural validation
    # sets, while L2 alone raised PSNR and SSIM and kept ST-LPIPS (docs/refinement.md, 2026-11-27).
    lpips_weight: float = 0.0
    lidar: bool = False  # also fit LiDAR depth (gt_depth), in the sweep and the loss
    lidar_weight: float = 0.1  # weight of the relative L1 depth term
    sweep: SweepConfig | None = field(default_factory=SweepConfig)  # None: no depth correction
    sweep_share: float = 0.5  # the sweep stops (depth unchanged) past this share of the budget
    # CPU threads while refining; None: each phase times its steps on torch's threads and on one and
    # keeps the faster (`ThreadChoice`). Refinement's tensors are small (a few views, 0.1-1 M
    # Gaussians): on these shared 2-core machines two threads stall on each other whenever another
    # job holds a core (measured: 2.9 s per step with 2 threads against 1.1 s with 1 beside one
    # busy process; 0.7 s against 1.1 s on the quiet machine).
    threads: int | None = None
    # Self-supervised steps on D before rebuilding (`refine.adapt`). None: `DEFAULT_ADAPT_STEPS`
    # where the model is given and ``lidar`` is off, else none (a saved reconstruction refined on
    # its own; fitting LiDAR); 0: never. An explicit K needs the model.
    adapt_steps: int | None = None
    adapt_lr: float = 5e-5
    # The adaptation and the reconstruction after it end within this share of the budget (a step
    # begins only where it and the rebuild still fit), leaving the rest to the sweep and the
    # gradient steps.
    adapt_share: float = ADAPT_SHARE
    # The image scale the adaptation's losses are computed at (the depth area-resized to it).
    adapt_scale: float = ADAPT_SCALE
    seed: int = 0

    def __post_init__(self):
        if not self.seconds >= 0 or math.isinf(self.seconds):
            raise InputError(f"--refine: expected a number of seconds >= 0, found {self.seconds}")
        if self.max_steps is not None and self.max_steps < 0:
            raise InputError(f"max_steps: expected >= 0, found {self.max_steps}")
        unknown = set(self.groups) - set(GROUPS)
        if unknown:
            raise InputError(f"groups: expected a subset of {', '.join(GROUPS)}, found {', '.join(sorted(unknown))}")
        if self.views_per_step < 1:
            raise InputError(f"views_per_step: expected >= 1, found {self.views_per_step}")
        if self.threads is not None and self.threads < 1:
            raise InputError(f"--threads: expected a positive number of threads, found {self.threads}")
        if self.adapt_steps is not None and self.adapt_steps < 0:
            raise InputError(f"--adapt: expected a number of steps >= 0, found {self.adapt_steps}")
        if not 0 <= self.adapt_share <= 1:
            raise InputError(f"adapt_share: expected a share of the budget in [0, 1], found {self.adapt_share}")
        if not 0 < self.adapt_scale <= 1:
            raise InputError(f"adapt_scale: expected an image scale in (0, 1], found {self.adapt_scale}")
        if not 0 <= self.sweep_share <= 1:
            raise InputError(f"sweep_share: expected a share of the budget in [0, 1], found {self.sweep_share}")
        if not self.lpips_weight >= 0:
            raise InputError(f"lpips_weight: expected a weight >= 0, found {self.lpips_weight}")
        if self.blend not in BLEND_MODES:
            raise InputError(f"blend: expected one of {', '.join(BLEND_MODES)}, found {self.blend!r}")
        if not self.scales or any(not 0 < s <= 1 for _, s in self.scales):
            raise InputError(f"scales: expected image scales in (0, 1], found {self.scales}")

    def learning_rate(self, group: str) -> float:
        return dict(self.lr)[group]

    def scale_at(self, fraction: float) -> float:
        """The image scale at ``fraction`` of the budget."""
        current = self.scales[0][1]
        for start, scale in self.scales:
            if fraction >= start:
                current = scale
        return current


class Clock:
    """The budget: seconds since the start, and whether another step of ``step_s`` still fits."""

    def __init__(self, seconds: float, should_stop: Callable[[], bool] | None):
        self.start = time.perf_counter()
        self.seconds = seconds
        self.should_stop = should_stop or (lambda: False)

    @property
    def elapsed(self) -> float:
        return time.perf_counter() - self.start

    @property
    def fraction(self) -> float:
        return min(1.0, self.elapsed / self.seconds) if self.seconds > 0 else 1.0

    def fits(self, step_s: float = 0.0, share: float = 1.0) -> bool:
        """Whether ``step_s`` more seconds end within ``share`` of the budget (and no stop was asked)."""
        return not self.should_stop() and self.elapsed + step_s <= share * self.seconds

    def stopped(self) -> bool:
        return self.should_stop() or self.elapsed >= self.seconds

    def stopped_at(self, share: float) -> Callable[[], bool]:
        """A stop test for a stage that may use the budget up to ``share`` of it."""
        return lambda: self.should_stop() or self.elapsed >= share * self.seconds


def _check(pair: FramePair, recon: Reconstruction) -> None:
    if recon.num_views != pair.num_views or tuple(recon.image_size) != tuple(pair.image_size):
        raise InputError(
            f"refine: the reconstruction ({recon.num_views} cameras, {recon.image_size[1]}x{recon.image_size[0]}) "
            f"is not of this scene ({pair.num_views} cameras, {pair.image_size[1]}x{pair.image_size[0]})"
        )
    if len(recon.gaussians) == 0:
        raise InputError("refine: the reconstruction has no Gaussians")


def refine(
    model,
    pair: FramePair,
    recon: Reconstruction,
    config: RefineConfig = RefineConfig(),
    progress: Progress | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> Reconstruction:
    """The refined reconstruction (module docstring); ``model`` (or None) is used only to adapt D."""
    _check(pair, recon)
    check_reconstruct_memory(pair.num_views, *pair.image_size, source="refine", refine=True)
    if config.adapt_steps and model is None:
        raise InputError("--adapt: adapting D needs the model's weights")
    if config.adapt_steps is None:
        config = replace(config, adapt_steps=DEFAULT_ADAPT_STEPS if model is not None and not config.lidar else 0)
    threads = torch.get_num_threads()
    torch.set_num_threads(refine_threads(config))
    try:
        return _refine(model, pair, recon, config, progress, should_stop)
    finally:
        torch.set_num_threads(threads)


def refine_threads(config: RefineConfig) -> int:
    """The threads refinement starts on (``RefineConfig.threads``, else torch's; with None each
    phase then chooses by timing, `ThreadChoice`)."""
    return config.threads if config.threads is not None else torch.get_num_threads()


def _refine(model, pair: FramePair, recon: Reconstruction, config: RefineConfig, progress, should_stop) -> Reconstruction:
    from drivingscene.methods.refine.loop import adapt_and_rebuild, corrected_gaussians, gradient_steps, refined_reconstruction

    clock = Clock(config.seconds, should_stop)
    report = progress or (lambda fraction, message: None)
    torch.manual_seed(config.seed)
    inputs = refine_inputs(pair, config.lidar)
    meta: dict = {"budget_s": config.seconds, "steps": 0, "step_s": None, "threads": torch.get_num_threads()}
    if config.adapt_steps and clock.fits(share=config.adapt_share):
        rebuild_s = float(recon.meta.get("timings", {}).get("total_s", 1.0))  # the feed-forward pass's time
        recon = adapt_and_rebuild(model, pair, recon, inputs, config, clock, report, meta, rebuild_s)
    local = recon.gaussians.transform(inputs.world_to_local)
    rays = gaussian_rays(local, inputs.cam_to_local, inputs.intrinsics, inputs.image_size)
    # The sweep corrects the model's depth; after an adaptation the depth is the adapted D's, which
    # the sweep made worse on procedural pairs (docs/refinement.md, *Sharing the budget*), and the
    # default adaptation leaves it no time before its share ends anyway.
    adapted = bool((meta.get("adapt") or {}).get("steps"))
    if config.sweep is not None and not adapted and clock.fits(share=config.sweep_share):
        local = corrected_gaussians(local, rays, inputs, recon, config, clock, report, meta)
        rays = gaussian_rays(local, inputs.cam_to_local, inputs.intrinsics, inputs.image_size)
    params = RefineParams(local, rays, tuple(config.groups))
    if config.groups and clock.fits():
        gradient_steps(params, inputs, recon, config, clock, report, meta)
    meta["total_s"] = round(clock.elapsed, 3)
    report(1.0, f"refined in {clock.elapsed:.1f} s")
    return refined_reconstruction(recon, params, inputs, meta)


def describe(meta: dict) -> str:
    """One line about a refinement from its ``meta["refinement"]``."""
    steps = meta.get("steps", 0)
    per = f", {meta['step_s']:.2f} s per step" if meta.get("step_s") else ""
    return f"refined {meta.get('total_s', 0):.1f} s: {steps} steps{per}"
