"""``drivingscene validate`` and ``drivingscene info``: on a scene.npz, its problems or its summary;
on a recon.npz or a .ply (told apart by ``drivingscene.sources``), what the file is."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

FRAMES = {"z": "z-up (DrivingScene's world)", "-y": "y-down (graphdeco / COLMAP convention)"}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "validate",
        help="check a scene.npz against the format (a recon.npz too); one line per problem, exit 2 if invalid",
    )
    p.add_argument("files", nargs="+", type=Path, metavar="FILE", help="scene.npz files (a recon.npz or .ply: says what it is)")
    p.add_argument(
        "--geometry",
        action="store_true",
        help="also check that a valid scene's poses, extrinsics and LiDAR agree with its images, camera by camera "
        "(docs/importing.md); exit 1 where an image disagrees",
    )
    p.set_defaults(func=run_validate)
    p = sub.add_parser("info", help="summarise a scene.npz, or say what a recon.npz or .ply holds")
    p.add_argument("file", type=Path, metavar="FILE", help="a scene.npz, recon.npz or 3DGS .ply")
    p.set_defaults(func=run_info)


def describe_gaussians(source) -> str:
    """One line on a recon.npz or PLY opened by ``open_source``: what it is and what it holds."""
    recon = source.recon
    g = recon.gaussians
    counts = f"{len(g)} Gaussians ({int(g.dynamic.sum())} dynamic), SH degree {g.sh_degree}"
    if source.kind == "ply":
        from drivingscene.export.ply import ply_stored_sh_degree

        stored = ply_stored_sh_degree(source.path)
        if stored is not None and stored > g.sh_degree:  # graphdeco's layout: higher bands written as zeros
            counts += f" (stored as degree {stored}, the higher bands all zero)"
        return f"{source.path}: a 3DGS PLY, {counts}, frame {FRAMES.get(source.up, source.up)}"
    h, w = recon.image_size
    hidden = int(recon.hidden.sum()) if recon.hidden is not None else 0
    parts = [counts, f"{recon.num_views} cameras ({', '.join(recon.camera_names)}) at {w}x{h}"]
    if hidden:
        parts.append(f"{hidden} hidden by edits")
    if "method" in recon.meta:
        parts.append(f"method {recon.meta['method']}")
    return f"{source.path}: a DrivingScene reconstruction ({'; '.join(parts)})"


def run_validate(args: argparse.Namespace) -> int:
    from drivingscene.data.frame_pair import validate_frame_pair_file
    from drivingscene.errors import InputError, SceneFormatError
    from drivingscene.sources import open_source, source_kind

    bad = disagree = 0
    for path in args.files:
        kind = source_kind(path)
        if kind == "scene":
            problems = [str(p) for p in validate_frame_pair_file(path)]
        else:
            try:
                source = open_source(path)  # a recon.npz is validated on reading, a PLY is only read
                verdict = "valid" if kind == "recon" else "readable (validate checks scene.npz and recon.npz files)"
                print(f"{describe_gaussians(source)}: {verdict}")
                _warn_unknown_members(path, kind)
                continue
            except SceneFormatError as e:
                problems = [str(p) for p in e.problems]
            except InputError as e:
                problems = [str(e)]
        for problem in problems:
            print(problem, file=sys.stderr)
        if problems:
            bad += 1
        else:
            print(f"{path}: valid")
            _warn_unknown_members(path, kind)
            if args.geometry:
                disagree += check_geometry(path)
    return 2 if bad else 1 if disagree else 0


def unknown_member_lines(path: Path, kind: str) -> list[str]:
    """`data.validate.unknown_members` of a scene or recon .npz (nothing for other files)."""
    from drivingscene.data import validate
    from drivingscene.data.memory import declared_npz
    from drivingscene.gaussians import recon

    specs = {"scene": (validate.REQUIRED, validate.OPTIONAL), "recon": (recon.REQUIRED, recon.OPTIONAL)}.get(kind)
    return [] if specs is None else validate.unknown_members(declared_npz(path), *specs)


def _warn_unknown_members(path: Path, kind: str) -> None:
    for line in unknown_member_lines(path, kind):
        print(f"{path}: warning: {line}", file=sys.stderr)


def check_geometry(path: Path) -> int:
    """Print `methods.rig_check`'s table for the scene at ``path`` and one line per image that
    disagrees; the number of such images."""
    from drivingscene.data.frame_pair import load_frame_pair
    from drivingscene.methods.rig_check import check_rig, summarise, table_lines

    checks = check_rig(load_frame_pair(path))
    print("\n".join(table_lines(checks)))
    problems = summarise(checks).problems
    for line in problems:
        print(f"{path}: {line}", file=sys.stderr)
    if not problems:
        print(f"{path}: geometry consistent with the images")
    return len(problems)


def run_info(args: argparse.Namespace) -> int:
    from drivingscene.sources import source_kind

    kind = source_kind(args.file)
    if kind == "ply":
        from drivingscene.export.ply import describe_point_cloud

        points = describe_point_cloud(args.file)  # export --kind points: says so instead of a 3DGS error
        if points is not None:
            print(points)
            return 0
    if kind != "scene":
        from drivingscene.sources import open_source

        print(describe_gaussians(open_source(args.file)))
        return 0
    from drivingscene.data.frame_pair import load_frame_pair
    from drivingscene.data.summary import summarise

    print(summarise(load_frame_pair(args.file), args.file))
    for line in unknown_member_lines(args.file, kind):
        print(f"unknown     {line}")
    return 0
