"""``drivingscene bench geometry``: how often the geometry check (`methods.rig_check`) reports an
image whose geometry is right, by the largest expected motion it puts to the epipolar test.

On procedural pairs the poses, extrinsics and depth are exact, so every image the check reports
is a false alarm; unguided DIS stops following the motion from some tens of pixels on, and
``RigCheckConfig.max_motion_px`` is chosen here as the largest setting with none. Real scenes
(their geometry unknown to be right) are shown, never used to choose.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

from drivingscene.arguments import positive_int
from drivingscene.bench import write_report
from drivingscene.machine import machine_description

DEFAULT_MOTIONS = (15.0, 20.0, 25.0, 30.0, 40.0, 60.0)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", type=Path, nargs="+", required=True, help="folders of pairs and/or pair files")
    p.add_argument("--count", type=positive_int, default=10, help="pairs per folder (default 10)")
    p.add_argument(
        "--motions",
        type=float,
        nargs="+",
        default=list(DEFAULT_MOTIONS),
        metavar="PX",
        help=f"settings of the largest expected motion put to the epipolar test (default: {' '.join(f'{m:g}' for m in DEFAULT_MOTIONS)})",
    )
    p.add_argument("-o", "--out", type=Path, default=None, help="write the markdown report here (default: print it)")


def run(args: argparse.Namespace) -> int:
    from drivingscene.data.frame_pair import load_frame_pair
    from drivingscene.methods.rig_check import RigCheckConfig, check_rig
    from drivingscene.train.data import pair_files

    default = RigCheckConfig()
    everything = replace(default, max_motion_px=float("inf"))  # every image tested: the settings are applied below
    rows = []
    for path in args.data:
        files = pair_files(path, args.count)
        checks = [c for f in files for c in check_rig(load_frame_pair(f), everything)]
        for motion in args.motions:
            tested = [c for c in checks if c.off_line_px is not None and c.motion_px <= motion]
            reported = [c for c in tested if "behind" in c.verdict or "epipolar" in c.verdict]
            mark = " (default)" if motion == default.max_motion_px else ""
            rows.append(f"| {path} ({len(files)}) | {motion:g}{mark} | {len(checks)} | {len(tested)} | {len(reported)} |")
            print(rows[-1], flush=True)
    cmd = "drivingscene bench geometry --data " + " ".join(str(d) for d in args.data) + f" --count {args.count}"
    if list(args.motions) != list(DEFAULT_MOTIONS):
        cmd += " --motions " + " ".join(f"{m:g}" for m in args.motions)
    text = "\n".join(
        [
            "# The geometry check on pairs whose geometry is known",
            "",
            f"Measured with `{cmd}` on {machine_description()}, {time.strftime('%Y-%m-%d')}. Per set and setting of the "
            "largest expected motion (median rigid flow of the road plane, pixels at the checked size) put to the "
            "epipolar test: the images, those tested, and those reported (matches behind the cameras or off their "
            "epipolar lines). On procedural pairs every report is a false alarm.",
            "",
            "| pairs | largest motion tested (px) | images | tested | reported |",
            "|---|---|---|---|---|",
            *rows,
            "",
        ]
    )
    write_report(text, args.out, announce=False)
    return 0
