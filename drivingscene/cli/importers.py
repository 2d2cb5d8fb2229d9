"""``drivingscene import nuscenes|ddad|rig``: real driving data into a scene.npz (docs/importing.md)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from drivingscene.arguments import check_output


def _resolution(text: str) -> tuple[int, int]:
    from drivingscene.data.importers.common import parse_resolution

    return parse_resolution(text)


def _common(p: argparse.ArgumentParser, default_res: str | None = "176x320") -> None:
    res_help = "output image size HxW" + (f" (default {default_res})" if default_res else " (default: the images' own size)")
    p.add_argument("--res", type=_resolution, default=default_res, help=res_help)  # argparse converts a string default
    p.add_argument(
        "--fit",
        choices=("crop", "pad"),
        default="crop",
        help="another aspect ratio: scale to cover and centre-crop (default), or scale to fit and pad (padding is masked)",
    )
    p.add_argument("-o", "--out", type=Path, required=True, metavar="SCENE", help="the scene.npz to write")
    p.add_argument("--force", action="store_true", help="overwrite SCENE if it exists")
    p.add_argument(
        "--no-check",
        action="store_true",
        help="do not check the written scene's poses, extrinsics and LiDAR against its images "
        "(`drivingscene validate SCENE --geometry`; about a second)",
    )


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("import", help="import real driving data (nuScenes, DDAD, your own rig) into a scene.npz")
    isub = p.add_subparsers(dest="dataset", metavar="DATASET", required=True, parser_class=type(p))

    n = isub.add_parser("nuscenes", help="two keyframes (or a keyframe and a later sweep) of a nuScenes scene (nuscenes-devkit)")
    n.add_argument("--dataroot", type=Path, required=True, help="the nuScenes folder (holds samples/, sweeps/, v1.0-*/)")
    n.add_argument("--version", default="v1.0-mini", help="table folder, e.g. v1.0-mini or v1.0-trainval (default v1.0-mini)")
    n.add_argument("--scene", required=True, help="scene name, e.g. scene-0061")
    n.add_argument("--sample", type=int, default=0, help="index of the first keyframe within the scene (default 0)")
    n.add_argument(
        "--next",
        choices=("keyframe", "sweep"),
        default="keyframe",
        help="second frame: the next keyframe (0.5 s later, default) or the next camera sweep (~0.08 s)",
    )
    n.add_argument("--eval-sweeps", action="store_true", help="keep the camera sweeps between the two keyframes as eval frames")
    _common(n)
    n.set_defaults(func=run_nuscenes)

    d = isub.add_parser("ddad", help="two samples of a DDAD scene in the DGP layout (scene_*.json, calibration/, rgb/)")
    d.add_argument("scene_dir", type=Path, metavar="SCENE_DIR", help="a DDAD scene folder (DGP layout: scene_*.json, rgb/, ...)")
    d.add_argument(
        "--samples",
        type=int,
        nargs=2,
        default=(0, 1),
        metavar=("I", "J"),
        help="the two keyframes (default 0 1); the same sample twice: a still pair, 0.1 s apart",
    )
    d.add_argument("--eval", type=int, nargs="*", default=(), metavar="K", help="samples between I and J kept as eval frames")
    d.add_argument("--no-mask", action="store_true", help="no ego-body valid_mask (default: the DDAD rig's documented polygons)")
    _common(d)
    d.set_defaults(func=run_ddad)

    r = isub.add_parser("rig", help="your own rig: a folder of images plus rig.json (docs/importing.md)")
    r.add_argument("folder", type=Path, metavar="FOLDER", help="images plus rig.json (docs/importing.md)")
    r.add_argument(
        "--frames",
        type=int,
        nargs=2,
        default=(0, 1),
        metavar=("I", "J"),
        help="the two keyframes (default 0 1); the same sample twice: a still pair, 0.1 s apart",
    )
    r.add_argument("--eval", type=int, nargs="*", default=(), metavar="K", help="frames between I and J kept as eval frames")
    _common(r, default_res=None)
    r.set_defaults(func=run_rig)


def _write(pair, args: argparse.Namespace) -> int:
    from drivingscene.data.frame_pair import save_frame_pair

    save_frame_pair(pair, args.out)
    h, w = pair.image_size
    extra = f", {pair.num_eval} eval frame(s)" if pair.num_eval else ""
    depth = ", LiDAR depth" if pair.gt_depth is not None else ""
    mask = f", {100 * (1 - pair.world_mask().mean()):.1f}% masked" if pair.valid_mask is not None else ""
    print(f"{args.out}: {pair.num_views} cameras, {w}x{h}, {pair.duration:.3f} s apart{extra}{depth}{mask}")
    if not args.no_check:
        _check_geometry(pair, args.out)
    return 0


def _check_geometry(pair, out: Path) -> None:
    """One line on whether the imported scene's geometry agrees with its images (`methods.rig_check`),
    and a warning per image that does not; the import stands either way."""
    from drivingscene.methods.rig_check import check_rig, summarise

    summary = summarise(check_rig(pair))
    for line in summary.problems:
        print(f"{out}: warning: {line}", file=sys.stderr)
    if summary.problems:
        print(
            f"{out}: {len(summary.problems)} of {summary.images} images disagree with the geometry: "
            f"`drivingscene validate {out} --geometry` shows the table"
        )
    elif summary.tested:
        print(
            f"{out}: geometry consistent with the images ({summary.tested} of {summary.images} images tested; docs/importing.md)"
        )
    else:
        print(f"{out}: geometry not checked: no image has the motion and texture to test it")


def run_nuscenes(args: argparse.Namespace) -> int:
    from drivingscene.data.importers.nuscenes import import_nuscenes

    check_output(args.out, args.force, "-o")
    pair = import_nuscenes(
        args.dataroot,
        args.version,
        args.scene,
        args.sample,
        next_frame=args.next,
        eval_sweeps=args.eval_sweeps,
        size=args.res,
        fit=args.fit,
    )
    return _write(pair, args)


def run_ddad(args: argparse.Namespace) -> int:
    from drivingscene.data.importers.ddad import import_ddad

    check_output(args.out, args.force, "-o")
    pair = import_ddad(args.scene_dir, tuple(args.samples), tuple(args.eval), size=args.res, fit=args.fit, mask=not args.no_mask)
    return _write(pair, args)


def run_rig(args: argparse.Namespace) -> int:
    from drivingscene.data.importers.rig import import_rig

    check_output(args.out, args.force, "-o")
    pair = import_rig(args.folder, tuple(args.frames), tuple(args.eval), size=args.res, fit=args.fit)
    return _write(pair, args)
