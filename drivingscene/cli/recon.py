"""``drivingscene reconstruct`` (the model), ``drivingscene oracle`` (ground truth) and
``drivingscene classical`` (the learning-free baseline)."""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

from drivingscene.arguments import (
    Progress,
    adaptation_settings,
    add_adaptation_arguments,
    add_amp_arguments,
    add_match_arguments,
    check_output,
    fraction,
    non_negative_int,
    non_negative_seconds,
    positive_int,
)
from drivingscene.errors import InputError


def add_refine_arguments(p: argparse.ArgumentParser) -> None:
    """``--refine SECONDS``, ``--lidar``, ``--adapt K``, ``--refine-steps N``, ``--adapt-share``,
    ``--adapt-scale`` (docs/refinement.md)."""
    p.add_argument(
        "--refine",
        type=non_negative_seconds,
        default=None,
        metavar="SECONDS",
        help="then refine the Gaussians against the input images for this many seconds (docs/refinement.md)",
    )
    p.add_argument("--lidar", action="store_true", help="with --refine: also fit the scene's LiDAR depth (gt_depth)")
    p.add_argument(
        "--adapt",
        type=non_negative_int,
        default=None,
        metavar="K",
        help="with --refine: first adapt D to the pair for K steps (default 15, none with --lidar; 0: not at all)",
    )
    p.add_argument("--refine-steps", type=positive_int, default=None, metavar="N", help="with --refine: at most N gradient steps")
    add_adaptation_arguments(p, prefix="with --refine: ")


def add_file_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--file-precision",
        choices=("float16", "float32"),
        default="float16",
        help="how the Gaussians' rotations, scales, opacities and colours are stored (default float16: the same "
        "picture, docs/reconstruction-format.md; float32 as before issue 48)",
    )
    p.add_argument(
        "--deflate",
        action="store_true",
        help="compress the file (the Gaussians barely compress; about 2 s more to write per 6x176x320 pair)",
    )


def _scale(text: str) -> float | str:
    if text == "auto":
        return text
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not 0 < value <= 1:
        raise argparse.ArgumentTypeError(f"expected a scale in (0, 1] or 'auto', found {text!r}")
    return value


def memory_scale(scene: Path, scale: float | str, refine: bool) -> float:
    """The scale to reconstruct ``scene`` at (``--scale``, 'auto': the largest that fits), checked
    against the memory available from the file's array headers, before anything is loaded."""
    from drivingscene.data.memory import declared_nbytes, declared_npz
    from drivingscene.machine import available_memory_bytes
    from drivingscene.methods.memory import check_reconstruct_memory, fitting_scale

    arrays = declared_npz(scene)
    if len(arrays.get("images", ((),))[0]) != 5:  # no readable images: the loader says what is wrong
        return 1.0 if scale == "auto" else scale
    _, views, height, width, _ = arrays["images"][0]
    loaded = sum(declared_nbytes(*a) for a in arrays.values())
    if scale == "auto":
        scale = fitting_scale(views, height, width, available_memory_bytes() - loaded, refine) or 1.0
    check_reconstruct_memory(views, height, width, str(scene), refine, loaded, flag="--scale", scale=scale)
    return scale


def refine_config(args: argparse.Namespace):
    """The ``RefineConfig`` of the refine flags; one-line errors for flags without ``--refine``."""
    from drivingscene.methods.refine import RefineConfig

    if args.refine is None:
        flags = (
            ("--lidar", args.lidar),
            ("--adapt", args.adapt is not None),
            ("--refine-steps", args.refine_steps),
            ("--adapt-share", args.adapt_share is not None),
            ("--adapt-scale", args.adapt_scale is not None),
        )
        for flag, given in flags:
            if given:
                raise InputError(f"{flag}: only with --refine SECONDS")
        return None
    return RefineConfig(
        seconds=args.refine,
        lidar=args.lidar,
        adapt_steps=args.adapt,
        max_steps=args.refine_steps,
        threads=args.threads,
        **adaptation_settings(args),
    )


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("reconstruct", help="reconstruct a scene.npz with the model into recon.npz")
    p.add_argument("scene", type=Path, metavar="SCENE", help="a scene.npz (drivingscene synth, drivingscene import)")
    p.add_argument("-o", "--out", type=Path, required=True, metavar="RECON", help="the recon.npz to write")
    p.add_argument("--weights", type=Path, default=None, help="model weights (default: assets/weights/drivingscene.safetensors)")
    p.add_argument("--static-only", action="store_true", help="no residual flow (every Gaussian static)")
    p.add_argument(
        "--no-search", action="store_true", help="R's flow as it is, without the search along the rigid flow (ablation)"
    )
    p.add_argument(
        "--no-parallax",
        action="store_true",
        help="every pixel R and the search move stays dynamic, also where a static surface at another depth "
        "explains its flow (docs/depth.md, parallax before motion)",
    )
    objects = p.add_mutually_exclusive_group()
    objects.add_argument(
        "--objects",
        action="store_true",
        help="track moving objects as wholes between the keyframes (the default; methods/object_motion.py, "
        "docs/moving-objects.md)",
    )
    objects.add_argument(
        "--no-objects",
        action="store_true",
        help="R's and the search's flow alone on moving objects, no tracking (ablation: faster, moving objects "
        "worse; docs/moving-objects.md)",
    )
    p.add_argument(
        "--per-pixel",
        action="store_true",
        help="one Gaussian per pixel and keyframe: flat blocks not merged (about twice the Gaussians; ablation, "
        "docs/parsimony.md)",
    )
    p.add_argument(
        "--budget",
        type=fraction,
        default=None,
        metavar="SHARE",
        help="at most this share (0-1] of the per-pixel Gaussians: the flat-block merge loosened until it holds "
        "(depth edges and moving objects stay unmerged; docs/parsimony.md)",
    )
    add_match_arguments(p)
    p.add_argument("--threads", type=positive_int, default=None, help="torch threads (default: torch's choice)")
    add_amp_arguments(p)
    p.add_argument("--device", default="cpu", help="cpu (default), cuda or cuda:N (a GPU is optional)")
    add_refine_arguments(p)
    p.add_argument(
        "--scale",
        type=_scale,
        default=1.0,
        metavar="S",
        help="reconstruct the keyframes resized by S in (0, 1], or 'auto': the largest scale that fits in the "
        "memory available (default 1: refused with a message when it does not fit)",
    )
    add_file_arguments(p)
    p.add_argument("--force", action="store_true", help="overwrite RECON if it exists")
    p.set_defaults(func=run_reconstruct)

    p = sub.add_parser("oracle", help="per-pixel Gaussians from a scene's ground-truth depth and scene flow")
    p.add_argument("scene", type=Path, metavar="SCENE", help="a scene.npz (drivingscene synth, drivingscene import)")
    p.add_argument("-o", "--out", type=Path, required=True, metavar="RECON", help="the recon.npz to write")
    p.add_argument("--no-flow", action="store_true", help="ignore gt_scene_flow (every Gaussian static)")
    p.add_argument(
        "--refine", type=int, default=2, metavar="N", help="iterations of the colour solve (default 2; 0 = raw pixel colours)"
    )
    p.add_argument("--force", action="store_true", help="overwrite RECON if it exists")
    p.set_defaults(func=run_oracle)
    _register_classical(sub)
    _register_prune(sub)


def _register_classical(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "classical",
        help="learning-free baseline: OpenCV DIS optical flow triangulated with the known poses, no network",
    )
    p.add_argument("scene", type=Path, metavar="SCENE", help="a scene.npz (drivingscene synth, drivingscene import)")
    p.add_argument("-o", "--out", type=Path, required=True, metavar="RECON", help="the recon.npz to write")
    p.add_argument(
        "--preset", choices=("medium", "fast", "ultrafast"), default="medium", help="OpenCV DIS preset (default medium)"
    )
    p.add_argument(
        "--refine",
        type=non_negative_int,
        default=2,
        metavar="N",
        help="iterations of the colour solve (default 2; 0 = raw pixel colours)",
    )
    p.add_argument("--force", action="store_true", help="overwrite RECON if it exists")
    p.set_defaults(func=run_classical)


def _register_prune(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("prune", help="model no more than the scene needs: prune and merge a reconstruction's Gaussians")
    p.add_argument("recon", type=Path, metavar="RECON", help="the recon.npz to prune")
    p.add_argument("-o", "--out", type=Path, required=True, metavar="OUT", help="the pruned recon.npz to write")
    p.add_argument("--scene", type=Path, default=None, help="scene.npz with intermediate frames: report the PSNR change there")
    p.add_argument("--target", type=positive_int, default=None, help="at most this many Gaussians")
    p.add_argument("--min-opacity", type=float, default=0.02, help="drop Gaussians less opaque than this (default 0.02)")
    p.add_argument("--merge-cell", type=float, default=3.0, help="merge cell in multiples of a Gaussian's size (0: no merging)")
    p.add_argument("--max-distance", type=float, default=None, help="drop Gaussians farther from the rig (metres)")
    p.add_argument("--force", action="store_true", help="overwrite OUT if it exists")
    p.set_defaults(func=run_prune)


def run_prune(args: argparse.Namespace) -> int:
    import torch

    from drivingscene.gaussians.budget import BudgetConfig, apply_budget
    from drivingscene.gaussians.recon import load_reconstruction, save_reconstruction

    check_output(args.out, args.force, "-o")
    if not 0 <= args.min_opacity < 1:
        raise InputError(f"--min-opacity: expected a value in [0, 1), found {args.min_opacity}")
    if args.merge_cell < 0:
        raise InputError(f"--merge-cell: expected a value >= 0, found {args.merge_cell}")
    recon = load_reconstruction(args.recon)
    config = BudgetConfig(args.min_opacity, args.max_distance, args.merge_cell, target_count=args.target)
    centre = torch.from_numpy(recon.ego_to_world[:, :3, 3].mean(0)).float()
    gaussians, report = apply_budget(recon.visible(), config, centre)
    pruned = recon.with_gaussians(gaussians)
    for line in report.lines():
        print(line)
    if args.scene is not None:
        from drivingscene.data.frame_pair import load_frame_pair
        from drivingscene.eval.reconstruction import score_novel_views

        pair = load_frame_pair(args.scene)
        before, after = (score_novel_views(r, pair, None)["psnr"] for r in (recon, pruned))
        print(f"intermediate-frame PSNR {before:.2f} -> {after:.2f} dB ({after - before:+.2f})")
    save_reconstruction(pruned, args.out)
    print(f"{args.out}: written")
    return 0


def _report(recon, path: Path) -> None:
    g = recon.gaussians
    timings = recon.meta.get("timings", {})
    total = f", {timings['total_s']:.3f} s" if "total_s" in timings else ""
    total += f" ({recon.meta['precision']})" if "precision" in recon.meta else ""
    merged = (
        f" ({100 * len(g) / per_pixel:.0f} % of {per_pixel} per pixel)"
        if (per_pixel := recon.meta.get("per_pixel_gaussians"))
        else ""
    )
    print(f"{path}: {len(g)} Gaussians{merged} ({int(g.dynamic.sum())} dynamic), {recon.num_views} cameras{total}")


def run_reconstruct(args: argparse.Namespace) -> int:
    check_output(args.out, args.force, "-o")
    with Progress("drivingscene reconstruct") as progress:  # stage lines on stderr once it takes more than a second
        return _reconstruct(args, progress)


def _reconstruct(args: argparse.Namespace, progress: Progress) -> int:
    from drivingscene.data.frame_pair import load_frame_pair
    from drivingscene.data.summary import motion_warnings
    from drivingscene.gaussians.recon import save_reconstruction
    from drivingscene.methods.devices import resolve_device
    from drivingscene.methods.feedforward import InferenceOptions, load_model, reconstruct
    from drivingscene.methods.matched_depth import match_mode

    if args.per_pixel and args.budget is not None:
        raise InputError("--per-pixel and --budget: expected one of them (a budget merges Gaussians)")
    config = refine_config(args)
    device = resolve_device(args.device)
    if config is not None and device.type != "cpu":
        raise InputError("--refine: runs on the CPU rasterizer; use --device cpu")
    scale = memory_scale(args.scene, args.scale, config is not None)
    if scale != 1 and config is not None and config.lidar:
        raise InputError("--lidar: the LiDAR depth is not resized; drop --scale or --lidar")
    progress.stage(f"loading {args.scene}")
    pair = load_frame_pair(args.scene)
    for line in motion_warnings(pair):  # the reconstruction goes on, as import's geometry check
        print(f"{args.scene}: warning: {line}", file=sys.stderr)
    if config is not None and config.lidar and pair.gt_depth is None:
        raise InputError(f"{args.scene}: --lidar: the scene has no LiDAR depth (gt_depth); drop --lidar")
    if scale != 1:
        from drivingscene.data.resize import resized_pair

        pair = resized_pair(pair, scale)
    progress.stage("loading the networks")
    model = load_model(args.weights, device=device)
    options = InferenceOptions(use_residual=not args.static_only, amp=args.amp, threads=args.threads)
    if args.no_search:
        options = replace(options, search=None)
    if args.per_pixel:
        options = replace(options, merge=None)
    if args.budget is not None:
        options = replace(options, merge=replace(options.merge, budget=args.budget))
    if args.no_parallax:
        options = replace(options, lift=replace(options.lift, epipolar_static=False))
    if args.no_objects:
        options = replace(options, objects=None)
    options = replace(options, match=match_mode(args.match))
    progress.stage(f"reconstructing {pair.num_views} cameras at {pair.image_size[1]}x{pair.image_size[0]}")
    recon = reconstruct(model, pair, options, progress=progress)
    if args.budget is not None and len(recon.gaussians) > args.budget * recon.meta["per_pixel_gaussians"]:
        share = len(recon.gaussians) / recon.meta["per_pixel_gaussians"]
        print(
            f"warning: --budget {args.budget:g}: reached {share:.3f} of the per-pixel Gaussians at most "
            "(depth edges and moving objects are not merged)",
            file=sys.stderr,
        )
    progress.stage(stage_times(recon.meta.get("timings", {})))
    if config is not None:
        recon = run_refinement(model, pair, recon, config)
    progress.stage(f"writing {args.out}")
    _report(recon, save_reconstruction(recon, args.out, args.file_precision, args.deflate))
    return 0


STAGES = (("static_s", "networks D+P"), ("match_s", "matching"), ("flow_s", "flow"), ("assembly_s", "assembly"))


def stage_times(timings: dict) -> str:
    """The model's stages as one progress line, from ``recon.meta["timings"]`` (feedforward.reconstruct)."""
    done = ", ".join(f"{name} {timings[key]:.2f} s" for key, name in STAGES if key in timings)
    return f"reconstructed: {done}" if done else "reconstructed"


def run_refinement(model, pair, recon, config):
    """``refine`` with a tqdm bar over the budget's seconds; prints one summary line."""
    from tqdm import tqdm

    from drivingscene.methods.refine import describe, refine

    with tqdm(
        total=round(config.seconds, 1), unit="s", desc="refine", bar_format="{l_bar}{bar}| {n:.1f}/{total:.1f} s {postfix}"
    ) as bar:

        def progress(fraction, message):
            if fraction is not None:
                bar.n = round(min(fraction, 1.0) * config.seconds, 1)
            bar.set_postfix_str(message, refresh=True)

        recon = refine(model, pair, recon, config, progress=progress)
    print(describe(recon.meta["refinement"]))
    return recon


def run_oracle(args: argparse.Namespace) -> int:
    from drivingscene.data.frame_pair import load_frame_pair
    from drivingscene.gaussians.recon import save_reconstruction
    from drivingscene.methods.oracle import oracle_reconstruction

    check_output(args.out, args.force, "-o")
    if args.refine < 0:
        raise InputError(f"--refine: expected a number of steps >= 0, found {args.refine}")
    recon = oracle_reconstruction(load_frame_pair(args.scene), use_scene_flow=not args.no_flow, refine=args.refine)
    _report(recon, save_reconstruction(recon, args.out))
    return 0


def run_classical(args: argparse.Namespace) -> int:
    from drivingscene.data.frame_pair import load_frame_pair
    from drivingscene.gaussians.recon import save_reconstruction
    from drivingscene.methods.classical import ClassicalConfig, classical_reconstruction

    check_output(args.out, args.force, "-o")
    config = ClassicalConfig(preset=args.preset, refine=args.refine)
    recon = classical_reconstruction(load_frame_pair(args.scene), config)
    _report(recon, save_reconstruction(recon, args.out))
    return 0
