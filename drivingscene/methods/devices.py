"""Where the reconstruction runs: ``--device`` parsed, a GPU waited for, and a GPU's results
handed to the CPU for the steps that have only compiled CPU kernels (the assembly)."""

from __future__ import annotations

from dataclasses import fields, is_dataclass, replace

import torch

from drivingscene.errors import InputError


def resolve_device(name: str) -> torch.device:
    """``cpu``, ``cuda`` or ``cuda:N``; a one-line error when the GPU is not there."""
    try:
        device = torch.device(name)
    except RuntimeError:
        raise InputError(f"--device: expected cpu, cuda or cuda:N, found {name!r}") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise InputError(f"--device {name}: torch {torch.__version__} sees no CUDA GPU; use --device cpu")
    if device.type not in ("cpu", "cuda"):
        raise InputError(f"--device: expected cpu, cuda or cuda:N, found {name!r}")
    return device


def on_cpu(value):
    """``value`` (tensors, dataclasses of them, lists, tuples, dicts, None) with every tensor on the CPU."""
    if isinstance(value, torch.Tensor) or is_dataclass(value) and hasattr(value, "to"):  # PairTensors.to
        return value.to("cpu")
    if is_dataclass(value):
        return replace(value, **{f.name: on_cpu(getattr(value, f.name)) for f in fields(value) if f.init})
    if isinstance(value, (list, tuple)):
        return type(value)(on_cpu(v) for v in value)
    if isinstance(value, dict):
        return {k: on_cpu(v) for k, v in value.items()}
    return value


def sync(device: torch.device) -> None:
    """Wait for the GPU's queued work (a timing's end), nothing on the CPU."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def gpu_name(device: torch.device) -> str:
    """``", GPU <name>"`` for a benchmark's machine line where ``device`` is a GPU, else ``""``."""
    return "" if device.type != "cuda" else f", GPU {torch.cuda.get_device_name(device)}"
