"""``drivingscene synth``: the procedural surround-view benchmark (one pair, or a dataset folder)."""

from __future__ import annotations

import argparse
import math
import re
import sys
from pathlib import Path

from drivingscene.arguments import check_output, parse_resolution
from drivingscene.errors import InputError

KNOBS = {  # flag: (config field, parser, meaning)
    "--ego-speed": ("ego_speed", "float", "ego speed in m/s"),
    "--object-speed-scale": ("object_speed_scale", "float", "factor on every moving object's speed"),
    "--num-moving": ("num_moving", "int", "number of moving vehicles and pedestrians"),
    "--keyframe-gap": ("keyframe_gap", "float", "seconds between the keyframes"),
    "--texture-strength": ("texture_strength", "float", "procedural texture amplitude (0 = flat colours)"),
    "--exposure-change": ("exposure_change", "float", "brightness gain of keyframe 1 relative to keyframe 0"),
    "--noise-std": ("noise_std", "float", "Gaussian image noise std in [0, 1] units"),
    "--blackout-camera": (
        "blackout_camera",
        "camera",
        "camera (a name of the rig or an index) whose images are black, or 'none'",
    ),
    "--num-eval": ("num_eval", "int", "evaluation frames between the keyframes"),
    "--supersample": ("supersample", "int", "colour supersampling factor per axis"),
    "--rig": ("rig", "text", "camera rig: nuscenes, ddad or random (5-8 cameras drawn per seed)"),
    "--scene-style": ("scene_style", "text", "town, suburban or mixed (either, per seed)"),
    "--lighting": ("lighting", "text", "default, or varied (clear, hazy, overcast, golden, bright white sky)"),
    "--photometric": ("photometric", "float", "per-camera exposure, colour, lens, noise and JPEG jitter, strength in [0, 1]"),
    "--ego-body": ("ego_body", "float", "probability per camera of the ego car's body at the image bottom (masked)"),
    "--capture-spread": ("capture_spread", "float", "seconds spanned by one frame's camera triggers, in [0, 0.1]"),
    "--randomise-motion": ("randomise_motion", "bool", "true: ego speed, keyframe gap and object speeds drawn per seed"),
}
BOOLEANS = {"true": True, "yes": True, "on": True, "1": True, "false": False, "no": False, "off": False, "0": False}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "synth",
        help="generate the procedural surround-view benchmark with exact ground truth",
        description="One pair (--seed S --out file.npz) or a dataset (--split SPLIT --count N --out DIR). "
        "Seeds: train [0, 100000), val [100000, 110000), test [200000, 210000).",
    )
    p.add_argument("-o", "--out", metavar="PATH", help="file.npz for --seed, folder for --split")
    p.add_argument("--seed", metavar="S", help="generate this one seed")
    p.add_argument("--split", metavar="SPLIT", help="train, val or test: a dataset of the split's first seeds")
    p.add_argument("--count", metavar="N", help="number of pairs of the dataset")
    p.add_argument("--start", metavar="K", default="0", help="skip the split's first K seeds (default 0)")
    p.add_argument("--res", metavar="HxW", help="image size, e.g. 96x176 (default 176x320)")
    p.add_argument("--preset", metavar="NAME", default="default", help="difficulty preset (see --list-presets)")
    p.add_argument("--list-presets", action="store_true", help="print the presets and exit")
    for flag, (_, _, meaning) in KNOBS.items():
        p.add_argument(flag, metavar="X", help=f"{meaning} (overrides the preset)")
    p.add_argument("--preview", metavar="DIR", help="also write contact-sheet and ground-truth PNGs (of the first pair)")
    p.add_argument(
        "--preview-name",
        metavar="NAME",
        default="synth",
        help="file name prefix of the previews: NAME_contact_sheet.png (default synth)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument(
        "--force",
        action="store_true",
        help="overwrite file.npz (--seed) if it exists; with --split, make the pairs asked for anew, also in a "
        "folder made with other flags when they cover every pair it holds",
    )
    p.set_defaults(func=run)


def _number(flag: str, text: str | None, kind: str):
    if text is None:
        return None
    try:
        value = int(text) if kind == "int" else float(text)
    except ValueError:
        raise InputError(f"{flag}: expected {'an integer' if kind == 'int' else 'a number'}, found {text!r}") from None
    if kind == "float" and not math.isfinite(value):
        raise InputError(f"{flag}: expected a finite number, found {text!r}")
    return value


def config_from_args(args: argparse.Namespace):
    """The resolved ``SynthConfig``: the preset, then every flag given."""
    from drivingscene.synth.config import resolve_config

    overrides = {}
    if args.res is not None:
        overrides["height"], overrides["width"] = parse_resolution(args.res)
    for flag, (field, kind, _) in KNOBS.items():
        text = getattr(args, field)
        if text is None:
            continue
        if kind == "camera":  # checked against the rig by resolve_config
            overrides[field] = "none" if text.lower() == "none" else text
        elif kind == "text":
            overrides[field] = text
        elif kind == "bool":
            if text.lower() not in BOOLEANS:
                raise InputError(f"{flag}: expected true or false, found {text!r}")
            overrides[field] = BOOLEANS[text.lower()]
        else:
            overrides[field] = _number(flag, text, kind)
    return resolve_config(args.preset, **overrides)


def list_presets() -> str:
    from drivingscene.synth.config import PRESET_HELP, PRESETS

    width = max(len(n) for n in PRESETS)
    lines = []
    for name, overrides in PRESETS.items():
        flags = " ".join(f"--{k.replace('_', '-')} {v}" for k, v in overrides.items()) or "(no overrides)"
        lines.append(f"{name:<{width}}  {PRESET_HELP[name]}: {flags}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    if args.list_presets:
        print(list_presets())
        return 0
    config = config_from_args(args)
    if not re.fullmatch(r"[A-Za-z0-9_.-]+", args.preview_name):
        raise InputError(
            f"--preview-name: expected a file name prefix of letters, digits, '_', '-' or '.', found {args.preview_name!r}"
        )
    if args.out is None:
        raise InputError("--out: expected a file.npz (with --seed) or a folder (with --split)")
    if args.seed is not None:
        return _run_single(args, config)
    if args.split is None:
        raise InputError("--seed/--split: expected --seed S for one pair or --split SPLIT --count N for a dataset")
    return _run_dataset(args, config)


def _run_single(args: argparse.Namespace, config) -> int:
    for flag, value in (("--count", args.count), ("--split", args.split)):
        if value is not None:
            raise InputError(f"{flag}: not used with --seed (one pair); use --split SPLIT --count N for a dataset")
    seed = _number("--seed", args.seed, "int")
    if seed < 0 or seed >= 2**32:
        raise InputError(f"--seed: expected an integer in [0, 2^32), found {args.seed!r}")
    out = Path(args.out)
    if out.suffix != ".npz" or out.is_dir():
        raise InputError(f"--out: expected a path ending in .npz for --seed, found {args.out!r}")
    check_output(out, args.force, "--out")
    from drivingscene.data import save_frame_pair
    from drivingscene.synth.generate import generate_pair

    pair = generate_pair(config, seed)
    save_frame_pair(pair, out)
    print(f"{out}: seed {seed}, {config.height}x{config.width}, {pair.num_eval} eval frame(s)")
    if args.preview:
        _preview(pair, args.preview, args.preview_name)
    return 0


def _run_dataset(args: argparse.Namespace, config) -> int:
    from drivingscene.synth.config import split_seeds
    from drivingscene.synth.dataset import pair_path, write_dataset
    from drivingscene.synth.generate import generate_pair
    from drivingscene.synth.render import SynthRenderer

    if args.count is None:
        raise InputError("--count: expected the number of pairs to generate with --split")
    seeds = split_seeds(args.split, _number("--count", args.count, "int"), _number("--start", args.start, "int"))
    renderer = None

    def generate(seed: int):
        nonlocal renderer
        renderer = renderer or SynthRenderer()  # one GL context and program set for every pair
        return generate_pair(config, seed, renderer)

    written, skipped = write_dataset(
        args.out, args.split, seeds, config, generate, progress=not args.no_progress, force=args.force
    )
    print(
        f"{args.out}: {written} pair(s) written, {skipped} already present, split {args.split} seeds "
        f"[{seeds.start}, {seeds.stop})"
    )
    if args.preview:
        from drivingscene.data import load_frame_pair

        _preview(load_frame_pair(pair_path(args.out, seeds.start)), args.preview, args.preview_name)
    return 0


def _preview(pair, folder: str, name: str = "synth") -> None:
    from drivingscene.synth.preview import write_previews

    for path in write_previews(pair, folder, prefix=name):
        print(f"{path}: preview", file=sys.stderr)
