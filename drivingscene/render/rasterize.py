"""``rasterize``: differentiable 3D Gaussian splatting for a batch of cameras, on CPU.

Semantics (every backend but gsplat, and the float64 reference ``rasterize_reference``):

1. World covariance ``Σ = R S Sᵀ Rᵀ``, ``R`` from the normalised quaternion (w, x, y, z), ``S = diag(scales)``.
2. EWA projection (``project.py``): ``Σ2D = J W Σ Wᵀ Jᵀ + eps2d·I`` (``EPS2D`` = 0.1 px² low-pass by
   default; 0.3, gsplat's non-antialiased mode, for 3DGS files from other tools), ``J`` the
   pinhole Jacobian at the centre with the 3DGS off-image clamp.
   Pixel centres are at integer coordinates.
3. Culling: camera ``z < near`` or ``z > far``; a 3σ bounding circle (radius ``3·sqrt(λmax(Σ2D))``)
   that contains no pixel centre; opacity < 1/255.
4. Footprint and alpha: ``alpha = min(0.99, opacity·exp(-½ dᵀ Σ2D⁻¹ d))`` for pixel offset ``d``; a
   Gaussian contributes to a pixel only inside its 3σ ellipse (``dᵀ Σ2D⁻¹ d <= 9``) and with
   ``alpha >= 1/255``.
5. Order: per camera, by camera-space ``z`` of the centre (computed in float64), ties by index.
6. Front-to-back compositing ``w_i = alpha_i Π_{j<i} (1 - alpha_j)``; a Gaussian that would bring the
   transmittance below 1e-4 is dropped and the pixel stops (as 3DGS); at most ``max_layers``
   contributing Gaussians per pixel, the front-most ones (the reference has no cap). With
   ``surface_tolerance`` > 0 the pixel's front surface (its first Gaussian and those within that
   relative depth behind it) is averaged instead, ``w_i = A alpha_i / sum alpha`` with
   ``A = 1 - prod (1 - alpha)``, and the rest composited under it (``composite.py``).
7. Outputs: ``colors = Σ w_i c_i + T·background``; ``depths = Σ w_i z_i / Σ w_i`` (camera z of the
   centres, metres), 0 where ``Σ w_i < 1e-6``; ``alphas = Σ w_i = 1 - T``.

Gradients reach means, quats, scales, opacities, colours or SH coefficients, and the background;
culling, ordering and the choice of contributing Gaussians are piecewise constant (no gradient).

Pipeline: ``splats.make_splats`` culls, sorts and projects (with grad) the visible (camera, Gaussian)
pairs; a no-grad pair finder (compiled `drivingscene.kernels.find_pairs` or pure torch, identical result)
picks each pixel's contributing Gaussians into a dense ``[pixels, max_layers]`` buffer; then
``composite.composite`` recomputes alphas and weights over that buffer, with a hand-written backward.

Backends: ``"cpp"`` (compiled pair finding, CPU), ``"torch"`` (any device), ``"gsplat"`` (CUDA only,
optional, see ``gsplat_backend.py``), ``"auto"``: gsplat for CUDA tensors when it is installed, else
cpp when it builds, else torch. Inputs are float32 (float64 works on the torch path).

``max_layers`` (default 32) trades accuracy for speed in dense scenes: with one pixel-sized
Gaussian per pixel (docs/performance.md), 16 layers miss ~17 % of the opacity on average, 32
layers ~0.4 %, 48 layers ~0.003 %.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from drivingscene import kernels
from drivingscene.errors import InputError
from drivingscene.render.project import EPS2D

DEFAULT_MAX_LAYERS = 32
BACKENDS = ("auto", "torch", "cpp", "gsplat")


@dataclass(frozen=True)
class RenderOutput:
    """Rendered images for ``B`` cameras."""

    colors: Tensor  # [B, H, W, C] composited over the background
    depths: Tensor  # [B, H, W] expected camera z (metres): sum(w z) / sum(w); 0 where alpha < 1e-6
    alphas: Tensor  # [B, H, W] accumulated opacity sum(w) = 1 - final transmittance


def rasterize(
    means: Tensor,  # [N, 3] world, metres
    quats: Tensor,  # [N, 4] w, x, y, z (need not be normalised)
    scales: Tensor,  # [N, 3] metres (activated, > 0)
    opacities: Tensor,  # [N] in (0, 1)
    colors: Tensor,  # [N, C] colours, or [N, K, 3] SH coefficients with sh_degree
    viewmats: Tensor,  # [B, 4, 4] world_to_cam
    Ks: Tensor,  # [B, 3, 3] pixels, pixel centres at integer coordinates
    width: int,
    height: int,
    *,
    background: Tensor | None = None,  # [C] or [B, C]; default black
    sh_degree: int | None = None,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = EPS2D,
    max_layers: int = DEFAULT_MAX_LAYERS,
    backend: str = "auto",
    views: Tensor | None = None,  # [N] int: the one camera of the batch each Gaussian is drawn into
    surface_tolerance: float = 0.0,  # > 0: each pixel's front surface averaged (render.composite)
    pair_opacity=None,  # (camera_ids [M], gaussian_ids [M]) -> [M] opacity multipliers (`make_splats`)
) -> RenderOutput:
    """Render RGB, expected depth and alpha of Gaussians into ``B`` cameras.

    ``near``/``far`` are camera-z limits in metres, ``eps2d`` the 2D low-pass in px², ``max_layers``
    the most Gaussians composited per pixel (the front-most contributing ones). With SH colours the
    view direction is from each camera centre to the Gaussian. ``views`` draws each Gaussian into
    one camera of the batch only (its source image, say; -1: none), so that a batch of images each
    of its own Gaussians is one call (not on the gsplat backend). ``surface_tolerance`` > 0 averages
    the splats within that relative depth of each pixel's front-most one instead of compositing
    them (`drivingscene.render.composite`; not on the gsplat backend). Raises ``InputError`` on bad shapes.
    """
    backgrounds = check_inputs(means, quats, scales, opacities, colors, viewmats, Ks, width, height, background, sh_degree)
    if max_layers < 1:
        raise InputError(f"max_layers must be >= 1, found {max_layers}")
    chosen = choose_backend(backend, means)
    if chosen == "gsplat" and backend == "auto" and (views is not None or surface_tolerance > 0 or pair_opacity is not None):
        chosen = "torch"  # what gsplat does not do
    if views is not None and tuple(views.shape) != (means.shape[0],):
        raise InputError(f"views: expected shape [{means.shape[0]}] (one camera per Gaussian), found {list(views.shape)}")
    if chosen == "gsplat":
        if views is not None or surface_tolerance > 0 or pair_opacity is not None:
            raise InputError(
                "views, surface_tolerance and pair_opacity: not supported by the gsplat backend; use backend 'torch' or 'cpp'"
            )
        from drivingscene.render.gsplat_backend import rasterize_gsplat

        rgb, depths, alphas = rasterize_gsplat(
            means, quats, scales, opacities, colors, viewmats, Ks, width, height, backgrounds, sh_degree, near, far, eps2d
        )
        return RenderOutput(colors=rgb, depths=depths, alphas=alphas)
    from drivingscene.render.composite import composite, find_pairs_cpp, find_pairs_torch, pair_inputs
    from drivingscene.render.splats import make_splats

    dtype = means.dtype
    viewmats, Ks, backgrounds = viewmats.to(dtype), Ks.to(dtype), backgrounds.to(dtype)
    s = make_splats(
        means,
        quats,
        scales,
        opacities,
        colors,
        viewmats,
        Ks,
        width,
        height,
        sh_degree=sh_degree,
        near=near,
        far=far,
        eps2d=eps2d,
        views=views,
        pair_opacity=pair_opacity,
    )
    inp = pair_inputs(s, width, height)
    if chosen == "cpp":
        pair_ids = find_pairs_cpp(inp, width, height, max_layers)
    else:
        pair_ids = find_pairs_torch(inp, width, height, max_layers)
    rgb, depth, alpha = composite(
        pair_ids,
        s.means2d,
        s.conics,
        s.opacities,
        s.depths,
        s.colors,
        backgrounds,
        width,
        height,
        compiled=chosen == "cpp",
        surface_tolerance=surface_tolerance,
    )
    return RenderOutput(colors=rgb, depths=depth, alphas=alpha)


def choose_backend(backend: str, means: Tensor) -> str:
    """Resolve ``"auto"`` and check that an explicitly requested backend can run."""
    if backend not in BACKENDS:
        raise InputError(f"backend must be one of {BACKENDS}, found {backend!r}")
    if backend == "gsplat" or (backend == "auto" and means.is_cuda):
        from drivingscene.render.gsplat_backend import gsplat_available

        if gsplat_available() and means.is_cuda:
            return "gsplat"
        if backend == "gsplat":
            raise InputError("backend 'gsplat' needs CUDA tensors and an importable gsplat")
    if means.device.type != "cpu":
        if backend == "cpp":
            raise InputError(f"backend 'cpp' runs on CPU tensors, found device {means.device}")
        return "torch"
    if backend in ("cpp", "auto"):
        if kernels.load_extension():
            return "cpp"
        if backend == "cpp":
            raise InputError("backend 'cpp' requested but the C++ step could not be built (see the logged warning)")
    return "torch"


def _check_shape(name: str, t: Tensor, shape: tuple) -> None:
    """Raise ``InputError`` unless ``t`` has ``shape`` (``None`` matches any size)."""
    if t.dim() != len(shape) or any(s is not None and s != d for s, d in zip(shape, t.shape)):
        want = ", ".join("*" if s is None else str(s) for s in shape)
        raise InputError(f"{name} must have shape [{want}], found {list(t.shape)}")


def check_inputs(means, quats, scales, opacities, colors, viewmats, Ks, width, height, background, sh_degree) -> Tensor:
    """Validate shapes at the public boundary; returns backgrounds ``[B, C]`` (default black)."""
    _check_shape("means", means, (None, 3))
    n = means.shape[0]
    _check_shape("quats", quats, (n, 4))
    _check_shape("scales", scales, (n, 3))
    _check_shape("opacities", opacities, (n,))
    _check_shape("viewmats", viewmats, (None, 4, 4))
    _check_shape("Ks", Ks, (viewmats.shape[0], 3, 3))
    if sh_degree is None and (colors.dim() != 2 or colors.shape[0] != n):
        raise InputError(f"colors must be [N, C] (N={n}) without sh_degree, found {list(colors.shape)}")
    if sh_degree is not None:
        if not 0 <= sh_degree <= 3:
            raise InputError(f"sh_degree must be in 0..3, found {sh_degree}")
        k = (sh_degree + 1) ** 2
        if colors.dim() != 3 or colors.shape[0] != n or colors.shape[1] < k or colors.shape[2] != 3:
            raise InputError(f"colors must be [N, K>={k}, 3] SH coefficients (N={n}), found {list(colors.shape)}")
    if width < 1 or height < 1:
        raise InputError(f"width and height must be positive, found {width}x{height}")
    num_cams, channels = viewmats.shape[0], colors.shape[-1]
    if background is None:
        return torch.zeros(num_cams, channels, dtype=means.dtype, device=means.device)
    background = torch.as_tensor(background, dtype=means.dtype, device=means.device)
    if background.shape == (channels,):
        return background.expand(num_cams, channels)
    if background.shape == (num_cams, channels):
        return background
    raise InputError(f"background must be [{channels}] or [{num_cams}, {channels}], found {list(background.shape)}")
