"""The stability sweeps of ``drivingscene bench report``: generator knobs moved one at a time.

Each axis is one `SynthConfig` knob swept from its easiest setting on the same test seeds, every
other knob at the default preset. A method breaks on an axis where its in-between PSNR falls more
than `report_schema.BREAK_DB` below its easiest setting, is NaN, or where it raises (recorded, not
fatal). A dead camera's own in-between images are black too and are not scored: what is tested is
whether its black inputs spoil the other cameras' views.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass, replace

from drivingscene.bench.report_schema import breaks_at


@dataclass(frozen=True)
class Axis:
    name: str
    knob: str  # SynthConfig field
    values: tuple
    easiest: int  # index into values
    unit: str = ""


# What each method's curve holds per setting: the in-between PSNR over the pixels that see the
# world and over the moving ones, depth AbsRel, the error a setting raised.
FIELDS = ("psnr", "abs_rel", "error", "psnr_dyn")
AXES = (
    Axis("object speed", "object_speed_scale", (0.0, 1.0, 2.0, 4.0), 0, "x"),
    Axis("ego speed", "ego_speed", (0.0, 4.0, 8.0, 16.0, 24.0), 0, "m/s"),
    Axis("keyframe gap", "keyframe_gap", (0.1, 0.25, 0.5, 1.0), 0, "s"),
    Axis("texture", "texture_strength", (1.0, 0.5, 0.25, 0.0), 0, "x"),
    Axis("exposure change", "exposure_change", (1.0, 1.25, 1.5, 2.0), 0, "gain"),
    Axis("image noise", "noise_std", (0.0, 0.02, 0.05, 0.1), 0, "std"),
    Axis("dead camera", "blackout_camera", ("none", "0"), 0),
    Axis("rig", "rig", ("nuscenes", "ddad", "random"), 0),
    Axis("photometric jitter", "photometric", (0.0, 0.5, 1.0), 0),
)


def _axis_config(axis: Axis, value, size: tuple[int, int]):
    from drivingscene.synth.config import resolve_config

    height, width = size
    return resolve_config("default", height=height, width=width, **{axis.knob: value})


def _live_cameras(pair, axis: Axis, value):
    """The pair to score on: with a dead camera, its in-between images (black as well) are not
    scored; what is tested is whether its black inputs spoil the other cameras' views."""
    if axis.knob != "blackout_camera" or value == "none":
        return pair
    names = list(pair.camera_names)
    dead = names.index(value) if value in names else int(value)
    mask = pair.world_mask().copy()
    mask[dead] = False
    return replace(pair, valid_mask=mask)


def stability(methods: list, size: tuple[int, int], seeds: int, ends_only: bool = False) -> list[dict]:
    """Each axis swept on the first ``seeds`` test seeds at ``size`` (H, W); in-between PSNR and depth
    AbsRel (methods that reconstruct) per method (`report.Method`) and setting, mean over the seeds. ``ends_only``: the easiest and the hardest setting."""
    from drivingscene.eval.reconstruction import score_depth, score_frames, score_novel_views
    from drivingscene.synth.config import split_seeds
    from drivingscene.synth.generate import generate_pair
    from drivingscene.synth.render import SynthRenderer

    renderer = SynthRenderer()
    seed_list = list(split_seeds("test", seeds))
    out = []
    # Settings that make the same generator config (most axes' easiest value is the default preset's)
    # are run once: (config, method) -> (PSNR, AbsRel, error).
    done: dict[tuple[str, str], tuple] = {}
    for axis in AXES:
        values = (axis.values[axis.easiest], axis.values[-1]) if ends_only else axis.values
        curves = {m.name: {field: [] for field in FIELDS} for m in methods}
        for value in values:
            config = _axis_config(axis, value, size)
            scored_without = axis.knob == "blackout_camera" and value != "none"  # `_live_cameras`
            key = repr(config) + (f" scored without camera {value}" if scored_without else "")
            if all((key, m.name) in done for m in methods):
                for m in methods:
                    for field, result in zip(FIELDS, done[key, m.name]):
                        curves[m.name][field].append(result)
                continue
            pairs = [generate_pair(config, s, renderer) for s in seed_list]
            for m in methods:
                scores, moving, depths, error = [], [], [], None
                for pair in pairs:
                    target = _live_cameras(pair, axis, value)
                    try:
                        result = m.run(pair)
                        frame = score_frames(result, target, None) if m.frames else score_novel_views(result, target, None)
                        scores.append(frame["psnr"])
                        moving.append(frame.get("psnr_dyn", math.nan))
                        if not m.frames and result.depth is not None and pair.gt_depth is not None:
                            depths.append(score_depth(result, pair)["depth_abs_rel"])
                    except Exception as e:  # a method that raises breaks here: recorded, not fatal
                        error = f"{type(e).__name__}: {e}"[:200]
                        break
                value_psnr = (
                    None if error or not scores or not all(math.isfinite(s) for s in scores) else sum(scores) / len(scores)
                )
                curves[m.name]["psnr"].append(value_psnr)
                # depth AbsRel at the keyframes (ego speed 0: no parallax over time, issue 45)
                finite = [d for d in depths if math.isfinite(d)]
                curves[m.name]["abs_rel"].append(sum(finite) / len(finite) if finite and not error else None)
                curves[m.name]["error"].append(error)
                # the moving pixels' PSNR (the object-speed axis: what the dynamics are for, issue 46)
                finite = [x for x in moving if math.isfinite(x)]
                curves[m.name]["psnr_dyn"].append(sum(finite) / len(finite) if finite and not error else None)
                done[key, m.name] = tuple(curves[m.name][field][-1] for field in FIELDS)
        easiest = 0
        breaks = {name: breaks_at(c["psnr"], c["error"], easiest) for name, c in curves.items()}
        out.append(
            {
                "name": axis.name,
                "knob": axis.knob,
                "unit": axis.unit,
                "values": list(values),
                "easiest": easiest,
                "curves": curves,
                "breaks": breaks,
            }
        )
        print(f"stability: {axis.name} done", file=sys.stderr)
    return out
