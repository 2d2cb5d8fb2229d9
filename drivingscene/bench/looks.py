"""``drivingscene bench looks``: how much D's depth depends on the images' tone.

Every image of a pair is given one global tone change (a gamma ``out = in ** gamma`` or an
exposure gain, clipped), the model reconstructs it, and its depth is scored against ground truth
(procedural ``gt_depth``, or LiDAR on an imported real pair): D alone (``--match off``) and with the
matching of inference. Metric depth should not follow brightness; a network that learnt
"darker is nearer" from its training looks does. Several weights side by side show whether a
training change (``drivingscene train --input-jitter``) bought that invariance, and what it cost at
the original tone (gamma 1).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from drivingscene.arguments import positive_int
from drivingscene.bench import write_report
from drivingscene.errors import InputError
from drivingscene.machine import machine_description

DEFAULT_TONES = ("gamma=0.6", "gamma=1", "gamma=1.6", "gain=0.6", "gain=1.6")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--data", type=Path, nargs="+", required=True, help="folders of pairs and/or pair files with ground-truth depth"
    )
    p.add_argument("--count", type=positive_int, default=10, help="pairs per folder (default 10)")
    p.add_argument(
        "--weights", type=Path, nargs="+", default=None, help="model weights to compare (default: the shipped weights)"
    )
    p.add_argument(
        "--tones",
        nargs="+",
        default=list(DEFAULT_TONES),
        metavar="KIND=VALUE",
        help=f"tone changes applied to every image: gamma=G or gain=G (default: {' '.join(DEFAULT_TONES)})",
    )
    p.add_argument("-o", "--out", type=Path, default=None, help="write the markdown report here (default: print it)")


def parse_tone(text: str) -> tuple[str, float]:
    kind, sep, value = text.partition("=")
    try:
        number = float(value)
    except ValueError:
        number = float("nan")
    if not sep or kind not in ("gamma", "gain") or not 0.05 <= number <= 20:
        raise InputError(f"--tones: expected gamma=G or gain=G with G in [0.05, 20], found {text!r}")
    return kind, number


def toned(images: np.ndarray, kind: str, value: float) -> np.ndarray:
    """uint8 images with one global tone change: ``in ** value`` (gamma) or ``in * value`` (gain), clipped."""
    x = images.astype(np.float32) / 255.0
    x = x**value if kind == "gamma" else x * value
    return np.clip(np.rint(x * 255.0), 0, 255).astype(np.uint8)


def run(args: argparse.Namespace) -> int:
    from drivingscene.data.frame_pair import load_frame_pair
    from drivingscene.eval.reconstruction import score_depth
    from drivingscene.methods.feedforward import InferenceOptions, load_model, reconstruct
    from drivingscene.train.data import pair_files

    tones = [parse_tone(t) for t in args.tones]  # errors before any work
    sets = [(str(path), pair_files(path, args.count)) for path in args.data]
    weights = args.weights or [None]
    models = [(str(w) if w else "shipped", load_model(w)) for w in weights]
    modes = (("D alone", replace(InferenceOptions(), match=None)), ("matched", InferenceOptions()))
    rows = []
    for name, files in sets:
        pairs = [load_frame_pair(f) for f in files]
        if any(p.gt_depth is None for p in pairs):
            raise InputError(f"{name}: --data: expected pairs with gt_depth (procedural, or imported with LiDAR)")
        for label, model in models:
            for kind, value in tones:
                inputs = [replace(p, images=toned(p.images, kind, value)) for p in pairs]
                cells = []
                for _, options in modes:
                    scores = [score_depth(reconstruct(model, toned_pair, options), p) for toned_pair, p in zip(inputs, pairs)]
                    absrel = np.nanmean([s["depth_abs_rel"] for s in scores])
                    scaled = np.nanmean([s["depth_ms_abs_rel"] for s in scores])
                    cells.append(f"{absrel:.3f} | {scaled:.3f}")
                rows.append(f"| {name} ({len(pairs)}) | {label} | {kind} {value:g} | {' | '.join(cells)} |")
                print(rows[-1], flush=True)
    cmd = "drivingscene bench looks --data " + " ".join(str(d) for d in args.data) + f" --count {args.count}"
    if args.weights:
        cmd += " --weights " + " ".join(str(w) for w in args.weights)
    if list(args.tones) != list(DEFAULT_TONES):
        cmd += " --tones " + " ".join(args.tones)
    text = "\n".join(
        [
            "# Depth and the images' tone",
            "",
            "How far D's metric depth follows the brightness of its input: every image of a pair is given one global "
            "tone change (gamma: out = in ** G; gain: out = G x in, clipped) and reconstructed; D alone is `--match off`, "
            "matched is the inference default. Ground truth: the generator's depth, or LiDAR on an imported real pair "
            "(shown, never used to choose). Depth should not follow the tone; what the rows cost at gamma 1 matters as much "
            "as the spread across the tones. Why this exists and what was tried: [training.md](training.md).",
            "",
            f"Measured with `{cmd}` on {machine_description()}, {time.strftime('%Y-%m-%d')}. Every image of a pair "
            "given the tone change; depth AbsRel against the ground truth (metric | median-scaled), means over the pairs.",
            "",
            "| pairs | weights | tone | D alone AbsRel | D alone, median-scaled | matched AbsRel | matched, median-scaled |",
            "|---|---|---|---|---|---|---|",
            *rows,
            "",
        ]
    )
    write_report(text, args.out, announce=False)
    return 0
