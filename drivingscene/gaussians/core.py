"""Dynamic 3D Gaussians of a frame pair.

Each Gaussian comes from one keyframe (0 or 1) and carries a world displacement ``flow`` towards
the other keyframe (zero for static ones). At normalised time t in [0, 1]:

    keyframe-0 Gaussians sit at  means + t * flow
    keyframe-1 Gaussians sit at  means + (1 - t) * flow

so both sets can be rendered together at any t; how much each set shows is the blend mode. The rule
is defined once, in ``drivingscene.gaussians.timing`` (``means_at`` and ``time_weights`` call it).

Scales and opacities are stored as the raw parameters that 3DGS files hold (log scales, opacity
logits), so files round-trip bit for bit; ``scales`` and ``opacities`` are their activations.
Quaternions need not be unit length (renderers normalise them), again as in 3DGS files.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, fields, replace

import torch
from torch import Tensor

from drivingscene.errors import InputError
from drivingscene.gaussians import timing

# A view-bound Gaussian (`Gaussians.view_rays`) is drawn at full opacity while the angle at its mean
# between the view ray and the ray it was seen along is at most VIEW_FADE_DEG[0], not at all beyond
# VIEW_FADE_DEG[1], linearly in the cosine between (chosen on validation pairs; docs/magnification.md).
VIEW_FADE_DEG = (3.0, 15.0)

SH_C0 = 0.28209479177387814  # Y_0^0; colour = SH_C0 * sh[:, 0] + 0.5 (3DGS convention)


def rgb_to_sh0(rgb: Tensor) -> Tensor:
    """Colours ``[..., 3]`` in [0, 1] to degree-0 SH coefficients."""
    return (rgb - 0.5) / SH_C0


def sh0_to_rgb(sh0: Tensor) -> Tensor:
    return sh0 * SH_C0 + 0.5


def num_sh_coeffs(degree: int) -> int:
    return (degree + 1) ** 2


def sh_degree_from_coeffs(num_coeffs: int) -> int:
    degree = round(num_coeffs**0.5) - 1
    if num_coeffs not in (1, 4, 9, 16) or num_sh_coeffs(degree) != num_coeffs:
        raise InputError(f"sh: expected 1, 4, 9 or 16 coefficients per channel (degree 0-3), found {num_coeffs}")
    return degree


@dataclass(frozen=True, eq=False)
class Gaussians:
    """A set of N dynamic Gaussians (activated values, float32 tensors on one device)."""

    means: Tensor  # [N, 3] world, metres, at their own keyframe
    quats: Tensor  # [N, 4] w, x, y, z, not necessarily unit
    log_scales: Tensor  # [N, 3] log of the standard deviations in metres
    opacity_logits: Tensor  # [N] logit of the opacity
    sh: Tensor  # [N, K, 3] SH coefficients, K = (degree + 1)^2
    flows: Tensor  # [N, 3] world displacement towards the other keyframe
    keyframes: Tensor  # [N] int64, 0 or 1
    cameras: Tensor  # [N] int64 source camera index, -1 if unknown
    # [N, 3] unit direction along which a *view-bound* Gaussian was seen (from its source camera
    # centre to its mean); zero for every other Gaussian. A view-bound Gaussian is one whose depth
    # another input image contradicts (it sees through it: `gaussians.visibility`): drawn at full
    # opacity from its source direction, faded away from it (`view_fade`). None: all zero.
    view_rays: Tensor | None = None

    def __post_init__(self):
        n = self.means.shape[0]
        if self.view_rays is None:
            object.__setattr__(self, "view_rays", self.means.new_zeros(n, 3))
        expected = {
            "means": (n, 3),
            "quats": (n, 4),
            "log_scales": (n, 3),
            "opacity_logits": (n,),
            "flows": (n, 3),
            "keyframes": (n,),
            "cameras": (n,),
            "view_rays": (n, 3),
        }
        for name, shape in expected.items():
            if tuple(getattr(self, name).shape) != shape:
                raise InputError(f"Gaussians.{name}: expected shape {list(shape)}, found {list(getattr(self, name).shape)}")
        if self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3:
            raise InputError(f"Gaussians.sh: expected shape [{n}, K, 3], found {list(self.sh.shape)}")
        sh_degree_from_coeffs(self.sh.shape[1])

    @classmethod
    def create(
        cls,
        means: Tensor,
        quats: Tensor,
        scales: Tensor,
        opacities: Tensor,
        sh: Tensor,
        flows: Tensor | None = None,
        keyframes: Tensor | int = 0,
        cameras: Tensor | int = -1,
    ) -> Gaussians:
        """Build from activated values (scales in metres, opacities in (0, 1)) with defaults: no flow,
        keyframe 0, unknown camera. ``sh`` may be ``[N, 3]`` (degree 0)."""
        n = means.shape[0]
        if sh.ndim == 2:
            sh = sh[:, None, :]
        long = dict(dtype=torch.int64, device=means.device)
        if not torch.is_tensor(keyframes):
            keyframes = torch.full((n,), int(keyframes), **long)
        if not torch.is_tensor(cameras):
            cameras = torch.full((n,), int(cameras), **long)
        return cls(
            means=means,
            quats=torch.nn.functional.normalize(quats, dim=-1),
            log_scales=torch.log(scales),
            opacity_logits=torch.logit(opacities),
            sh=sh,
            flows=torch.zeros_like(means) if flows is None else flows,
            keyframes=keyframes.to(torch.int64),
            cameras=cameras.to(torch.int64),
        )

    @classmethod
    def empty(cls, sh_degree: int = 0, device=None) -> Gaussians:
        z = torch.zeros(0, 3, device=device)
        return cls.create(
            z,
            torch.zeros(0, 4, device=device),
            z,
            torch.zeros(0, device=device),
            torch.zeros(0, num_sh_coeffs(sh_degree), 3, device=device),
        )

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def scales(self) -> Tensor:
        """``[N, 3]`` standard deviations in metres."""
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> Tensor:
        """``[N]`` opacities in (0, 1)."""
        return torch.sigmoid(self.opacity_logits)

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_coeffs(self.sh.shape[1])

    @property
    def device(self) -> torch.device:
        return self.means.device

    @property
    def dynamic(self) -> Tensor:
        """``[N]`` bool: Gaussians that move relative to the world."""
        return self.flows.abs().amax(dim=-1) > 0

    @property
    def view_bound(self) -> Tensor:
        """``[N]`` bool: Gaussians drawn only near the direction they were seen along (`view_rays`)."""
        return self.view_rays.abs().amax(dim=-1) > 0

    def colors(self) -> Tensor:
        """View-independent RGB ``[N, 3]`` from the DC coefficient."""
        return sh0_to_rgb(self.sh[:, 0]).clamp(0, 1)

    def means_at(self, t: float | Tensor) -> Tensor:
        """World positions ``[N, 3]`` at normalised time t (``timing.means_at``)."""
        return timing.means_at(self.means, self.flows, self.keyframes, t)

    def time_weights(self, t: float | Tensor, mode: str = "all") -> Tensor:
        """Opacity multipliers ``[N]`` for showing both keyframes' Gaussians at time t in blend ``mode``
        (``timing.time_weights``: "all", "fade", "nearest"; "layers" and "cameras" weigh 1)."""
        return timing.time_weights(self.keyframes, t, mode, self.means.dtype)

    def at_time(self, t: float | Tensor) -> Gaussians:
        """The Gaussians moved to time t, as static Gaussians of keyframe 0 (for export/rendering)."""
        return replace(
            self, means=self.means_at(t), flows=torch.zeros_like(self.flows), keyframes=torch.zeros_like(self.keyframes)
        )

    def transform(self, a_to_b: Tensor) -> Gaussians:
        """The Gaussians in another frame: ``a_to_b`` ``[4, 4]`` rigid (computed in float64)."""
        from drivingscene.geometry.se3 import matrix_to_quat, quat_multiply

        mat = a_to_b.to(device=self.device, dtype=torch.float64)
        rot, trans = mat[:3, :3], mat[:3, 3]
        means = (self.means.double() @ rot.T + trans).to(self.means.dtype)
        flows = (self.flows.double() @ rot.T).to(self.flows.dtype)
        view_rays = (self.view_rays.double() @ rot.T).to(self.view_rays.dtype)
        quats = quat_multiply(matrix_to_quat(rot).to(self.quats.dtype).expand_as(self.quats), self.quats)
        return replace(self, means=means, flows=flows, quats=quats, view_rays=view_rays)

    def index(self, selector: Tensor | slice | Sequence[int]) -> Gaussians:
        """A subset by bool mask or integer indices."""
        if isinstance(selector, slice):
            return Gaussians(**{f.name: getattr(self, f.name)[selector] for f in fields(self)})
        ids = torch.as_tensor(selector, device=self.means.device)
        if ids.dtype == torch.bool:
            if ids.shape != (len(self),):
                raise IndexError(f"Gaussians.index: a mask of {len(self)} entries expected, found shape {list(ids.shape)}")
            ids = ids.nonzero().squeeze(1)  # once, not once per field
        # index_select: a plain gather (its backward an index_add), several times faster on a CPU
        # than advanced indexing; negative indices count from the end as with indexing
        ids = torch.where(ids < 0, ids + len(self), ids).long()
        return Gaussians(**{f.name: getattr(self, f.name).index_select(0, ids) for f in fields(self)})

    def split(self, sizes: Sequence[int]) -> list[Gaussians]:
        """Consecutive runs of ``sizes`` Gaussians (``torch.split`` of every field: differentiable,
        its backward one concatenation where indexing each run would scatter into a full copy)."""
        parts = {f.name: torch.split(getattr(self, f.name), list(sizes)) for f in fields(self)}
        return [Gaussians(**{name: chunks[i] for name, chunks in parts.items()}) for i in range(len(sizes))]

    def with_sh_degree(self, degree: int) -> Gaussians:
        """Truncate or zero-pad the SH coefficients to ``degree``."""
        k = num_sh_coeffs(degree)
        sh = self.sh[:, :k]
        if sh.shape[1] < k:
            sh = torch.cat([sh, sh.new_zeros(len(self), k - sh.shape[1], 3)], dim=1)
        return replace(self, sh=sh)

    def to(self, device=None, dtype=None) -> Gaussians:
        out = {}
        for f in fields(self):
            value = getattr(self, f.name)
            out[f.name] = value.to(device=device, dtype=dtype) if value.is_floating_point() else value.to(device=device)
        return Gaussians(**out)

    def detach(self) -> Gaussians:
        return Gaussians(**{f.name: getattr(self, f.name).detach() for f in fields(self)})

    @staticmethod
    def cat(parts: Sequence[Gaussians]) -> Gaussians:
        """Concatenate; SH degrees are padded to the highest one."""
        degree = max(p.sh_degree for p in parts)
        parts = [p.with_sh_degree(degree) for p in parts]
        return Gaussians(**{f.name: torch.cat([getattr(p, f.name) for p in parts]) for f in fields(Gaussians)})


def view_fade_cosines() -> tuple[float, float]:
    """The cosines of `VIEW_FADE_DEG`: full opacity at or above the first, none at or below the second."""
    return math.cos(math.radians(VIEW_FADE_DEG[0])), math.cos(math.radians(VIEW_FADE_DEG[1]))


def view_fade(view_rays: Tensor, means: Tensor, centre: Tensor) -> Tensor:
    """``[N]`` opacity multipliers of Gaussians at ``means`` ``[N, 3]`` seen from a camera at
    ``centre`` ``[3]``: 1 for those not view-bound (zero ``view_rays``), else 1 within
    `VIEW_FADE_DEG` [0] of their view ray, 0 beyond [1], linear in the cosine between."""
    full, zero = view_fade_cosines()
    cos = (torch.nn.functional.normalize(means - centre.to(means), dim=-1) * view_rays).sum(-1)
    fade = ((cos - zero) / (full - zero)).clamp(0.0, 1.0)
    return torch.where(view_rays.abs().amax(dim=-1) > 0, fade, torch.ones_like(fade))
