"""``drivingscene bench inference``: seconds to reconstruct one 6-camera pair (networks + Gaussian
assembly), at several resolutions, with peak memory. The target is 176x320 in <= 0.5 s on 2 cores.

Peak memory is measured per size in a fresh process (the high-water mark of a process that has
reconstructed only that size), so that a size's figure does not depend on the sizes before it."""

from __future__ import annotations

import argparse
import multiprocessing
import statistics
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from drivingscene.arguments import Progress, add_list_argument
from drivingscene.data.atomic import atomic_write_text
from drivingscene.errors import InputError
from drivingscene.machine import current_rss_bytes, machine_description, peak_rss_bytes

SIZES = ("96x176", "176x320", "352x640")


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_list_argument(
        p,
        "--sizes",
        nargs="*",
        default=list(SIZES),
        metavar="HxW",
        help="procedural pairs generated at these sizes (none: only the --scenes, e.g. on a machine without EGL)",
    )
    p.add_argument(
        "--scenes",
        nargs="+",
        type=Path,
        default=[],
        metavar="SCENE",
        help="also time these scene files as they are (e.g. a real pair from `drivingscene import`: the matching's "
        "fallback runs where D's shape is off, so real frames may take longer than procedural ones)",
    )
    p.add_argument("--runs", type=int, default=5, help="timed runs per size (after 2 warm-up runs)")
    p.add_argument("--weights", type=Path, default=None, help="default: the shipped weights")
    p.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    from drivingscene.arguments import add_amp_arguments

    add_amp_arguments(p)  # default: bf16 autocast where the CPU/GPU does bf16 natively, else float32
    p.add_argument("--no-search", action="store_true", help="R's flow as it is (no search along the rigid flow)")
    p.add_argument("--no-objects", action="store_true", help="no object tracking (methods/object_motion.py)")
    p.add_argument(
        "--track-full-size",
        action="store_true",
        help="the object tracking at the image's size however wide (ObjectMotionConfig.max_width off: the path before "
        "2026-12-04); by default a pair wider than 320 is tracked downsampled",
    )
    p.add_argument(
        "--per-pixel", action="store_true", help="one Gaussian per pixel: flat blocks not merged (gaussians/parsimony.py)"
    )
    from drivingscene.arguments import add_match_arguments

    add_match_arguments(p)
    p.add_argument("--device", default="cpu", help="cpu (default), cuda or cuda:N")
    p.add_argument(
        "--profile",
        type=int,
        default=0,
        metavar="N",
        help="also list the N operations that take the most time in a reconstruction of each pair (torch profiler, "
        f"self CPU time, mean of {PROFILE_RUNS} reconstructions after the timed runs; the compiled kernels appear under "
        "their op names, those of drivingscene.kernels; OpenCV's matching is outside torch and does not appear)",
    )
    p.add_argument("-o", "--out", type=Path, default=None, help="also write the markdown table here")


WARMUP_RUNS = 2
PROFILE_RUNS = 3


def _pair(size: str):
    from drivingscene.arguments import parse_resolution
    from drivingscene.synth.config import SynthConfig
    from drivingscene.synth.generate import generate_pair

    height, width = parse_resolution(size)
    return generate_pair(SynthConfig(height=height, width=width), 200000)


def _options(amp: bool, threads: int, without: tuple[str, ...] = (), match: str = "fallback"):
    """Default inference options with the ``--match`` mode, less the steps named in ``without`` ("search",
    "objects", "merge"; "downsampled_tracking": the tracking at the image's size)."""
    from drivingscene.methods.feedforward import InferenceOptions
    from drivingscene.methods.matched_depth import match_mode

    options = InferenceOptions(amp=amp, threads=threads, match=match_mode(match))
    if "downsampled_tracking" in without and options.objects is not None:
        options = replace(options, objects=replace(options.objects, max_width=None))
    return replace(options, **{step: None for step in without if step != "downsampled_tracking"})


def _peak_in_this_process(
    weights: Path | None, device: str, pair_path: str, amp: bool, threads: int, without: tuple[str, ...], match: str
) -> tuple[float, ...]:
    """MiB the process's resident memory peaks above where it stood with the model and the pair
    loaded, over one reconstruction, and the process's whole peak (run in a fresh process by
    `peak_memory_mib`); on a GPU also the GPU memory torch allocated at its peak above the loaded
    model, and in all."""
    import torch

    from drivingscene.data.frame_pair import load_frame_pair
    from drivingscene.methods.devices import resolve_device
    from drivingscene.methods.feedforward import load_model, reconstruct

    torch.set_num_threads(threads)
    device = resolve_device(device)
    model = load_model(weights, device=device)
    pair = load_frame_pair(pair_path)
    base = current_rss_bytes()
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
        gpu_base = torch.cuda.memory_allocated(device)
    reconstruct(model, pair, _options(amp, threads, without, match))
    peak = peak_rss_bytes()
    if device.type != "cuda":
        return (peak - base) / 2**20, peak / 2**20
    gpu = torch.cuda.max_memory_allocated(device)
    return (peak - base) / 2**20, peak / 2**20, (gpu - gpu_base) / 2**20, gpu / 2**20


def peak_memory_mib(
    pair, weights: Path | None, device: str, amp: bool, threads: int, without: tuple[str, ...] = (), match: str = "fallback"
) -> tuple[float, ...]:
    """Peak resident memory (MiB) of one reconstruction of ``pair`` above the loaded model and
    pair, and of the whole process (and on a GPU the same two of its memory), in a fresh process (spawned, so it inherits none of this
    process's memory)."""
    from drivingscene.data.frame_pair import save_frame_pair

    with tempfile.TemporaryDirectory() as tmp:
        path = str(save_frame_pair(pair, Path(tmp) / "pair.npz", compress=False))
        with multiprocessing.get_context("spawn").Pool(1) as pool:
            return pool.apply(_peak_in_this_process, (weights, device, path, amp, threads, without, match))


def profile_ops(model, pair, options, top: int, runs: int = PROFILE_RUNS) -> list[dict]:
    """The ``top`` operations by self CPU time in ``runs`` reconstructions of ``pair`` (torch
    profiler, grouped by operation and input shapes): name, shapes, milliseconds and calls per
    reconstruction. The profiler's own overhead inflates the small operations a little."""
    from torch.profiler import ProfilerActivity, profile

    from drivingscene.methods.feedforward import reconstruct

    with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
        for _ in range(runs):
            reconstruct(model, pair, options)
    events = sorted(prof.key_averages(group_by_input_shape=True), key=lambda e: -e.self_cpu_time_total)
    return [
        dict(op=e.key, shapes=_shapes(e.input_shapes), ms=e.self_cpu_time_total / 1e3 / runs, calls=e.count / runs)
        for e in events[:top]
    ]


def _shapes(shapes) -> str:
    """The tensor inputs' shapes of a profiled operation, e.g. ``12x36x98x178, 16x36x3x3``."""
    tensors = [shape for shape in shapes or [] if shape and all(isinstance(n, int) for n in shape)]  # not scalars or lists
    return ", ".join("x".join(str(n) for n in shape) for shape in tensors)


def measure(
    model,
    sizes: list[str],
    runs: int,
    amp: bool,
    threads: int,
    without: tuple[str, ...] = (),
    weights: Path | None = None,
    device: str = "cpu",
    scenes: list[Path] = (),
    match: str = "fallback",
    progress=lambda fraction, message: None,
    profile: int = 0,
) -> list[dict]:
    """One row per size (a generated procedural pair) and per scene file. The timed runs go round
    the pairs in turn, so that a shared machine's slow spells fall on every pair alike, after each
    pair's warm-up; each pair's peak memory comes from a fresh process (`peak_memory_mib`, before
    any timing). ``progress(fraction, message)`` hears of each step (``arguments.Progress``)."""
    from drivingscene.data.frame_pair import load_frame_pair
    from drivingscene.methods.feedforward import reconstruct

    options = _options(amp, threads, without, match)
    progress(0.0, f"generating the procedural pairs ({', '.join(sizes)})")
    pairs = {size: _pair(size) for size in sizes}
    for path in scenes:
        pair = load_frame_pair(path)
        pairs[f"{path.name} ({pair.num_views} × {pair.image_size[0]}x{pair.image_size[1]})"] = pair
    sizes = list(pairs)
    peak = {}
    for size in sizes:
        progress(0.0, f"peak memory of {size} in a fresh process")
        peak[size] = peak_memory_mib(pairs[size], weights, device, amp, threads, without, match)
    totals, parts, count = {s: [] for s in sizes}, {s: [] for s in sizes}, {}
    for size in sizes:
        progress(0.0, f"{WARMUP_RUNS} warm-up runs of {size}")
        for _ in range(WARMUP_RUNS):  # oneDNN builds its kernels for each new shape on the first calls
            recon = reconstruct(model, pairs[size], options)
        count[size] = len(recon.gaussians)
    for run in range(runs):
        for k, size in enumerate(sizes):
            progress((run * len(sizes) + k) / (runs * len(sizes)), f"run {run + 1}/{runs} of {size}")
            tic = time.perf_counter()
            recon = reconstruct(model, pairs[size], options)
            totals[size].append(time.perf_counter() - tic)
            parts[size].append(recon.meta["timings"])
    ops = {}
    for size in sizes if profile > 0 else ():
        progress(1.0, f"profiling {size}")
        ops[size] = profile_ops(model, pairs[size], options, profile)
    rows = []
    for size in sizes:
        part = {k: statistics.median(p[k] for p in parts[size]) for k in parts[size][0]}
        part.setdefault("search_s", 0.0)
        part.setdefault("match_s", 0.0)
        part.setdefault("match_views", 0.0)
        rows.append(
            dict(
                size=size,
                median=statistics.median(totals[size]),
                best=min(totals[size]),
                gaussians=count[size],
                peak_mib=peak[size],
                ops=ops.get(size, []),
                **part,
            )
        )
    return rows


def run(args: argparse.Namespace) -> int:
    import torch

    from drivingscene.methods.devices import gpu_name, resolve_device
    from drivingscene.methods.feedforward import load_model

    if not args.sizes and not args.scenes:
        raise InputError("bench inference: nothing to time: give --sizes HxW ... or --scenes FILE ...")
    device = resolve_device(args.device)
    torch.set_num_threads(args.threads)
    model = load_model(args.weights, device=device)
    from drivingscene.precision import cpu_flags_summary, describe_precision, resolve_amp

    amp = resolve_amp(args.amp, device)  # once, so the spawned processes of the memory figures use the same
    without = tuple(
        step
        for step, off in (
            ("search", args.no_search),
            ("objects", args.no_objects),
            ("merge", args.per_pixel),
            ("downsampled_tracking", args.track_full_size),
        )
        if off
    )
    with Progress("drivingscene bench inference") as progress:  # on stderr once it takes more than a second
        rows = measure(
            model,
            args.sizes,
            args.runs,
            amp,
            args.threads,
            without,
            args.weights,
            args.device,
            args.scenes,
            args.match,
            progress,
            args.profile,
        )
    from drivingscene.kernels import load_extension

    kernels = "on" if load_extension() else "off: torch paths"
    if device.type != "cpu":
        kernels = f"{kernels} for the assembly, which runs on the CPU (the networks and the flow search on the GPU as torch paths; OpenCV's matching and tracking on the CPU)"
    lines = [
        f"Measured with `drivingscene bench inference --sizes {' '.join(args.sizes)}"
        f"{' --scenes ' + ' '.join(str(p) for p in args.scenes) if args.scenes else ''} --runs {args.runs}"
        f"{'' if device.type == 'cpu' else ' --device ' + args.device}{' --no-search' if args.no_search else ''}"
        f"{' --no-objects' if args.no_objects else ''}{' --per-pixel' if args.per_pixel else ''}"
        f"{' --track-full-size' if args.track_full_size else ''}"
        f"{'' if args.match == 'fallback' else ' --match ' + args.match}"
        f"{'' if args.amp is None else (' --amp' if args.amp else ' --no-amp')}"
        f"{' --profile ' + str(args.profile) if args.profile else ''}`"
        f" on {machine_description(cpu_flags_summary())}"
        f"{gpu_name(device)}; precision: {describe_precision(device, args.amp)}; compiled CPU kernels {kernels}; "
        f"median of {args.runs} runs per size, taken in turn across the sizes after {WARMUP_RUNS} warm-up runs each; "
        "peak RSS: one reconstruction in a fresh process, above its memory with the model and the pair loaded "
        "/ that process's whole peak.",
        "",
        "| pair (H×W) | total s (median) | best s | networks D+P s | matching s (cameras matched again) "
        "| flow (rigid + R + search + lift) s | of which search s | assembly + sky s | Gaussians | peak RSS: reconstruction / process |"
        + (" peak GPU memory: reconstruction / process |" if device.type == "cuda" else ""),
        "|---|---|---|---|---|---|---|---|---|---|" + ("---|" if device.type == "cuda" else ""),
    ]
    for r in rows:
        lines.append(
            f"| {r['size']} | {r['median']:.3f} | {r['best']:.3f} | {r['static_s']:.3f} | {r['match_s']:.3f} ({r['match_views']:.0f}) "
            f"| {r['flow_s']:.3f} "
            f"| {r['search_s']:.3f} | "
            f"{r['assembly_s']:.3f} | {r['gaussians'] / 1e3:.0f}k | {r['peak_mib'][0]:.0f} / {r['peak_mib'][1]:.0f} MiB |"
            + (f" {r['peak_mib'][2]:.0f} / {r['peak_mib'][3]:.0f} MiB |" if len(r["peak_mib"]) > 2 else "")
        )
    for r in rows:
        if r["ops"]:
            lines += [
                "",
                f"Where the time of {r['size']} goes: the {len(r['ops'])} operations with the most self CPU time per "
                f"reconstruction (torch profiler, mean of {PROFILE_RUNS}, after the timed runs):",
                "",
                "| operation | input shapes | ms | calls |",
                "|---|---|---|---|",
                *(f"| {o['op']} | {o['shapes']} | {o['ms']:.2f} | {o['calls']:.0f} |" for o in r["ops"]),
            ]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        atomic_write_text(args.out, text)
    return 0
