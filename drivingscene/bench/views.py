"""``drivingscene bench views``: quality where the viewer's user looks.

Every figure elsewhere scores views at a rig camera's own pose at the input's size; the viewer
draws the scene larger and from elsewhere. This benchmark renders every method from the viewpoints
a viewer's user takes (`views_cameras`: the rig pose, moved sideways or up, a bird's-eye-like view,
the viewer's default overview, the rig pose magnified 2x and 4x) at t = 0 and t = 0.5 and scores
them against the procedural generator's ground truth rendered at those poses and sizes
(`drivingscene.synth.novel_view`). Methods: the model, the oracle, the classical method, and a
textured depth-mesh baseline built from the model's depth (`drivingscene.methods.depth_mesh`); at
magnified sizes also the input upsampled bicubically. Real scenes (``--scenes``) have no ground
truth away from the rig: only the magnification rows against the input upsampled, and pictures of
the overview.

Writes ``DIR/views.md``, ``DIR/views.json`` and ``DIR/views_*.png`` (and ``DIR/real_overview_*.png``
with ``--scenes``; those show real frames).
"""

from __future__ import annotations

import argparse
import json
import re
import time
from dataclasses import dataclass, replace
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from drivingscene.arguments import parse_resolution, positive_int
from drivingscene.bench.views_cameras import CLASSES, OVERVIEW, RIG, SIDE_1, UP_10_DOWN
from drivingscene.bench.views_run import CLASSICAL, MESH, MODEL, ORACLE, PER_PIXEL, Plan
from drivingscene.errors import InputError

MESSAGE = "drivingscene bench views"
CHARTS = {"classes": "views_classes.png", "magnification": "views_magnification.png", "examples": "views_examples.png"}


@dataclass(frozen=True)
class Profile:
    count: int
    size: tuple[int, int]  # (H, W)
    plan: Plan


PROFILES = {
    "full": Profile(6, (176, 320), Plan(CLASSES, (0.0, 0.5), (2, 4), (720, 1280), 2)),
    "quick": Profile(1, (64, 112), Plan((RIG, SIDE_1, UP_10_DOWN, OVERVIEW), (0.0, 0.5), (2, 4), (126, 224), 2)),
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--quick",
        action="store_true",
        help="1 pair at 64x112, fewer viewpoints, a small overview: a smoke test (about a minute on 2 cores)",
    )
    p.add_argument("--count", type=positive_int, default=None, help="procedural test pairs (default 6; quick: 1)")
    p.add_argument(
        "--res",
        type=parse_resolution,
        default=None,
        metavar="HxW",
        help="procedural pairs' size (default 176x320; quick: 64x112)",
    )
    p.add_argument(
        "--scenes",
        type=Path,
        nargs="+",
        default=[],
        metavar="SCENE",
        help="real scenes (from `drivingscene import`): magnification rows and overview pictures",
    )
    p.add_argument("--weights", type=Path, default=None, help="model weights (default: the shipped ones)")
    # not "out": the bench runner checks --out as a file, this is a folder of several files
    p.add_argument(
        "-o",
        "--out",
        dest="out_dir",
        type=Path,
        required=True,
        metavar="DIR",
        help="folder for views.md, views.json and the charts",
    )


def _slug(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("_") or "scene"


def _outputs(args: argparse.Namespace) -> list[Path]:
    names = ["views.md", "views.json", *CHARTS.values()] + [f"real_overview_{_slug(s.stem)}.png" for s in args.scenes]
    return [args.out_dir / n for n in names]


def _check_outputs(args: argparse.Namespace) -> None:
    """Refuse to overwrite any of this run's files without --force (as the bench runner does for --out)."""
    if args.out_dir.exists() and not args.out_dir.is_dir():
        raise InputError(f"{args.out_dir}: --out exists and is not a folder")
    if not args.force:
        for path in _outputs(args):
            if path.exists():
                raise InputError(f"{path}: --out: exists; pass --force to overwrite it")


def _command(args: argparse.Namespace) -> str:
    parts = [MESSAGE] + (["--quick"] if args.quick else [])
    parts += [f"--count {args.count}"] if args.count else []
    parts += [f"--res {args.res[0]}x{args.res[1]}"] if args.res else []
    parts += ["--scenes " + " ".join(str(s) for s in args.scenes)] if args.scenes else []
    parts += [f"--weights {args.weights}"] if args.weights else []
    return " ".join(parts + [f"--out {args.out_dir}"])


def _reconstructions(model, pair, oracle: bool, per_pixel: bool = False) -> dict:
    from drivingscene.methods.classical import classical_reconstruction
    from drivingscene.methods.feedforward import InferenceOptions, reconstruct
    from drivingscene.methods.oracle import oracle_reconstruction

    recons = {MODEL: reconstruct(model, pair)}
    if per_pixel:  # the parsimony ablation: one Gaussian per pixel and keyframe (gaussians/parsimony.py)
        recons[PER_PIXEL] = reconstruct(model, pair, replace(InferenceOptions(), merge=None, dedupe=None))
    if oracle:
        recons[ORACLE] = oracle_reconstruction(pair)
    recons[CLASSICAL] = classical_reconstruction(pair)
    return recons


def _methods(recons: dict, mesh) -> dict:
    from drivingscene.bench.views_run import gaussian_method, mesh_method

    out = {MODEL: gaussian_method(recons[MODEL]), MESH: mesh_method(mesh)}
    out.update({name: gaussian_method(r) for name, r in recons.items() if name != MODEL})
    return out


def _procedural(args, profile: Profile, model, renderer, perceptual, progress, results) -> str:
    from drivingscene.bench.views_run import flying_of, score_procedural
    from drivingscene.methods.depth_mesh import DepthMeshRenderer
    from drivingscene.synth.config import resolve_config, split_seeds
    from drivingscene.synth.generate import generate_pair
    from drivingscene.synth.novel_view import ProceduralScene

    height, width = args.res or profile.size
    config = resolve_config("default", height=height, width=width)
    seeds = split_seeds("test", args.count or profile.count)
    for i, seed in enumerate(seeds):
        progress(i / len(seeds), f"procedural pair {i + 1}/{len(seeds)} (seed {seed})")
        pair = generate_pair(config, seed, renderer)
        recons = _reconstructions(model, pair, oracle=True, per_pixel=not args.quick)
        mesh = DepthMeshRenderer(recons[MODEL], renderer.ctx, capture_ego_to_world=pair.camera_ego_poses())
        try:
            with ProceduralScene(config, seed, renderer) as truth:
                got = score_procedural(pair, str(seed), truth, _methods(recons, mesh), profile.plan, perceptual, examples=i == 0)
        finally:
            mesh.release()
        results["records"] += got.records
        results["flying"].setdefault("procedural", {})[str(seed)] = flying_of(recons, pair.gt_depth)
        if i == 0:
            results["examples"] = got.examples
    count = f"{len(seeds)} pair" + ("s" if len(seeds) > 1 else "")
    return f"test split seeds {seeds[0]}-{seeds[-1]}, default preset, {count}, {width}x{height}"


def _real(args, pairs: list, profile: Profile, model, renderer, perceptual, progress, results) -> None:
    from drivingscene.bench.views_charts import overview_picture
    from drivingscene.bench.views_run import flying_of, score_real
    from drivingscene.methods.depth_mesh import DepthMeshRenderer

    for path, pair in zip(args.scenes, pairs):
        progress(None, f"real scene {path.name}")
        name = path.stem
        recons = _reconstructions(model, pair, oracle=False, per_pixel=not args.quick)
        mesh = DepthMeshRenderer(recons[MODEL], renderer.ctx, capture_ego_to_world=pair.camera_ego_poses())
        try:
            got, pictures = score_real(pair, name, recons[MODEL], _methods(recons, mesh), profile.plan, perceptual)
        finally:
            mesh.release()
        results["records"] += got.records
        results["flying"].setdefault("real", {})[name] = flying_of(recons, pair.gt_depth)  # LiDAR returns
        picture = args.out_dir / f"real_overview_{_slug(name)}.png"
        overview_picture(
            pair.images[0, 0].astype(np.float32) / 255.0, pictures, picture, f"{name}: the viewer's default overview at t = 0"
        )
        results["pictures"][name] = picture.name


def run(args: argparse.Namespace) -> int:
    import torch

    from drivingscene.arguments import Progress
    from drivingscene.bench.views_charts import classes_chart, examples_chart, magnification_chart
    from drivingscene.bench.views_report import build_report, markdown
    from drivingscene.data.atomic import atomic_write_text
    from drivingscene.data.frame_pair import load_frame_pair
    from drivingscene.eval.lpips import load_perceptual
    from drivingscene.machine import machine_description
    from drivingscene.methods.depth_mesh import MAX_GRAZING_DEG
    from drivingscene.methods.feedforward import load_model
    from drivingscene.precision import describe_precision
    from drivingscene.synth.render import SynthRenderer

    start = time.perf_counter()
    _check_outputs(args)
    real_pairs = [load_frame_pair(p) for p in args.scenes]  # every file checked before the long part
    profile = PROFILES["quick" if args.quick else "full"]
    args.out_dir.mkdir(parents=True, exist_ok=True)
    model = load_model(args.weights)
    perceptual = load_perceptual("stlpips")
    renderer = SynthRenderer()
    results = {"records": [], "flying": {}, "examples": {}, "pictures": {}}
    with Progress(MESSAGE) as progress:
        procedural = _procedural(args, profile, model, renderer, perceptual, progress, results)
        _real(args, real_pairs, profile, model, renderer, perceptual, progress, results)
        progress(1.0, "writing the report")
    plan = profile.plan
    meta = {
        "command": _command(args),
        "machine": machine_description(),
        "precision": describe_precision(torch.device("cpu")),
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "quick": bool(args.quick),
        "settings": {
            "procedural": procedural,
            "real": ", ".join(s.stem for s in args.scenes) + (f", {len(args.scenes)} scenes" if len(args.scenes) > 1 else ""),
            "real_names": [s.stem for s in args.scenes],
            "classes": list(plan.classes),
            "times": list(plan.times),
            "magnifications": [1, *plan.magnifications],
            "overview_size": list(plan.overview_size),
            "side": "both ways (+y, left, and -y, right) for every camera",
            "mesh_max_angle_deg": MAX_GRAZING_DEG,
            "perceptual": perceptual.name,
            "lpips_note": f"ST-LPIPS is computed up to {plan.lpips_max_magnification}x magnification (and on the overview); "
            f"at larger magnifications it is left out (CPU time): –.",
        },
        "real_pictures": results["pictures"],
    }
    report = build_report(results["records"], results["flying"], meta)
    report["run_seconds"] = time.perf_counter() - start
    charts = {}
    for key, draw in (("classes", classes_chart), ("magnification", magnification_chart)):
        if draw(report, args.out_dir / CHARTS[key]) is not None:
            charts[key] = CHARTS[key]
    caption = "The first procedural pair's camera 0 from every viewpoint at t = 0 (side: moved left)"
    if examples_chart(results["examples"], args.out_dir / CHARTS["examples"], caption) is not None:
        charts["examples"] = CHARTS["examples"]
    report["run_seconds"] = time.perf_counter() - start
    atomic_write_text(args.out_dir / "views.json", json.dumps(report, indent=1, allow_nan=False))
    atomic_write_text(args.out_dir / "views.md", markdown(report, charts))
    print(f"{args.out_dir / 'views.md'}: written")
    return 0
