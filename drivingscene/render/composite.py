"""Pair finding (no grad) and differentiable front-to-back compositing (Kerbl et al. 2023, eq. 3).

Per pixel ``p`` and splat ``i`` (in front-to-back order), with ``d = p - mean2d`` in pixels:

    sigma_i = 0.5 * (a dx² + c dy²) + b dx dy          (half the squared Mahalanobis distance)
    alpha_i = min(0.99, opacity_i * exp(-sigma_i))
    T_0 = 1,  T_{i+1} = T_i (1 - alpha_i),  w_i = alpha_i T_i

A splat contributes only if ``sigma_i <= sigma_max_i = min(4.5, ln(255 opacity_i))``, i.e. inside
its 3-sigma ellipse (``4.5 = 3²/2``) and with ``alpha >= 1/255``. A splat that would bring the
transmittance below 1e-4 is dropped and the pixel stops (as 3DGS), and at most ``max_layers``
splats contribute per pixel. Pair finding applies these rules without grad and returns splat ids
``[P, max_layers]``; ``composite`` recomputes alphas and weights with autograd over that buffer.
The torch and C++ pair finders do the same float32 operations in the same order, so they return the
same pairs.

Surface averaging (``surface_tolerance`` tau > 0; the depth tolerance of EWA surface splatting,
Zwicker et al. 2001, docs/magnification.md): the pixel's front group F, its first splat and the
splats after it whose depth is within ``z_0 (1 + tau)``, is averaged instead of composited,
``w_i = A alpha_i / sum_F alpha`` with ``A = 1 - prod_F (1 - alpha)``, and what lies behind it is
composited as above under the transmittance ``1 - A``. Compositing one surface front to back lets
the nearer of two neighbouring splats win between their centres, which a magnified view shows; the
average interpolates them. Accumulated alpha is unchanged. tau = 0 is plain compositing.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from drivingscene import kernels
from drivingscene.errors import InputError
from drivingscene.render.splats import Splats

MAX_ALPHA = 0.99
MIN_TRANSMITTANCE = 1e-4
SIGMA_CUT = 4.5  # 3-sigma ellipse: 0.5 * 3**2
MIN_WEIGHT_SUM = 1e-6  # below this accumulated alpha, expected depth is reported as 0
# The layered blends' and the colour solve's surface tolerance (relative depth; docs/magnification.md):
# an image's own layer is one surface, averaged within it. 0 would be plain compositing.
SURFACE_TOLERANCE = 0.2
_CHUNK = 1 << 22  # candidate (splat, pixel) pairs evaluated at once by the torch pair finder
_PIXEL_CHUNK = 8192  # pixels composited at once (keeps [pixels, layers] temporaries near cache size)


@dataclass(frozen=True)
class PairInputs:
    """Detached, contiguous per-splat data both pair finders read (float32 unless inputs are float64)."""

    means2d: Tensor  # [M, 2]
    conics: Tensor  # [M, 3]
    opacities: Tensor  # [M]
    sigma_max: Tensor  # [M]
    boxes: Tensor  # [M, 4] int32 pixel box x0, x1, y0, y1 (inclusive, clipped; empty if x0 > x1)
    camera_offsets: Tensor  # [B + 1] int64


def pair_inputs(splats: Splats, width: int, height: int) -> PairInputs:
    """Cut thresholds and pixel boxes of the ellipses ``sigma <= sigma_max`` (with a small margin)."""
    with torch.no_grad():
        means2d, conics, opacities = splats.means2d.detach(), splats.conics.detach(), splats.opacities.detach()
        sigma_max = torch.clamp(torch.log(255.0 * opacities), max=SIGMA_CUT)
        if kernels.available(kernels.splat_boxes, "auto", means2d, conics, sigma_max, splats.radii):
            boxes = kernels.splat_boxes(
                means2d.contiguous(),
                conics.contiguous(),
                sigma_max.contiguous(),
                splats.radii.detach().contiguous(),
                width,
                height,
            )
        else:
            boxes = splat_boxes_torch(means2d, conics, sigma_max, splats.radii, width, height)
        return PairInputs(
            means2d=means2d.contiguous(),
            conics=conics.contiguous(),
            opacities=opacities.contiguous(),
            sigma_max=sigma_max.contiguous(),
            boxes=boxes,
            camera_offsets=splats.camera_offsets.to(torch.int64).contiguous(),
        )


def splat_boxes_torch(means2d: Tensor, conics: Tensor, sigma_max: Tensor, radii: Tensor, width: int, height: int) -> Tensor:
    """Pixel boxes ``[M, 4]`` int32 x0, x1, y0, y1 (inclusive, clipped; empty if x0 > x1) of the
    ellipses ``sigma <= sigma_max``, in float64 (the reference of `kernels.splat_boxes`)."""
    q = conics.double()
    det = q[:, 0] * q[:, 2] - q[:, 1] * q[:, 1]
    ok = (det > 0) & (sigma_max > 0) & (radii > 0)
    det = torch.where(ok, det, torch.ones_like(det))
    two_s = 2.0 * sigma_max.double().clamp(min=0.0)
    # Extent of {dᵀ Q d <= 2 sigma_max} along x is sqrt(2 sigma_max (Q⁻¹)_xx) = sqrt(2 sigma_max c / det).
    half = torch.stack([torch.sqrt(two_s * q[:, 2] / det), torch.sqrt(two_s * q[:, 0] / det)], dim=-1)
    half = half * (1 + 1e-3) + 1e-3
    centre = means2d.double()
    ok &= torch.isfinite(centre).all(-1) & torch.isfinite(half).all(-1)  # never cast NaN/inf to int
    size = torch.tensor([width - 1, height - 1], dtype=torch.float64, device=centre.device)
    lo = torch.where(ok[:, None], torch.ceil(centre - half), 0.0).clamp(min=0.0)
    hi = torch.where(ok[:, None], torch.floor(centre + half), -1.0)
    hi = torch.minimum(hi, size)
    lo, hi = torch.minimum(lo, size + 1.0), hi.clamp(min=-1.0)  # far off the image: empty, within int32
    return torch.stack([lo[:, 0], hi[:, 0], lo[:, 1], hi[:, 1]], dim=-1).to(torch.int32).contiguous()


def _half_sq_mahalanobis(dx: Tensor, dy: Tensor, conics: Tensor) -> Tensor:
    """``0.5 (a dx² + c dy²) + b dx dy``; this exact operation order is mirrored in find_pairs.cpp."""
    a, b, c = conics.unbind(-1)
    return 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy


def _alpha_for_decision(opacities: Tensor, sigma: Tensor) -> Tensor:
    """Alpha with the exponential taken in float64 then rounded, as in find_pairs.cpp."""
    return torch.clamp(opacities * torch.exp(-sigma.double()).to(sigma.dtype), max=MAX_ALPHA)


def _candidates(inp: PairInputs, width: int, height: int) -> tuple[Tensor, Tensor, Tensor]:
    """Pairs inside the boxes that pass the cut: splat ids ``[Q]``, global pixel ids ``[Q]``, sigma ``[Q]``."""
    boxes = inp.boxes.long()
    bw = (boxes[:, 1] - boxes[:, 0] + 1).clamp(min=0)
    area = bw * (boxes[:, 3] - boxes[:, 2] + 1).clamp(min=0)  # [M]
    dev = boxes.device
    cam = torch.repeat_interleave(torch.arange(len(inp.camera_offsets) - 1, device=dev), inp.camera_offsets.diff())  # [M]
    ends = area.cumsum(0)
    out_j, out_p, out_s = [], [], []
    start = 0
    while start < len(area):
        # Splats [start, stop) hold at most _CHUNK candidates (or a single large splat).
        base = ends[start - 1] if start > 0 else ends.new_zeros(())
        stop = max(start + 1, int(torch.searchsorted(ends, base + _CHUNK, right=True)))
        ids = torch.arange(start, stop, device=dev)
        j = torch.repeat_interleave(ids, area[start:stop])
        local = torch.arange(len(j), device=dev) - torch.repeat_interleave(
            ends[start:stop] - area[start:stop] - base, area[start:stop]
        )
        x = boxes[j, 0] + local % bw[j]
        y = boxes[j, 2] + local // bw[j]
        dx = x.to(inp.means2d.dtype) - inp.means2d[j, 0]
        dy = y.to(inp.means2d.dtype) - inp.means2d[j, 1]
        sigma = _half_sq_mahalanobis(dx, dy, inp.conics[j])
        keep = sigma <= inp.sigma_max[j]
        out_j.append(j[keep])
        out_p.append((cam[j] * height + y)[keep] * width + x[keep])
        out_s.append(sigma[keep])
        start = stop
    if not out_j:
        empty = torch.zeros(0, dtype=torch.int64, device=dev)
        return empty, empty, inp.means2d.new_zeros(0)
    return torch.cat(out_j), torch.cat(out_p), torch.cat(out_s)


def find_pairs_torch(inp: PairInputs, width: int, height: int, max_layers: int) -> Tensor:
    """Pure-torch pair finding: splat ids ``[B*H*W, max_layers]`` int32, -1 where empty."""
    num_pixels = (len(inp.camera_offsets) - 1) * height * width
    out = torch.full((num_pixels, max_layers), -1, dtype=torch.int32, device=inp.means2d.device)
    with torch.no_grad():
        j, pix, sigma = _candidates(inp, width, height)
        if len(j) == 0:
            return out
        # Sort by (pixel, splat); splat order is front-to-back within a camera.
        order = torch.sort(pix * len(inp.means2d) + j).indices
        j, pix, sigma = j[order], pix[order], sigma[order]
        keep = _front_to_back(_alpha_for_decision(inp.opacities[j], sigma), pix, max_layers)
        j, pix = j[keep], pix[keep]
        out[pix, _rank_in_runs(pix)[0]] = j.to(torch.int32)
    return out


def _rank_in_runs(keys: Tensor) -> tuple[Tensor, Tensor]:
    """For sorted ``keys`` ``[Q]``: position of each element within its run of equal keys, and run index."""
    pos = torch.arange(len(keys), device=keys.device)
    first = torch.ones_like(keys, dtype=torch.bool)
    first[1:] = keys[1:] != keys[:-1]
    return pos - torch.where(first, pos, 0).cummax(0).values, first.cumsum(0) - 1


def _front_to_back(alpha: Tensor, pix: Tensor, max_layers: int) -> Tensor:
    """Which candidates ``[Q]`` (sorted by pixel, then depth) are composited: transmittance, early stop, cap.

    Runs one step per depth rank ("layer") over all pixels at once. Pixels are ordered by candidate
    count, descending, so layer r is a prefix of that order and per-pixel state is sliced, not gathered.
    Transmittance is a float32 running product, as in find_pairs.cpp.
    """
    rank, seg = _rank_in_runs(pix)  # depth rank within the pixel, pixel segment
    counts = torch.bincount(seg)
    by_count = torch.sort(counts, descending=True, stable=True).indices
    place = torch.empty_like(by_count)
    place[by_count] = torch.arange(len(by_count), device=by_count.device)  # segment -> position in by_count order
    layer_sizes = torch.bincount(rank)  # pixels with more than r candidates
    layer_start = torch.cat([layer_sizes.new_zeros(1), layer_sizes.cumsum(0)])
    slot = layer_start[rank] + place[seg]  # layer-major storage
    alpha_by_layer = torch.empty_like(alpha)
    alpha_by_layer[slot] = alpha
    taken = torch.zeros_like(alpha, dtype=torch.bool)
    trans = torch.ones_like(counts, dtype=alpha.dtype)
    layers = torch.zeros_like(counts)
    live = torch.ones_like(counts, dtype=torch.bool)
    for lo, n in zip(layer_start.tolist(), layer_sizes.tolist()):
        nxt = trans[:n] * (1.0 - alpha_by_layer[lo : lo + n])
        stop = nxt < MIN_TRANSMITTANCE
        take = live[:n] & ~stop
        taken[lo : lo + n] = take
        trans[:n] = torch.where(take, nxt, trans[:n])
        layers[:n] += take
        live[:n] &= ~stop & (layers[:n] < max_layers)
    return taken[slot]


def find_pairs_cpp(inp: PairInputs, width: int, height: int, max_layers: int) -> Tensor:
    """Compiled pair finding (`drivingscene.kernels.find_pairs`: same rule and result as
    ``find_pairs_torch``); float32 decisions."""
    return kernels.find_pairs(
        inp.means2d.float().contiguous(),
        inp.conics.float().contiguous(),
        inp.opacities.float().contiguous(),
        inp.sigma_max.float().contiguous(),
        inp.boxes,
        inp.camera_offsets,
        width,
        height,
        max_layers,
    )


def composite(
    pair_ids: Tensor,  # [B*H*W, L] splat ids, -1 where empty
    means2d: Tensor,  # [M, 2]
    conics: Tensor,  # [M, 3]
    opacities: Tensor,  # [M]
    depths: Tensor,  # [M]
    colors: Tensor,  # [M, C]
    backgrounds: Tensor,  # [B, C]
    width: int,
    height: int,
    compiled: bool = False,
    surface_tolerance: float = 0.0,
) -> tuple[Tensor, Tensor, Tensor]:
    """Differentiable compositing over the pair buffer (``surface_tolerance``: module docstring).

    Returns colours ``[B, H, W, C]`` over the backgrounds, expected z-depth ``[B, H, W]`` (metres,
    ``sum w z / sum w``, 0 where ``sum w < 1e-6``) and accumulated alpha ``[B, H, W]`` (``sum w``).
    ``compiled``: forward and backward by the compiled kernels (`drivingscene.kernels.composite_forward`,
    ``composite_backward``) where the inputs are float32 CPU tensors, else by torch (the reference;
    equal up to float rounding, and 5-10x slower on a CPU).
    """
    num_cams, channels = backgrounds.shape
    packed = torch.cat([means2d, conics, opacities[:, None], depths[:, None], colors], dim=1)  # [M, 7 + C]
    if packed.shape[0] == 0:
        packed = packed.new_zeros(1, packed.shape[1])
    compiled = compiled and all(t.device.type == "cpu" and t.dtype == torch.float32 for t in (packed, backgrounds))
    if not surface_tolerance >= 0.0:
        raise InputError(f"surface_tolerance must be >= 0 (a relative depth), found {surface_tolerance}")
    rgb, depth, alpha = _Composite.apply(packed, backgrounds, pair_ids, width, height, compiled, float(surface_tolerance))
    return (
        rgb.reshape(num_cams, height, width, channels),
        depth.reshape(num_cams, height, width),
        alpha.reshape(num_cams, height, width),
    )


def _pixel_chunks(pair_ids: Tensor):
    """``(start, ids)`` for blocks of pixels (cache-sized), trailing layers unused in the block dropped."""
    for start in range(0, pair_ids.shape[0], _PIXEL_CHUNK):
        ids = pair_ids[start : start + _PIXEL_CHUNK]
        used = int((ids >= 0).sum(1).max()) if ids.numel() else 0
        yield start, ids[:, : max(used, 1)].long()


class _Composite(torch.autograd.Function):
    """Front-to-back compositing over ``[P, L]`` gathered splats with a hand-written backward, by
    the compiled kernels (``compiled``) or by torch (`composite_torch`, `composite_backward_torch`:
    the reference). Backward (Kerbl et al. 2023, supplementary; ``v_k = dL/dw_k``, ``T_k``
    transmittance before k): ``dL/dalpha_k = v_k T_k - (sum_{j>k} v_j w_j + (dL/drgb . bg) T_L) / (1 - alpha_k)``.
    """

    @staticmethod
    def forward(
        ctx, packed: Tensor, backgrounds: Tensor, pair_ids: Tensor, width: int, height: int, compiled: bool, tolerance: float
    ):
        forward = kernels.composite_forward if compiled else composite_torch
        rgb, depth, weight_sum = forward(packed, backgrounds, pair_ids, width, height, tolerance)
        ctx.save_for_backward(packed, backgrounds, pair_ids, depth, weight_sum)
        ctx.size, ctx.compiled, ctx.tolerance = (width, height), compiled, tolerance
        return rgb, depth, weight_sum

    @staticmethod
    def backward(ctx, grad_rgb: Tensor, grad_depth: Tensor, grad_alpha: Tensor):
        backward = kernels.composite_backward if ctx.compiled else composite_backward_torch
        packed, backgrounds, pair_ids, depth, weight_sum = ctx.saved_tensors
        grad_packed, grad_bg = backward(
            packed, backgrounds, pair_ids, *ctx.size, depth, weight_sum, grad_rgb, grad_depth, grad_alpha, ctx.tolerance
        )
        return grad_packed, grad_bg, None, None, None, None, None


def composite_torch(
    packed: Tensor, backgrounds: Tensor, pair_ids: Tensor, width: int, height: int, tolerance: float = 0.0
) -> tuple[Tensor, Tensor, Tensor]:
    """The torch compositing (`kernels.composite_forward`'s reference): colours ``[P, C]``, depth and
    accumulated alpha ``[P]``, over blocks of pixels so that the ``[pixels, layers]`` temporaries
    stay in cache."""
    num_pixels, channels = pair_ids.shape[0], backgrounds.shape[1]
    rgb = packed.new_empty(num_pixels, channels)
    depth = packed.new_empty(num_pixels)
    weight_sum = packed.new_empty(num_pixels)
    for start, ids in _pixel_chunks(pair_ids):
        g = _gather(packed, backgrounds, ids, start, width, height)
        f = _front_group(g, ids, tolerance)
        end = start + len(ids)
        ws = f.weights.sum(1)
        weight_sum[start:end] = ws
        rgb[start:end] = torch.stack([(f.weights * c).sum(1) for c in g.colors], dim=-1) + f.trans_final[:, None] * g.bg
        has = ws >= MIN_WEIGHT_SUM
        depth[start:end] = torch.where(has, (f.weights * g.z).sum(1) / torch.where(has, ws, torch.ones_like(ws)), 0.0)
    return rgb, depth, weight_sum


def composite_backward_torch(
    packed: Tensor,
    backgrounds: Tensor,
    pair_ids: Tensor,
    width: int,
    height: int,
    depth: Tensor,
    weight_sum: Tensor,
    grad_rgb: Tensor,
    grad_depth: Tensor,
    grad_alpha: Tensor,
    tolerance: float = 0.0,
) -> tuple[Tensor, Tensor]:
    """The torch backward (`kernels.composite_backward`'s reference): gradients of ``packed`` and
    ``backgrounds``, block by block as `composite_torch`."""
    grad_packed = torch.zeros_like(packed)
    has = weight_sum >= MIN_WEIGHT_SUM
    grad_d = torch.where(has, grad_depth / torch.where(has, weight_sum, torch.ones_like(weight_sum)), 0.0)
    trans_final = torch.empty_like(weight_sum)
    for start, ids in _pixel_chunks(pair_ids):
        end = start + len(ids)
        g = _gather(packed, backgrounds, ids, start, width, height)
        f = _front_group(g, ids, tolerance)
        trans_final[start:end] = f.trans_final
        grads = _chunk_grads(g, f, grad_rgb[start:end], grad_d[start:end], grad_alpha[start:end], depth[start:end])
        grad_packed.index_add_(0, ids.clamp(min=0).reshape(-1), grads.flatten(0, 1))
    num_cams, channels = backgrounds.shape
    grad_bg = (grad_rgb * trans_final[:, None]).reshape(num_cams, -1, channels).sum(1)
    return grad_packed, grad_bg


@dataclass(frozen=True)
class _Front:
    """Per pixel block: the front group's mask ``[p, L]``, its transmittance ``P`` and alpha sum
    ``[p]``, the weights ``[p, L]`` and the transmittance before each slot (1 in the group) and
    after the last ``[p]``."""

    mask: Tensor
    trans: Tensor
    alpha_sum: Tensor
    weights: Tensor
    trans_before: Tensor
    trans_final: Tensor
    single: Tensor  # [p] bool: the group is one splat (plain compositing, computed as such)


def _front_group(g, ids: Tensor, tolerance: float) -> _Front:
    """The front group of each pixel (module docstring) and the weights of every slot."""
    valid = ids >= 0
    first = valid & (valid.cumsum(1) == 1)  # the first listed splat (slots may be empty)
    if tolerance > 0.0:
        z_limit = torch.where(first, g.z, 0.0).sum(1, keepdim=True) * (1.0 + tolerance)
        near = (valid & (g.z <= z_limit)) | ~valid  # empty slots do not close the group
        mask = valid & (near.cumprod(1) > 0)
    else:
        mask = first
    alpha_f = torch.where(mask, g.alpha, 0.0)
    alpha_r = torch.where(mask, 0.0, g.alpha)
    trans_f = torch.prod(1.0 - alpha_f, dim=1)  # [p]
    sum_f = alpha_f.sum(1)
    single = mask.sum(1) == 1
    scale = torch.where(single, torch.ones_like(sum_f), (1.0 - trans_f) / torch.where(sum_f > 0, sum_f, torch.ones_like(sum_f)))
    trans_r = torch.cumprod(1.0 - alpha_r, dim=1) * trans_f[:, None]  # [p, L] after each slot, behind the group
    before_r = torch.cat([trans_f[:, None], trans_r[:, :-1]], dim=1)
    trans_before = torch.where(mask, 1.0, before_r)
    weights = torch.where(mask, alpha_f * scale[:, None], alpha_r * before_r)
    return _Front(mask, trans_f, sum_f, weights, trans_before, trans_r[:, -1], single)


def _chunk_grads(g, f: _Front, grad_rgb: Tensor, grad_d: Tensor, grad_alpha: Tensor, depth: Tensor) -> Tensor:
    """Gradients ``[p, L, 7 + C]`` w.r.t. the gathered splat rows of one pixel block (``grad_d = dL/dD / S``)."""
    weights = f.weights  # [p, L]
    # dL/dw_k: colour, expected depth (z_k - D) / S and alpha (sum of w) terms.
    v = grad_alpha[:, None] + grad_d[:, None] * (g.z - depth[:, None])
    for ch, c in enumerate(g.colors):
        v = v + grad_rgb[:, ch : ch + 1] * c
    vw = torch.where(f.mask, 0.0, v * weights)  # behind the group
    behind = torch.cumsum(vw.flip(1), dim=1).flip(1) - vw  # sum over j > k behind the group of v_j w_j
    bg_term = (grad_rgb * g.bg).sum(-1) * f.trans_final
    behind = behind + bg_term[:, None]
    behind_group = vw.sum(1) + bg_term  # [p] B: everything behind the front group
    plain = v * f.trans_before - behind / (1.0 - g.alpha)
    safe_sum = torch.where(f.alpha_sum > 0, f.alpha_sum, torch.ones_like(f.alpha_sum))
    mean_v = (torch.where(f.mask, v * g.alpha, 0.0).sum(1) / safe_sum)[:, None]
    cover = (1.0 - f.trans) / safe_sum
    averaged = cover[:, None] * (v - mean_v) + (mean_v * f.trans[:, None] - behind_group[:, None]) / (1.0 - g.alpha)
    in_single = v - behind_group[:, None] / (1.0 - g.alpha)
    grad_alpha_k = torch.where(f.mask, torch.where(f.single[:, None], in_single, averaged), plain)
    grad_raw = torch.where(g.passes, grad_alpha_k, 0.0)  # clamp at 0.99 and empty slots stop gradients
    grad_sigma = -grad_raw * g.raw
    grads = (
        [
            -grad_sigma * (g.ca * g.dx + g.cb * g.dy),  # mean x
            -grad_sigma * (g.cb * g.dx + g.cc * g.dy),  # mean y
            0.5 * grad_sigma * g.dx * g.dx,  # conic a
            grad_sigma * g.dx * g.dy,  # conic b
            0.5 * grad_sigma * g.dy * g.dy,  # conic c
            grad_raw * g.raw_over_opacity,  # opacity
            weights * grad_d[:, None],  # depth
        ]
        + [weights * grad_rgb[:, ch : ch + 1] for ch in range(len(g.colors))]
    )
    return torch.stack(grads, -1)


@dataclass(frozen=True)
class _Gathered:
    """Per (pixel, layer) quantities ``[p, L]`` of one pixel block, recomputed by forward and backward."""

    dx: Tensor
    dy: Tensor
    ca: Tensor
    cb: Tensor
    cc: Tensor
    z: Tensor
    colors: list  # C tensors [p, L]
    raw: Tensor  # opacity * exp(-sigma)
    raw_over_opacity: Tensor  # exp(-sigma)
    alpha: Tensor  # min(raw, 0.99), 0 in empty slots
    passes: Tensor  # bool: slot used and raw <= 0.99 (alpha has a gradient)
    bg: Tensor  # [p, C] background of each pixel


def _gather(packed: Tensor, backgrounds: Tensor, ids: Tensor, start: int, width: int, height: int) -> _Gathered:
    """Gather the splat rows of pixels ``start .. start + len(ids)`` (global index over cameras)."""
    valid = ids >= 0
    rows = packed.index_select(0, ids.clamp(min=0).reshape(-1)).view(*ids.shape, -1)  # [p, L, 7 + C]
    mx, my, ca, cb, cc, opac, z, *colors = rows.unbind(-1)
    pix = torch.arange(start, start + ids.shape[0], device=ids.device)
    u = (pix % width).to(packed.dtype)[:, None]  # [p, 1]
    v = ((pix // width) % height).to(packed.dtype)[:, None]
    dx, dy = u - mx, v - my
    e = torch.exp(-(0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy))
    raw = opac * e
    alpha = torch.where(valid, torch.clamp(raw, max=MAX_ALPHA), 0.0)
    bg = backgrounds[pix // (width * height)]  # [p, C]
    return _Gathered(dx, dy, ca, cb, cc, z, colors, raw, e, alpha, valid & (raw <= MAX_ALPHA), bg)
