"""``drivingscene bench refine --choices`` and ``--speed``: how refinement's settings were chosen.

- ``--choices --steps N``: each variant of `CHOICES` refines every pair for exactly N steps (not
  seconds, so that the comparison does not depend on the machine's load), scored on the held-out
  in-between frame; validation pairs only.
- ``--speed``: seconds per step on the first pair for views per step x image scale x threads
  (a few steps each, the first one, which builds caches, not counted).
"""

from __future__ import annotations

import math
import statistics

from drivingscene.methods.refine import RefineConfig

HALF = (("depth", 0.0025), ("color", 0.0125), ("opacity", 0.025), ("scale", 0.0025), ("flow", 0.005))
DOUBLE = (("depth", 0.01), ("color", 0.05), ("opacity", 0.1), ("scale", 0.01), ("flow", 0.02))
CHOICES: dict[str, dict] = {
    "default": {},
    "learning rates x2": {"lr": DOUBLE},
    "learning rates x0.5": {"lr": HALF},
    "without the depth group": {"groups": ("color", "opacity", "scale", "flow")},
    "colour only": {"groups": ("color",)},
    "6 views per step, half the steps": {"views_per_step": 6, "steps": 0.5},
    "cosine decay of the rates": {"decay": True},
    "with the paper's LPIPS term (0.05)": {"lpips_weight": 0.05},
    "without the depth sweep": {"sweep": None},
    "adapt D for 5 steps first": {"adapt_steps": 5},
}


def variant_config(name: str, steps: int, lidar: bool = False) -> RefineConfig:
    """The variant at ``steps`` gradient steps; D is not adapted unless the variant says so (the
    variants compare the sweep and the steps, which an adaptation would precede and, for the sweep,
    replace)."""
    kwargs = {"adapt_steps": 0, **CHOICES[name]}
    fraction = kwargs.pop("steps", 1.0)
    return RefineConfig(seconds=1e9, max_steps=max(1, round(steps * fraction)), lidar=lidar, **kwargs)


def choices_scores(model, pairs: dict, steps: int, depth_scale: float, perceptual) -> dict[str, dict[str, dict]]:
    """pair -> variant -> scores (``"model"``: the reconstruction refinement starts from)."""
    from drivingscene.bench.refine_scores import keyframe_psnr, scaled_depth
    from drivingscene.eval.reconstruction import score_depth, score_novel_views
    from drivingscene.methods.feedforward import reconstruct
    from drivingscene.methods.refine import refine

    out = {}
    for name, pair in pairs.items():
        base = scaled_depth(reconstruct(model, pair), pair, depth_scale)
        rows = {}
        for variant in ["model", *CHOICES]:
            recon = base if variant == "model" else refine(model, pair, base, variant_config(variant, steps))
            row = score_novel_views(recon, pair, perceptual)
            row.update(score_depth(recon, pair), keyframes_psnr=keyframe_psnr(recon, pair))
            row["steps"] = recon.meta.get("refinement", {}).get("steps", 0)
            rows[variant] = row
        out[name] = rows
    return out


def choices_report(scores: dict, lpips_name: str) -> str:
    from drivingscene.bench.refine_scores import _fmt, _mean

    names = list(scores)
    variants = list(next(iter(scores.values())))
    head = ["variant", "steps", "in-between PSNR", "change (dB)", lpips_name, "depth AbsRel", "keyframe re-render PSNR"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    base = _mean([scores[n]["default"] for n in names], "psnr")
    for v in variants:
        rows = [scores[n][v] for n in names]
        psnr = _mean(rows, "psnr")
        cells = [
            str(rows[0]["steps"]),
            _fmt(psnr, "{:.2f}"),
            _fmt(psnr - base, "{:+.2f}"),
            _fmt(_mean(rows, "lpips"), "{:.3f}"),
            _fmt(_mean(rows, "depth_abs_rel"), "{:.3f}"),
            _fmt(_mean(rows, "keyframes_psnr"), "{:.2f}"),
        ]
        lines.append("| " + " | ".join([v, *cells]) + " |")
    per = ["| pair | " + " | ".join(variants) + " |", "|" + "---|" * (len(variants) + 1)]
    per += [f"| {n} | " + " | ".join(_fmt(scores[n][v].get("psnr", math.nan), "{:.2f}") for v in variants) + " |" for n in names]
    return "\n".join(lines) + "\n\nIn-between PSNR per pair:\n\n" + "\n".join(per) + "\n"


def speed_rows(model, pair, steps: int = 4, threads_list=(1, 2), views_list=(1, 3, 6), scale_list=(1.0, 0.5)) -> list[dict]:
    """Seconds per step for views per step x image scale x threads on one pair."""
    from drivingscene.methods.feedforward import reconstruct
    from drivingscene.methods.refine import refine

    base = reconstruct(model, pair)
    rows = []
    for threads in threads_list:
        for views in views_list:
            for scale in scale_list:
                config = RefineConfig(
                    seconds=1e9,
                    max_steps=steps,
                    sweep=None,
                    adapt_steps=0,
                    views_per_step=views,
                    scales=((0.0, scale),),
                    threads=threads,
                )
                times = refine(model, pair, base, config).meta["refinement"]["step_times"][1:]
                rows.append({"threads": threads, "views": views, "scale": scale, "step_s": statistics.median(times)})
    sweep = []
    for threads in threads_list:
        config = RefineConfig(seconds=1e9, groups=(), adapt_steps=0, threads=threads)
        sweep.append({"threads": threads, "seconds": refine(model, pair, base, config).meta["refinement"]["sweep"]["seconds"]})
    return rows + [{"sweep": sweep, "gaussians": len(base.gaussians), "size": list(pair.image_size)}]


def speed_report(rows: list[dict]) -> str:
    info = rows[-1]
    height, width = info["size"]
    lines = ["| threads | views per step | image scale | s / step |", "|---|---|---|---|"]
    lines += [f"| {r['threads']} | {r['views']} | {r['scale']:g} | {r['step_s']:.2f} |" for r in rows[:-1]]
    sweep = ", ".join(f"{s['seconds']:.2f} s on {s['threads']} thread(s)" for s in info["sweep"])
    return (
        f"{info['gaussians']:,} Gaussians, {width}x{height} input views; the depth sweep: {sweep}.\n\n" + "\n".join(lines) + "\n"
    )
