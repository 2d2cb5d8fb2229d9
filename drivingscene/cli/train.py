"""``drivingscene train``: the two-stage (or joint) training of the model."""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

from drivingscene.arguments import add_amp_arguments, positive_int
from drivingscene.errors import InputError
from drivingscene.train.config import RENDER_VIEWS, STAGES


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "train",
        help="train the model: --stage static, then dynamic (or joint for the ablation); gaussians: P alone, depth: D alone, after them",
    )
    p.add_argument("--stage", choices=STAGES, required=True, help="which networks train (docs/training.md)")
    p.add_argument(
        "--data",
        type=Path,
        required=True,
        nargs="+",
        metavar="DIR",
        help="training pairs (drivingscene synth --split train); several folders: a mix",
    )
    p.add_argument(
        "--val-data",
        type=Path,
        default=None,
        nargs="+",
        metavar="DIR",
        help="validation pairs (drivingscene synth --split val); several: interleaved",
    )
    p.add_argument(
        "-o", "--out", type=Path, required=True, metavar="DIR", help="run folder: checkpoints, log.jsonl, model.safetensors"
    )
    p.add_argument("--init", type=Path, default=None, metavar="WEIGHTS", help="start from these weights (stage 2: stage 1's)")
    p.add_argument("--steps", type=positive_int, default=None, help="gradient steps of the stage (default: the stage's)")
    p.add_argument("--lr", type=float, default=None, help="Adam learning rate (default 1e-4, the paper's)")
    p.add_argument("--flow-lr", type=float, default=None, help="learning rate of R, the residual flow network (default: --lr)")
    p.add_argument(
        "--flow-supervision",
        type=float,
        default=None,
        metavar="W",
        help="add W x L1 flow error against the pairs' ground-truth flow (synthetic pre-training of R; not in the paper)",
    )
    p.add_argument(
        "--search-supervision",
        type=float,
        default=None,
        metavar="W",
        help="add W x L1 error of R's flow against the search along the rigid flow where the search overrides R "
        "(self-supervised; not in the paper)",
    )
    p.add_argument(
        "--depth-supervision",
        type=float,
        default=None,
        metavar="W",
        help="add W x L1 log-depth error against the pairs' ground-truth depth (synthetic pre-training of D; not in the paper)",
    )
    p.add_argument("--seed", type=int, default=None, help="random seed of the data order and initialisation")
    p.add_argument("--threads", type=positive_int, default=None, help="torch threads per process")
    p.add_argument("--batch-pairs", type=positive_int, default=None, help="frame pairs per step and process (default 1)")
    p.add_argument("--render-every", type=positive_int, default=None, help="L_render on every n-th step")
    p.add_argument(
        "--render-views",
        nargs="+",
        choices=RENDER_VIEWS,
        default=None,
        help="L_render's targets, in turn: the intermediate frame, the other keyframe from one keyframe's Gaussians, "
        "the input views from both (default: all three)",
    )
    p.add_argument(
        "--render-blend",
        choices=("layers", "all"),
        default=None,
        help="how L_render combines both keyframes' Gaussians (default: layers, as inference)",
    )
    p.add_argument(
        "--input-jitter",
        type=float,
        default=None,
        metavar="STRENGTH",
        help="photometric jitter of D's input images at this strength in [0, 2] (the losses compare the originals; default 0)",
    )
    p.add_argument("--val-every", type=positive_int, default=None, help="validate every n-th step")
    p.add_argument("--ckpt-every", type=positive_int, default=None, help="write a checkpoint every n-th step")
    p.add_argument(
        "--lpips", choices=("auto", "lpips", "stlpips"), default=None, help="perceptual loss network (auto: the one installed)"
    )
    add_amp_arguments(p)  # --amp / --no-amp; default: bf16 autocast where the CPU does bf16 natively
    p.add_argument("--config", type=Path, default=None, help="JSON config to start from (e.g. a run's config.json)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
    register_ship(sub)


def register_ship(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("ship-weights", help="copy trained weights (+ JSON) for shipping, optionally as float16")
    p.add_argument(
        "source", type=Path, metavar="RUN_OR_WEIGHTS", help="a run folder (its latest checkpoint) or model.safetensors"
    )
    p.add_argument("dest", type=Path, nargs="?", metavar="OUT.safetensors", help="the weights to write (or -o OUT.safetensors)")
    p.add_argument("-o", "--out", type=Path, default=None, metavar="OUT.safetensors", help="the weights to write")
    p.add_argument("--float32", action="store_true", help="keep float32 (default: float16, half the size)")
    p.add_argument("--note", default="", help="text stored in the JSON (e.g. which runs it came from)")
    p.add_argument("--force", action="store_true", help="overwrite OUT.safetensors (and its JSON) if it exists")
    p.set_defaults(func=run_ship)


def run_ship(args: argparse.Namespace) -> int:
    from drivingscene.arguments import check_output
    from drivingscene.methods.feedforward import load_model
    from drivingscene.train.checkpoint import export_weights, model_from_run

    if (args.dest is None) == (args.out is None):
        raise InputError("-o/--out: expected the weights to write once, as -o OUT.safetensors (or the positional OUT)")
    args.dest = args.dest or args.out
    check_output(args.dest, args.force, "-o")
    if args.source.is_dir():
        model, info = model_from_run(args.source)
    else:
        model = load_model(args.source)
        meta = json.loads(args.source.with_suffix(".json").read_text())
        info = {k: v for k, v in meta.items() if k not in ("model", "dtype")}
    info["source"] = str(args.source)
    if args.note:
        info["note"] = args.note
    path = export_weights(model, model.config.to_dict(), args.dest, info, half=not args.float32)
    print(f"{path}: {path.stat().st_size / 1e6:.1f} MB")
    return 0


def run(args: argparse.Namespace) -> int:
    from drivingscene.train.config import TrainConfig
    from drivingscene.train.trainer import train

    base = TrainConfig()
    if args.resume and args.config is None and (args.out / "config.json").exists():
        args.config = args.out / "config.json"  # continue with the run's own settings unless overridden
    if args.config is not None:
        try:
            base = TrainConfig.from_dict(json.loads(args.config.read_text()))
        except (OSError, ValueError, TypeError) as e:
            raise InputError(f"{args.config}: --config: expected a training config JSON: {e}") from None
    for name, value in (("--lr", args.lr), ("--flow-lr", args.flow_lr)):
        if value is not None and not value > 0:
            raise InputError(f"{name}: expected a positive learning rate, found {value}")
    if args.input_jitter is not None and not 0.0 <= args.input_jitter <= 2.0:
        raise InputError(f"--input-jitter: expected a strength in [0, 2], found {args.input_jitter}")
    for flag, field, value in (
        ("--flow-supervision", "flow_sup", args.flow_supervision),
        ("--depth-supervision", "depth_sup", args.depth_supervision),
        ("--search-supervision", "search_sup", args.search_supervision),
    ):
        if value is not None:
            if not value >= 0:
                raise InputError(f"{flag}: expected a weight >= 0, found {value}")
            base = replace(base, weights=replace(base.weights, **{field: value}))
    config = base.with_overrides(
        stage=args.stage,
        data=",".join(str(d) for d in args.data),
        val_data=",".join(str(d) for d in args.val_data) if args.val_data else None,
        out=str(args.out),
        init=str(args.init) if args.init else None,
        steps=args.steps,
        lr=args.lr,
        flow_lr=args.flow_lr,
        seed=args.seed,
        threads=args.threads,
        batch_pairs=args.batch_pairs,
        render_every=args.render_every,
        render_views=tuple(args.render_views) if args.render_views else None,
        render_blend=args.render_blend,
        input_jitter=args.input_jitter,
        val_every=args.val_every,
        ckpt_every=args.ckpt_every,
        lpips=args.lpips,
        amp=args.amp,
    )
    path = train(config, resume=args.resume, show_progress=not args.no_progress)
    print(f"weights: {path}")
    return 0
