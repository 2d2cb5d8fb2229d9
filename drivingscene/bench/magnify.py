"""``drivingscene bench magnify``: which footprints, colours and layer blend hold up when the view is
larger than the input (docs/magnification.md).

Every approach is one `Variant`: the footprint rule on the Gaussians (`gaussians.assembly`), the
colour solve (`render.color_solve`), the renderer's screen-space low-pass and the layered blend's
rule (`render.scene.LayerBlend`). Each is scored on the same pairs, at the rig poses: the input
views re-rendered (both keyframes), the in-between frame, and each rig camera at t = 0 at 1, 2 and 4
times the input size, against the generator's ground truth rendered at that size (procedural) or
against the input upsampled bicubically (real, and procedural too), with the share of holes (world
pixels whose coverage is below 0.95) and that of the image's own layer alone (its raw accumulated
alpha, before the blend's coverage rule). The first row is the renderer as it was (3DGS footprints
and low-pass); the row marked default is what the model, the viewer and every benchmark use. Rows
up to the default add one change each; the rows after it change one thing of the default. Every
row but the last draws the far layer (`InferenceOptions.far_layer`, added after these rows were
chosen); the last is the default without it.

Beside the variants, a reference that knows no geometry: each input image interpolated by
normalised Gaussians of the splats' smallest size (`gaussian_interpolation`), its samples
deconvolved as the colour solve does: what the splats' kernel and the solve give at the rig poses
without any geometry, against which the surface averaging of each layer (`render.composite`) is
measured.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import dataclass, field, replace
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch

from drivingscene.arguments import positive_int
from drivingscene.data.atomic import atomic_write_text
from drivingscene.errors import InputError
from drivingscene.gaussians.assembly import MAX_FOOTPRINT, NO_FOOTPRINT_RULE, FootprintRule
from drivingscene.gaussians.parsimony import BlockMerge
from drivingscene.methods.feedforward import FAR_LAYER
from drivingscene.render.color_solve import ITERATIONS
from drivingscene.render.composite import SURFACE_TOLERANCE
from drivingscene.render.project import EPS2D, EPS2D_3DGS
from drivingscene.render.scene import LayerBlend

MAGNIFICATIONS = (1, 2, 4)
BEFORE_BLEND = LayerBlend(coverage_full=1.0, angle_scale=0.5, angle_scale_at_keyframe=0.5, surface_tolerance=0.0)
COMPOSITED = LayerBlend(surface_tolerance=0.0)  # each layer composited front to back (before surface averaging)


@dataclass(frozen=True)
class Variant:
    name: str
    footprints: FootprintRule = FootprintRule()
    fit_colors: int = ITERATIONS
    eps2d: float = EPS2D
    blend: LayerBlend = LayerBlend()
    note: str = ""
    far_layer: float = FAR_LAYER  # InferenceOptions.far_layer
    # InferenceOptions.merge: these rows were measured with one Gaussian per pixel, before the flat
    # blocks were merged (issue 49, docs/parsimony.md); True: the merge's default (its own row), or
    # a `BlockMerge` of its own
    merge: bool | BlockMerge = False


BEFORE_CAP = FootprintRule(max_footprint=1.0)  # the cap before 2026-11-28 (two solve iterations)
VARIANTS = (
    Variant("3DGS footprints and low-pass (before)", NO_FOOTPRINT_RULE, 0, EPS2D_3DGS, BEFORE_BLEND),
    Variant("colour solve alone", NO_FOOTPRINT_RULE, 2, EPS2D_3DGS, BEFORE_BLEND),
    Variant("3D floor 0.2 px² (Mip-Splatting filter), low-pass 0.1", FootprintRule(0.0), 0, EPS2D, BEFORE_BLEND),
    Variant("floor + cap at 1 px", BEFORE_CAP, 0, EPS2D, BEFORE_BLEND),
    Variant("floor + cap + colour solve", BEFORE_CAP, 2, EPS2D, BEFORE_BLEND),
    Variant("+ coverage rule (0.7)", BEFORE_CAP, 2, EPS2D, replace(COMPOSITED, angle_scale_at_keyframe=0.5)),
    Variant("+ own camera at its keyframe", BEFORE_CAP, 2, blend=COMPOSITED),
    Variant(f"+ surface averaging, tolerance {SURFACE_TOLERANCE:g}", BEFORE_CAP, 2),
    Variant(f"+ cap at {MAX_FOOTPRINT:g} px, {ITERATIONS} solve iterations (default)", note="default"),
    *(
        Variant(f"tolerance {tol:g} instead", blend=LayerBlend(surface_tolerance=tol))
        for tol in (0.05, 0.1, 0.3)
        if tol != SURFACE_TOLERANCE
    ),
    Variant(f"cap at {MAX_FOOTPRINT:g} px, two solve iterations", fit_colors=2),
    Variant(f"cap at 1 px, {ITERATIONS} solve iterations", BEFORE_CAP),
    Variant("cap at 0.7 px instead", FootprintRule(0.7)),
    Variant("floor 0.15 px² instead of 0.2", FootprintRule(floor=0.15)),
    Variant("floor 0.3 px² instead of 0.2", FootprintRule(floor=0.3)),
    Variant("floor 0.45 px², no coverage rule", FootprintRule(floor=0.45), eps2d=0.05, blend=LayerBlend(coverage_full=1.0)),
    Variant("cap at 2.5 px instead", FootprintRule(2.5)),
    Variant("no cap", FootprintRule(0.0)),
    Variant("sharp view weights at all times (0.1)", blend=LayerBlend(angle_scale=0.1, angle_scale_at_keyframe=0.1)),
    Variant("one iteration of the colour solve", fit_colors=1),
    Variant("eight iterations of the colour solve", fit_colors=8),
    Variant("no far layer (beyond the sky distance: the sky model)", far_layer=0.0),
    Variant(
        "default + flat 2x2 blocks merged, colours solved over them (the reconstruction's default since 2026-12-02)",
        merge=True,
        note="default",
    ),
    Variant(
        "default + flat 2x2 blocks merged as on 2026-12-01 (colour range 0.06, each block its mean colour)",
        merge=BlockMerge(color_range=0.06, color_test="range", fit_colors=0),
    ),
)
DEFAULT = VARIANTS[8]  # the renderer's default, one Gaussian per pixel: the chain of fixes above ends here
MERGED = VARIANTS[-2]  # the reconstruction's default (issue 49)
QUICK = (VARIANTS[0], DEFAULT)


@dataclass
class Scores:
    """Per variant and pair set: lists of per-pair means, averaged in the report."""

    values: dict[str, list[float]] = field(default_factory=dict)

    def add(self, key: str, value: float) -> None:
        self.values.setdefault(key, []).append(float(value))

    def mean(self, key: str) -> float:
        v = [x for x in self.values.get(key, []) if not math.isnan(x)]
        return float(np.mean(v)) if v else math.nan


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quick", action="store_true", help="1 small pair, the first and the default variant (a smoke test)")
    p.add_argument(
        "--default-only",
        action="store_true",
        help="score the defaults alone: one Gaussian per pixel and merged (their figures, not the comparison)",
    )
    p.add_argument("--count", type=positive_int, default=4, help="procedural test pairs (default 4)")
    p.add_argument("--start", type=int, default=0, help="skip the split's first seeds")
    p.add_argument("--split", choices=("test", "val"), default="test", help="procedural split (val: to choose settings on)")
    p.add_argument("--scenes", type=Path, nargs="+", default=[], metavar="SCENE", help="real scenes (rows against the input)")
    p.add_argument("--weights", type=Path, default=None, help="model weights (default: the shipped ones)")
    p.add_argument(
        "--merge-range",
        type=float,
        default=None,
        metavar="COLOUR",
        help="the merged rows' BlockMerge.color_range (default: the reconstruction's, 0.045): how much detail a merged block may hold",
    )
    p.add_argument("-o", "--out", type=Path, default=Path("out/bench/magnify.md"), help="markdown report")
    p.add_argument("--json", type=Path, default=None, help="the numbers as JSON")


def _psnr(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> float:
    mse = ((pred.clamp(0, 1) - target) ** 2)[mask].mean()
    return float(10 * torch.log10(1.0 / mse.clamp(min=1e-12)))


def _magnified(intrinsics: np.ndarray, k: int) -> torch.Tensor:
    from drivingscene.geometry.camera import scale_intrinsics

    return scale_intrinsics(torch.from_numpy(intrinsics).float(), k, k)


def gaussian_interpolation(
    image: torch.Tensor, k: int, floor: float = FootprintRule().floor, eps2d: float = EPS2D, iterations: int = 2
) -> torch.Tensor:
    """``image`` ``[H, W, C]`` resampled at ``k`` times its size by normalised Gaussians centred on its
    pixels (variance ``floor`` source px² plus the screen low-pass ``eps2d`` output px², the
    smallest splats the footprint rule allows), after ``iterations`` Richardson steps that make the
    1x resampling reproduce the image: the splats' kernel and colour solve without geometry or
    compositing. Pixel centres at integers: output x samples source (x + 0.5) / k - 0.5."""
    height, width = image.shape[:2]

    def weights(n: int, scale: int) -> torch.Tensor:  # [n * scale, n], rows summing to 1
        var = floor + eps2d / scale**2
        at = (torch.arange(n * scale, dtype=torch.float64) + 0.5) / scale - 0.5
        w = torch.exp(-0.5 * (torch.arange(n, dtype=torch.float64)[None] - at[:, None]) ** 2 / var)
        w = torch.where(w > 1e-4, w, torch.zeros_like(w))
        return w / w.sum(1, keepdim=True)

    def resample(c: torch.Tensor, scale: int) -> torch.Tensor:
        rows = torch.einsum("yi,ijc->yjc", weights(height, scale), c)
        return torch.einsum("xj,yjc->yxc", weights(width, scale), rows)

    src = image.double()
    c = src.clone()
    for _ in range(iterations):
        c = c + src - resample(c, 1)
    return resample(c, k).to(image.dtype)


def score_pair(model, pair, variant: Variant, truth=None, references: dict | None = None) -> dict[str, float]:
    """Every figure of one variant on one pair (``truth``: a `ProceduralScene` for ground truth at size).
    ``references``: a dict kept across the variants of one pair, in which the images every variant
    is scored against (ground truth, the input upsampled bicubically, `gaussian_interpolation`) are
    made once."""
    references = {} if references is None else references
    import cv2

    from drivingscene.bench.views_scoring import area_down
    from drivingscene.methods.feedforward import InferenceOptions, reconstruct
    from drivingscene.render.scene import (
        render_eval_frames,
        render_gaussians,
        render_input_views,
        source_axes,
        source_centres,
    )

    opts = InferenceOptions(
        fit_colors=variant.fit_colors,
        footprints=variant.footprints,
        surface_tolerance=variant.blend.surface_tolerance,
        far_layer=variant.far_layer,
        merge=BlockMerge() if variant.merge is True else variant.merge or None,
    )
    times = []
    for _ in range(2):  # the second run is timed warm (kernels built, caches filled)
        start = time.perf_counter()
        recon = reconstruct(model, pair, opts)
        times.append(time.perf_counter() - start)
    out = {"seconds": times[-1], "share": len(recon.gaussians) / recon.meta.get("per_pixel_gaussians", len(recon.gaussians))}
    raster = {"eps2d": variant.eps2d, "layer_blend": variant.blend}
    height, width = pair.image_size
    world = (
        torch.from_numpy(pair.valid_mask)
        if pair.valid_mask is not None
        else torch.ones(pair.num_views, height, width, dtype=torch.bool)
    )
    inputs = torch.from_numpy(pair.images).float() / 255
    views = render_input_views(recon, pair, **raster)
    out["input_views"] = _psnr(views, inputs, world[None].expand(2, -1, -1, -1))
    if pair.num_eval:
        frames = render_eval_frames(recon, pair, **raster)
        out["in_between"] = _psnr(
            frames, torch.from_numpy(pair.eval_images).float() / 255, world[None].expand(pair.num_eval, -1, -1, -1)
        )
    g, axes = recon.visible(), source_axes(recon)
    w2c = recon.world_to_cam_at(0.0).float()
    surface = torch.from_numpy(recon.depth[0] > 0) & world  # pixels that see a surface (not sky)
    for k in MAGNIFICATIONS:
        kk = _magnified(recon.intrinsics, k)
        if truth is not None and ("truth", k) not in references:  # the rig's poses: the same for every variant
            cams = np.linalg.inv(w2c.double().numpy())
            references["truth", k] = torch.from_numpy(
                truth.render(cams, kk.double().numpy(), (height * k, width * k), 0.0).images
            )
        truths = references.get(("truth", k))
        for v in range(pair.num_views):
            mask = torch.from_numpy(
                cv2.resize(world[v].numpy().astype(np.uint8), (width * k, height * k), interpolation=cv2.INTER_NEAREST) > 0
            )
            solid = torch.from_numpy(
                cv2.resize(surface[v].numpy().astype(np.uint8), (width * k, height * k), interpolation=cv2.INTER_NEAREST) > 0
            )
            res = render_gaussians(
                g, 0.0, w2c[v : v + 1], kk[v : v + 1], height * k, width * k,
                sky_sh=recon.sky_sh, ground=recon.ground, blend="cameras", source_axes=axes,
                source_centres=source_centres(recon), **raster,
            )  # fmt: skip
            image = res.colors[0].clamp(0, 1)
            if ("bicubic", k, v) not in references:
                source = pair.images[0, v].astype(np.float32) / 255
                references["bicubic", k, v] = torch.from_numpy(
                    np.clip(cv2.resize(source, (width * k, height * k), interpolation=cv2.INTER_CUBIC), 0, 1)
                )
                references["gauss", k, v] = gaussian_interpolation(torch.from_numpy(source), k).clamp(0, 1)
                references["bilinear", k, v] = torch.from_numpy(
                    np.clip(cv2.resize(source, (width * k, height * k), interpolation=cv2.INTER_LINEAR), 0, 1)
                )
            up, gauss = references["bicubic", k, v], references["gauss", k, v]
            _add(out, f"x{k}_vs_bicubic", _psnr(image, up, mask))
            _add(out, f"x{k}_gauss_vs_bicubic", _psnr(gauss, up, mask))
            _add(out, f"x{k}_bilinear_vs_bicubic", _psnr(references["bilinear", k, v], up, mask))
            # what the magnified view holds of the input: averaged back over k x k blocks to the input's size
            _add(out, f"x{k}_down_vs_input", _psnr(area_down(image[None], k)[0], inputs[0, v], world[v]))
            if truths is not None:
                _add(out, f"x{k}_vs_truth", _psnr(image, truths[v], mask))
                _add(out, f"x{k}_bicubic_vs_truth", _psnr(up, truths[v], mask))
                _add(out, f"x{k}_gauss_vs_truth", _psnr(gauss, truths[v], mask))
            _add(out, f"x{k}_holes", float(((res.alphas[0] < 0.95) & solid).sum() / solid.sum().clamp(min=1)))
            own = g.index((g.keyframes == 0) & (g.cameras == v))
            raw = render_gaussians(own, 0.0, w2c[v : v + 1], kk[v : v + 1], height * k, width * k, eps2d=variant.eps2d).alphas[0]
            _add(out, f"x{k}_raw_holes", float(((raw < 0.95) & solid).sum() / solid.sum().clamp(min=1)))
    return {key: (float(np.mean(v)) if isinstance(v, list) else v) for key, v in out.items()}


def _add(out: dict, key: str, value: float) -> None:
    out.setdefault(key, []).append(value)


def run(args: argparse.Namespace) -> int:
    from drivingscene.data.frame_pair import load_frame_pair
    from drivingscene.machine import machine_description
    from drivingscene.methods.feedforward import load_model
    from drivingscene.synth.config import resolve_config, split_seeds
    from drivingscene.synth.generate import generate_pair
    from drivingscene.synth.novel_view import ProceduralScene
    from drivingscene.synth.render import SynthRenderer

    wall = time.perf_counter()
    variants = (DEFAULT, MERGED) if args.default_only else QUICK if args.quick else VARIANTS
    if args.merge_range is not None:  # the merged default at another colour bound (named as before)
        if not args.merge_range >= 0:
            raise InputError(f"--merge-range: expected a colour difference >= 0, found {args.merge_range}")
        merged = replace(MERGED, merge=BlockMerge(color_range=args.merge_range))
        variants = tuple(merged if v is MERGED else v for v in variants)
    count = 1 if args.quick else args.count
    config = resolve_config("default", **({"height": 64, "width": 112} if args.quick else {}))
    model = load_model(args.weights)
    renderer = SynthRenderer()
    seeds = list(split_seeds(args.split, count, args.start))
    sets: dict[str, dict[str, Scores]] = {"procedural": {v.name: Scores() for v in variants}}
    for seed in seeds:
        pair = generate_pair(config, seed, renderer)
        with ProceduralScene(config, seed, renderer) as truth:
            references: dict = {}
            for v in variants:
                for key, value in score_pair(model, pair, v, truth, references).items():
                    sets["procedural"][v.name].add(key, value)
    for path in args.scenes:
        pair = load_frame_pair(path)
        sets[str(path)] = {v.name: Scores() for v in variants}
        references = {}
        for v in variants:
            for key, value in score_pair(model, pair, v, references=references).items():
                sets[str(path)][v.name].add(key, value)
    minutes = (time.perf_counter() - wall) / 60
    machine = machine_description()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out, _markdown(args, sets, variants, seeds, config, machine, minutes))
    if args.json:
        data = {
            "format": "drivingscene/bench-magnify", "version": 1, "machine": machine, "minutes": round(minutes, 1),
            "seeds": seeds, "sets": {s: {n: {k: sc.mean(k) for k in sc.values} for n, sc in rows.items()} for s, rows in sets.items()},
        }  # fmt: skip
        args.json.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(args.json, json.dumps(data, indent=1) + "\n")
    print(f"drivingscene bench magnify: wrote {args.out} ({minutes:.1f} min)")
    return 0


def _cell(x: float, digits: int = 2) -> str:
    return "–" if math.isnan(x) else f"{x:.{digits}f}"


def _markdown(args, sets, variants, seeds, config, machine, minutes) -> str:
    flags = " --quick" if args.quick else f" --count {args.count}" + (f" --start {args.start}" if args.start else "")
    flags += " --default-only" if args.default_only else ""
    flags += f" --split {args.split}" if args.split != "test" else ""
    flags += f" --merge-range {args.merge_range}" if args.merge_range is not None else ""
    scenes = (" --scenes " + " ".join(map(str, args.scenes))) if args.scenes else ""
    lines = [
        f"Measured with `drivingscene bench magnify{flags}{scenes} --out {args.out}` on {machine}, "
        f"{datetime.now(timezone.utc):%Y-%m-%d}, in {minutes:.1f} min. Procedural: {args.split} seeds "
        f"{seeds[0]}-{seeds[-1]} at {config.height}x{config.width}; each rig camera at t = 0 at 1, 2 and 4 times "
        "the input size. PSNR in dB over the pixels that see the world; holes: world pixels (not sky) "
        "whose coverage is below 0.95 in the picture, and in the image's own layer alone (raw alpha).",
        "",
    ]
    for name, rows in sets.items():
        truth = name == "procedural"
        lines += [f"### {f'Procedural {args.split} pairs' if truth else name}", ""]
        head = (
            "| variant | s/pair | input views | in-between | "
            + " | ".join(f"{k}x vs {'truth' if truth else 'bicubic'}" for k in MAGNIFICATIONS)
            + " | 4x holes | 4x raw holes |"
        )
        lines += [head, "|" + "---|" * (head.count("|") - 1)]
        for v in variants:
            sc = rows[v.name]
            ref = "vs_truth" if truth else "vs_bicubic"
            cells = [_cell(sc.mean("seconds")), _cell(sc.mean("input_views")), _cell(sc.mean("in_between"))]
            cells += [_cell(sc.mean(f"x{k}_{ref}")) for k in MAGNIFICATIONS]
            cells += [f"{100 * sc.mean('x4_holes'):.2f} %", f"{100 * sc.mean('x4_raw_holes'):.1f} %"]
            label = f"**{v.name}**" if v.note == "default" else v.name
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
        default = rows[DEFAULT.name]
        if truth:
            lines += ["", "The input upsampled bicubically, against the same ground truth: " + ", ".join(
                f"{k}x {_cell(default.mean(f'x{k}_bicubic_vs_truth'))} dB" for k in MAGNIFICATIONS
            ) + "; the default variant against the input upsampled bicubically: " + ", ".join(
                f"{k}x {_cell(default.mean(f'x{k}_vs_bicubic'))} dB" for k in MAGNIFICATIONS
            ) + "."]  # fmt: skip
        if MERGED.name in rows:
            merged = rows[MERGED.name]
            lines += ["", "The reconstruction's default (flat blocks merged, " + f"{100 * merged.mean('share'):.1f} % of the "
                "per-pixel Gaussians) against " + ("ground truth: " if truth else "the input upsampled bicubically: ") + ", ".join(
                f"{k}x {_cell(merged.mean(f'x{k}_{ref}'))} dB" for k in MAGNIFICATIONS
            ) + (" (the input upsampled bicubically: " + ", ".join(
                f"{k}x {_cell(default.mean(f'x{k}_bicubic_vs_truth'))}" for k in MAGNIFICATIONS[1:]
            ) + " dB)" if truth else "") + "."]  # fmt: skip
        lines += ["", "The default variant's magnified views averaged back over k x k blocks to the input's size, "
            "against the input (what a magnified view keeps of it; the 1x view itself: " + _cell(default.mean("x1_vs_bicubic"))
            + " dB): " + ", ".join(f"{k}x {_cell(default.mean(f'x{k}_down_vs_input'))}" for k in MAGNIFICATIONS[1:])
            + " dB. Another interpolator for scale: the input upsampled bilinearly scores " + ", ".join(
            f"{k}x {_cell(default.mean(f'x{k}_bilinear_vs_bicubic'))}" for k in MAGNIFICATIONS[1:]
        ) + " dB against the input upsampled bicubically."]  # fmt: skip
        lines += ["", "No geometry: the input interpolated by normalised Gaussians of the smallest splats "
            "(`gaussian_interpolation`: averaged, not composited by depth) scores " + ", ".join(
            f"{k}x {_cell(default.mean(f'x{k}_gauss_vs_bicubic'))}" for k in MAGNIFICATIONS
        ) + " dB against the input upsampled bicubically" + ("; against ground truth " + ", ".join(
            f"{k}x {_cell(default.mean(f'x{k}_gauss_vs_truth'))}" for k in MAGNIFICATIONS
        ) + " dB" if truth else "") + "."]  # fmt: skip
        lines.append("")
    return "\n".join(lines)
