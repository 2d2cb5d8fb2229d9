"""``drivingscene export``: PLY files from a reconstruction or another PLY."""

from __future__ import annotations

import argparse
from pathlib import Path

from drivingscene.arguments import add_output_argument, check_output, unit_interval


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="write Gaussians as a PLY file (3DGS, dynamic or points)")
    p.add_argument("source", type=Path, metavar="RECON_OR_PLY", help="recon.npz or a 3DGS .ply")
    add_output_argument(p, "--ply", required=True, metavar="OUT.ply", help="the PLY to write (--ply: the same, the old name)")
    p.add_argument(
        "--kind",
        choices=("3dgs", "dynamic", "points"),
        default="3dgs",
        help="3dgs (default: positions at --time, readable by 3DGS viewers), dynamic (keyframe positions plus flow), "
        "points (coloured points)",
    )
    p.add_argument(
        "--sh-degree",
        type=int,
        choices=(0, 1, 2, 3),
        default=None,
        help="SH degree written (3dgs, dynamic): lower drops higher bands (default: padded to 3, the layout 3DGS tools load)",
    )
    p.add_argument("--time", type=unit_interval, default=None, metavar="T", help="normalised time in [0, 1] (0 = keyframe 0)")
    p.add_argument("--include-hidden", action="store_true", help="also write Gaussians hidden by an edit")
    p.add_argument("--force", action="store_true", help="overwrite OUT.ply if it exists")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from drivingscene.errors import InputError
    from drivingscene.export.ply import write_ply
    from drivingscene.sources import open_source

    check_output(args.out, args.force, "-o")
    source = open_source(args.source)
    if source.kind == "scene":
        raise InputError(
            f"{args.source}: is a scene (images and poses), not Gaussians; expected a recon.npz or a .ply "
            f"(reconstruct it first: drivingscene reconstruct {args.source} -o recon.npz)"
        )
    gaussians = source.recon.gaussians if args.include_hidden else source.recon.visible()
    origin = source.recon.origin if source.recon is not None else None
    path = write_ply(gaussians, args.out, kind=args.kind, t=args.time, sh_degree=args.sh_degree, up=source.up, origin=origin)
    moving = int(gaussians.dynamic.sum())
    when = "" if args.time is None else f" at t={args.time:g}"
    print(f"{path}: {len(gaussians)} Gaussians ({moving} dynamic), {args.kind}{when}")
    return 0
