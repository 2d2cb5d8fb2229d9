"""``drivingscene bench runtimes``: D's encoder and decoder (the networks' bulk) on other runtimes.

The shipped model's depth encoder and decoder on a batch of 12 images (one 6-camera pair) at the
networks' input size, timed as torch runs them in the reconstruction (channels-last), in the
default layout, under bf16 autocast where the CPU does bf16 natively (what the reconstruction
then runs), as a frozen TorchScript graph (``torch.jit.optimize_for_inference``: oneDNN
fusions), with ``--compile`` through ``torch.compile`` (inductor), where ``openvino`` is installed
(not a dependency) through OpenVINO's CPU plugin at float32 and, with native bf16, bf16 inference
precision, and where ``onnxruntime`` is installed (not a dependency) exported to ONNX and run by
ONNX Runtime's CPU provider with the same thread count. Also the one-off costs (tracing, export,
session) and the largest difference to torch's outputs. Prints a markdown table (``--out``).
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from drivingscene.arguments import positive_int
from drivingscene.data.atomic import atomic_write_text


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--runs", type=positive_int, default=5, help="timed runs per runtime after 2 warm-up runs (default 5)")
    p.add_argument("--threads", type=positive_int, default=2, help="threads for every runtime (default 2)")
    p.add_argument("--weights", type=Path, default=None, help="default: the shipped weights")
    p.add_argument(
        "--compile",
        action="store_true",
        help="also torch.compile (inductor, needs a C++ compiler; about 90 s to compile on 2 cores)",
    )
    p.add_argument("-o", "--out", type=Path, default=None, help="also write the markdown table here")


def _median_seconds(call, runs: int) -> float:
    call(), call()  # warm-up: oneDNN and ONNX Runtime build their kernels for the shape on first calls
    times = []
    for _ in range(runs):
        tic = time.perf_counter()
        call()
        times.append(time.perf_counter() - tic)
    return statistics.median(times)


def measure(weights: Path | None, runs: int, threads: int, compile_: bool = False) -> tuple[list[dict], tuple[int, ...]]:
    """One row per runtime: median seconds, one-off seconds, largest absolute output difference."""
    import torch

    from drivingscene.methods.feedforward import load_model
    from drivingscene.precision import auto_amp

    torch.set_num_threads(threads)
    bf16_native = auto_amp("cpu")  # what the reconstruction runs on this CPU (precision.py)
    model = load_model(weights).eval()
    depth_net = model.depth_net
    height, width = model.config.input_size or (176, 320)

    class EncoderDecoder(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.encoder, self.decoder = depth_net.encoder, depth_net.decoder

        def forward(self, x):
            feats = self.encoder(x)
            disps, decoded = self.decoder(feats, (height, width))
            return (*feats, *disps, decoded)

    net = EncoderDecoder().eval()
    channels = 5 if depth_net.config.road_prior else 3
    x = torch.rand(12, channels, height, width, generator=torch.Generator().manual_seed(0))
    rows = []
    with torch.no_grad():
        reference = [o.contiguous() for o in net(x)]

        def diff(outputs) -> float:
            return max(float((torch.as_tensor(o) - r).abs().max()) for o, r in zip(outputs, reference))

        x_last = x.contiguous(memory_format=torch.channels_last)
        seconds = _median_seconds(lambda: net(x_last), runs)
        rows.append(
            dict(
                runtime="torch, channels-last, float32 (the reconstruction's without native bf16)",
                s=seconds,
                once=0.0,
                diff=diff(net(x_last)),
            )
        )
        rows.append(dict(runtime="torch, default layout", s=_median_seconds(lambda: net(x), runs), once=0.0, diff=0.0))
        if bf16_native:

            def bf16():
                with torch.autocast("cpu", dtype=torch.bfloat16):
                    return net(x_last)

            rows.append(
                dict(
                    runtime="torch, channels-last, bf16 autocast (the reconstruction's on this CPU)",
                    s=_median_seconds(bf16, runs),
                    once=0.0,
                    diff=diff([o.float() for o in bf16()]),
                )
            )
        tic = time.perf_counter()
        frozen = torch.jit.optimize_for_inference(torch.jit.freeze(torch.jit.trace(net, x_last, check_trace=False).eval()))
        once = time.perf_counter() - tic
        seconds = _median_seconds(lambda: frozen(x_last), runs)
        rows.append(dict(runtime="TorchScript, frozen, optimize_for_inference", s=seconds, once=once, diff=diff(frozen(x_last))))
        if compile_:
            tic = time.perf_counter()
            compiled = torch.compile(net)
            compiled(x_last)  # compiles on the first call
            once = time.perf_counter() - tic
            seconds = _median_seconds(lambda: compiled(x_last), runs)
            rows.append(
                dict(runtime="torch.compile (inductor), channels-last", s=seconds, once=once, diff=diff(compiled(x_last)))
            )
    rows += _openvino_rows(net, x, runs, threads, diff, bf16_native)
    try:
        import onnxruntime
    except ImportError:
        rows.append(dict(runtime="ONNX Runtime (not installed: pip install onnxruntime onnx)", s=None, once=None, diff=None))
        return rows, tuple(x.shape)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "encoder_decoder.onnx"
        tic = time.perf_counter()
        torch.onnx.export(net, (x,), str(path), opset_version=17, dynamo=False, input_names=["x"])
        options = onnxruntime.SessionOptions()
        options.intra_op_num_threads, options.inter_op_num_threads = threads, 1
        options.graph_optimization_level = onnxruntime.GraphOptimizationLevel.ORT_ENABLE_ALL
        session = onnxruntime.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        once = time.perf_counter() - tic
        feed = {"x": x.numpy()}
        seconds = _median_seconds(lambda: session.run(None, feed), runs)
        rows.append(
            dict(
                runtime=f"ONNX Runtime {onnxruntime.__version__}, CPU provider, all graph optimisations",
                s=seconds,
                once=once,
                diff=diff(session.run(None, feed)),
            )
        )
    return rows, tuple(x.shape)


def _openvino_rows(net, x, runs: int, threads: int, diff, bf16: bool) -> list[dict]:
    """OpenVINO's CPU plugin on the model converted from torch, at float32 and, with ``bf16`` (the CPU
    does bf16 natively: AMX, AVX512_BF16), at its bf16 inference precision (not installed: one row)."""
    try:
        import openvino
    except ImportError:
        return [dict(runtime="OpenVINO (not installed: pip install openvino)", s=None, once=None, diff=None)]
    precisions = ["f32"] + (["bf16"] if bf16 else [])
    rows = []
    for precision in precisions:
        tic = time.perf_counter()
        model = openvino.convert_model(net, example_input=x)
        config = {"INFERENCE_PRECISION_HINT": precision, "INFERENCE_NUM_THREADS": threads, "PERFORMANCE_HINT": "LATENCY"}
        compiled = openvino.Core().compile_model(model, "CPU", config)
        request = compiled.create_infer_request()
        once = time.perf_counter() - tic
        feed = x.numpy()

        def infer():
            result = request.infer({0: feed})
            return [result[output] for output in compiled.outputs]

        rows.append(
            dict(
                runtime=f"OpenVINO {openvino.__version__.split('-')[0]}, CPU plugin, {precision} inference precision",
                s=_median_seconds(infer, runs),
                once=once,
                diff=diff(infer()),
            )
        )
    return rows


def run(args: argparse.Namespace) -> int:
    from drivingscene.machine import machine_description
    from drivingscene.precision import cpu_flags_summary

    rows, shape = measure(args.weights, args.runs, args.threads, args.compile)
    base = rows[0]["s"]
    lines = [
        f"Measured with `drivingscene bench runtimes --runs {args.runs} --threads {args.threads}{' --compile' if args.compile else ''}` on "
        f"{machine_description(cpu_flags_summary())}; D's encoder and decoder on a float32 batch {list(shape)} "
        f"(one pair's 12 images at the networks' input size), median of {args.runs} runs after 2 warm-up runs.",
        "",
        "| runtime | s (median) | against torch channels-last | one-off s (trace, export, session) | largest output difference |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        if r["s"] is None:
            lines.append(f"| {r['runtime']} | – | – | – | – |")
        else:
            lines.append(f"| {r['runtime']} | {r['s']:.3f} | {r['s'] / base:.2f}x | {r['once']:.1f} | {r['diff']:.1e} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        atomic_write_text(args.out, text)
    return 0
