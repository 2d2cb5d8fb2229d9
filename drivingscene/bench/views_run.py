"""Scoring one pair for ``drivingscene bench views``: every method rendered at every viewpoint and
scored against the procedural generator's ground truth (or, for real pairs, the input upsampled).

A method is a function from `Viewpoints` to ``(colours [B, H, W, 3] in [0, 1], alphas [B, H, W])``:
the Gaussians of a reconstruction (`gaussian_method`), the depth-mesh baseline (`mesh_method`), or
the input upsampled bicubically (magnified rig views at t = 0 only).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
import torch
from torch import Tensor

from drivingscene.bench.views_cameras import Viewpoints, ego_pose_at, magnified_rig, overview_camera, viewpoint_class
from drivingscene.bench.views_scoring import HOLE_ALPHA, area_down, bicubic_up, flying_gaussians, holes, nearest_up, score_images
from drivingscene.eval.metrics import psnr

MODEL = "DrivingScene"
PER_PIXEL = "DrivingScene, one Gaussian per pixel"  # the parsimony ablation (InferenceOptions.merge, .dedupe off)
ORACLE = "oracle (GT depth + scene flow)"
CLASSICAL = "classical (DIS flow + triangulation)"
MESH = "depth mesh (DrivingScene's depth, DIBR)"
BICUBIC = "input upsampled bicubically"
PIXEL_BUDGET = 700_000  # pixels rendered in one call (4x 176x320: one camera; the overview: one)

Method = Callable[[Viewpoints], tuple[Tensor, Tensor]]


@dataclass(frozen=True)
class Plan:
    """What one run scores."""

    classes: tuple[str, ...]  # viewpoint classes (views_cameras.CLASSES)
    times: tuple[float, ...]  # normalised times
    magnifications: tuple[int, ...]  # > 1: the magnified rig rows (1 is the rig class)
    overview_size: tuple[int, int]  # (H, W)
    lpips_max_magnification: int  # ST-LPIPS only up to this magnification (CPU time)


@dataclass(frozen=True)
class ViewRecord:
    """The scores of one rendered image."""

    set: str  # "procedural" or "real"
    pair: str  # seed or scene name
    method: str
    viewpoint: str  # class
    magnification: int
    t: float
    camera: int  # rig camera the view derives from, -1 for the overview
    psnr: float
    ssim: float
    lpips: float | None  # ST-LPIPS (alex)
    holes: float | None  # share of world pixels with alpha < 0.95
    psnr_down: float | None = None  # real pairs: the render area-downsampled to the input size, against the input
    ssim_down: float | None = None
    psnr_seen: float | None = None  # procedural: PSNR over the pixels the oracle covers (surfaces some input image saw)


@dataclass
class PairResult:
    records: list[ViewRecord] = field(default_factory=list)
    flying: dict[str, tuple[int, int]] = field(default_factory=dict)  # method -> (flying, counted)
    examples: dict[tuple[str, int], dict[str, np.ndarray]] = field(default_factory=dict)  # (class, k) -> name -> [H, W, 3]


def _num(x) -> float | None:
    return None if x is None else float(x)


def gaussian_method(recon) -> Method:
    """Renders of ``recon``'s Gaussians (default "cameras" blend and rasterizer settings)."""
    from drivingscene.render import scene as render_scene

    gaussians = recon.visible()
    axes, centres = render_scene.source_axes(recon), render_scene.source_centres(recon)

    def render(vp: Viewpoints) -> tuple[Tensor, Tensor]:
        height, width = vp.size
        w2c = torch.from_numpy(vp.world_to_cam)
        ks = torch.from_numpy(vp.intrinsics).float()
        per = max(1, PIXEL_BUDGET // (height * width))
        colors, alphas = [], []
        with torch.no_grad():
            for s in range(0, len(vp), per):
                out = render_scene.render_gaussians(
                    gaussians,
                    vp.t,
                    w2c[s : s + per],
                    ks[s : s + per],
                    height,
                    width,
                    sky_sh=recon.sky_sh,
                    ground=recon.ground,
                    blend="cameras",
                    source_axes=axes,
                    source_centres=centres,
                )
                colors.append(out.colors.clamp(0, 1))
                alphas.append(out.alphas)
        return torch.cat(colors), torch.cat(alphas)

    return render


def mesh_method(mesh) -> Method:
    """Renders of a `DepthMeshRenderer`; its coverage stands for alpha."""

    def render(vp: Viewpoints) -> tuple[Tensor, Tensor]:
        out = mesh.render(vp.t, vp.world_to_cam, vp.intrinsics, *vp.size)
        return out.colors, out.coverage

    return render


def _keep_example(result: PairResult, key: tuple[str, int], name: str, image: Tensor) -> None:
    result.examples.setdefault(key, {})[name] = image.numpy().astype(np.float32)


def score_procedural(pair, name: str, truth, methods: dict[str, Method], plan: Plan, perceptual, examples: bool) -> PairResult:
    """Every method at every viewpoint of ``plan`` against the ground truth of the `ProceduralScene`
    ``truth``; magnified rig views also with the input upsampled bicubically at t = 0. Scored
    pixels: ``valid_mask`` at rig poses (nearest-neighbour upsampled), every pixel elsewhere (the
    ground truth has no ego body); holes over the pixels with true depth; "PSNR seen" over the pixels
    with true depth that the oracle covers (alpha >= 0.95): surfaces some input image saw, the same
    pixels for every method."""
    result = PairResult()
    args = (pair.ego_to_world, pair.cam_to_ego, pair.intrinsics, pair.image_size)
    for t in plan.times:
        sets = [viewpoint_class(c, t, *args, overview_size=plan.overview_size) for c in plan.classes]
        sets += [magnified_rig(t, k, *args) for k in plan.magnifications]
        for vp in sets:
            gt = truth.render(vp.cams_to_world, vp.intrinsics, vp.size, t, with_depth=True)
            target = torch.from_numpy(gt.images)
            mask = None
            if vp.name == "rig" and pair.valid_mask is not None:
                mask = torch.from_numpy(nearest_up(pair.valid_mask[vp.sources], vp.magnification))
            world = torch.from_numpy(gt.depth > 0) if mask is None else torch.from_numpy(gt.depth > 0) & mask
            rows = dict(methods)
            if vp.magnification > 1 and t == 0.0:
                bicubic = bicubic_up(pair.images[0], vp.magnification)[vp.sources]
                rows[BICUBIC] = lambda _vp, b=bicubic: (b, torch.ones(b.shape[:3]))
            lp = perceptual if vp.magnification <= plan.lpips_max_magnification else None
            key = (vp.name, vp.magnification)
            if examples and t == 0.0:
                _keep_example(result, key, "ground truth", target[0])
            seen = None  # the pixels the oracle covers: the oracle first
            for method in sorted(rows, key=lambda m: m != ORACLE):
                colors, alphas = rows[method](vp)
                if method == ORACLE:
                    seen = (alphas >= HOLE_ALPHA) & world
                s = score_images(colors, target, mask, lp)
                hole = holes(alphas, world)
                in_seen = (
                    None if seen is None else psnr(colors.permute(0, 3, 1, 2), target.permute(0, 3, 1, 2), seen).double().numpy()
                )
                for i in range(len(vp)):
                    result.records.append(
                        ViewRecord(
                            "procedural",
                            name,
                            method,
                            vp.name,
                            vp.magnification,
                            t,
                            int(vp.sources[i]),
                            float(s.psnr[i]),
                            float(s.ssim[i]),
                            None if s.lpips is None else float(s.lpips[i]),
                            _num(hole[i]),
                            psnr_seen=None if in_seen is None else float(in_seen[i]),
                        )
                    )
                if examples and t == 0.0:
                    _keep_example(result, key, method, colors[0])
    return result


def score_real(
    pair, name: str, model_recon, methods: dict[str, Method], plan: Plan, perceptual
) -> tuple[PairResult, dict[str, np.ndarray]]:
    """Real pairs have no ground truth away from the rig: each method's magnified render at t = 0
    (each camera at its image's capture pose) against the input upsampled bicubically (PSNR, SSIM,
    ST-LPIPS up to ``lpips_max_magnification``) and, area-downsampled back, against the input; holes
    over the world pixels (``valid_mask`` and not the model's sky). Also every method's overview at
    t = 0, returned as images ``[H, W, 3]``."""
    result = PairResult()
    mask_in = pair.world_mask()
    world_in = mask_in & (model_recon.depth[0] > 0)
    inputs = torch.from_numpy(pair.images[0]).float() / 255.0
    # each camera where its image was taken (real rigs trigger cameras at slightly different poses)
    captured = np.asarray(pair.camera_ego_poses()[0], np.float64) @ np.asarray(pair.cam_to_ego, np.float64)
    for k in (1, *plan.magnifications):
        vp = replace(
            magnified_rig(0.0, k, pair.ego_to_world, pair.cam_to_ego, pair.intrinsics, pair.image_size), cams_to_world=captured
        )
        reference = bicubic_up(pair.images[0], k)
        mask = torch.from_numpy(nearest_up(mask_in, k))
        world = torch.from_numpy(nearest_up(world_in, k))
        lp = perceptual if k <= plan.lpips_max_magnification else None
        for method, render in methods.items():
            colors, alphas = render(vp)
            s = score_images(colors, reference, mask, lp)
            down = score_images(area_down(colors, k), inputs, torch.from_numpy(mask_in), None) if k > 1 else s
            hole = holes(alphas, world)
            for i in range(len(vp)):
                result.records.append(
                    ViewRecord(
                        "real",
                        name,
                        method,
                        "rig",
                        k,
                        0.0,
                        i,
                        float(s.psnr[i]),
                        float(s.ssim[i]),
                        None if s.lpips is None else float(s.lpips[i]),
                        _num(hole[i]),
                        float(down.psnr[i]),
                        float(down.ssim[i]),
                    )
                )
    cam, k_over = overview_camera(ego_pose_at(pair.ego_to_world, 0.0), plan.overview_size[1], plan.overview_size[0])
    overview = Viewpoints("overview", 0.0, 1, cam[None], k_over[None], plan.overview_size, np.array([-1]))
    pictures = {method: render(overview)[0][0].numpy() for method, render in methods.items()}
    return result, pictures


def flying_of(recons: dict, gt_depth: np.ndarray | None) -> dict[str, tuple[int, int]]:
    """(flying, counted) Gaussians per method against ``gt_depth`` ``[2, V, H, W]`` (none without it)."""
    if gt_depth is None:
        return {}
    out = {}
    for method, recon in recons.items():
        f = flying_gaussians(recon, gt_depth)
        out[method] = (f.flying, f.counted)
    return out
