"""Atomic checkpoints: weights (and optimiser state) in safetensors, everything else in JSON.

A checkpoint is ``step_XXXXXXX.safetensors`` plus its ``step_XXXXXXX.json`` (step, optimiser
scalars, and the SHA-256 and byte size of the weights file), and ``latest.json`` (a copy of the
newest one's JSON); every file is written atomically and ``latest.json`` last, so a run killed
mid-save resumes from the previous complete checkpoint. On resume each candidate, newest first, is
checked against its recorded size and hash: a truncated or corrupted one is skipped with a warning
and the one before it is used, so at least two checkpoints are kept. Nothing is pickled.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from pathlib import Path

import torch
from safetensors.torch import load as load_bytes

from drivingscene.data.npz import atomic_write
from drivingscene.errors import InputError

log = logging.getLogger(__name__)
LATEST = "latest.json"
MIN_KEEP = 2  # the newest may be damaged; the one before it is the fallback


def _optimizer_tensors(optimizer: torch.optim.Optimizer) -> tuple[dict[str, torch.Tensor], dict]:
    state = optimizer.state_dict()
    tensors = {}
    scalars: dict = {"param_groups": state["param_groups"], "state": {}}
    for idx, entry in state["state"].items():
        for name, value in entry.items():
            if torch.is_tensor(value):
                tensors[f"optim.{idx}.{name}"] = value.contiguous()
            else:
                scalars["state"].setdefault(str(idx), {})[name] = value
    return tensors, scalars


def _restore_optimizer(optimizer: torch.optim.Optimizer, tensors: dict[str, torch.Tensor], scalars: dict) -> None:
    state: dict = {}
    for key, value in tensors.items():
        if key.startswith("optim."):
            _, idx, name = key.split(".", 2)
            state.setdefault(int(idx), {})[name] = value
    for idx, entry in scalars.get("state", {}).items():
        state.setdefault(int(idx), {}).update(entry)
    optimizer.load_state_dict({"state": state, "param_groups": scalars["param_groups"]})


def save_checkpoint(out_dir: Path, step: int, model: torch.nn.Module, optimizer, info: dict, keep: int = 2) -> Path:
    out_dir.mkdir(parents=True, exist_ok=True)
    name = f"step_{step:07d}.safetensors"
    tensors = {f"model.{k}": v.detach().contiguous() for k, v in model.state_dict().items()}
    optim_scalars = {}
    if optimizer is not None:
        opt_tensors, optim_scalars = _optimizer_tensors(optimizer)
        tensors.update(opt_tensors)
    tensors["rng.torch"] = torch.get_rng_state()
    data = _safetensors_bytes(tensors)
    atomic_write(out_dir / name, lambda f: f.write(data))
    meta = {
        "step": step,
        "weights": name,
        "bytes": len(data),
        "sha256": hashlib.sha256(data).hexdigest(),
        "optimizer": optim_scalars,
        **info,
    }
    text = json.dumps(meta, indent=1, sort_keys=True).encode()
    atomic_write((out_dir / name).with_suffix(".json"), lambda f: f.write(text))
    atomic_write(out_dir / LATEST, lambda f: f.write(text))
    for old in sorted(out_dir.glob("step_*.safetensors"))[: -max(keep, MIN_KEEP)]:
        old.unlink()
        old.with_suffix(".json").unlink(missing_ok=True)
    return out_dir / name


def _safetensors_bytes(tensors: dict[str, torch.Tensor]) -> bytes:
    from safetensors.torch import save

    return save(tensors)


def _verified(out_dir: Path, record: Path) -> tuple[dict, dict[str, torch.Tensor]]:
    """(meta, tensors) of the checkpoint ``record`` describes, after checking the weights' size and
    SHA-256 (when recorded: checkpoints from before the check have none)."""
    meta = json.loads(record.read_text())
    data = (out_dir / meta["weights"]).read_bytes()
    if "bytes" in meta and len(data) != meta["bytes"]:
        raise ValueError(f"{meta['weights']} has {len(data)} bytes, expected {meta['bytes']} (truncated?)")
    if "sha256" in meta and hashlib.sha256(data).hexdigest() != meta["sha256"]:
        raise ValueError(f"{meta['weights']}: SHA-256 differs from the recorded one (corrupted)")
    return meta, load_bytes(data)


def load_checkpoint(out_dir: Path) -> tuple[dict, dict[str, torch.Tensor]] | None:
    """(meta, tensors) of the newest intact checkpoint in ``out_dir``, or None when there is none.

    ``latest.json`` first, then the kept ``step_*.json`` newest first; a damaged one is skipped
    with a warning. Raises InputError when checkpoints are there but none is intact."""
    latest = out_dir / LATEST
    if not latest.exists():
        return None
    records = [latest, *sorted(out_dir.glob("step_*.json"), reverse=True)]
    problems = []
    for record in records:
        try:
            meta, tensors = _verified(out_dir, record)
        except (OSError, ValueError, KeyError, TypeError) as e:
            problems.append(f"{record.name}: {e}")
            log.warning("%s: checkpoint not usable, trying the previous one: %s", record, e)
            continue
        if record != latest and problems:
            log.warning("%s: resuming from the previous intact checkpoint, step %d", out_dir, int(meta["step"]))
        return meta, tensors
    raise InputError(f"{latest}: expected a complete checkpoint, none is intact: {'; '.join(problems)}")


def restore(model: torch.nn.Module, optimizer, meta: dict, tensors: dict[str, torch.Tensor]) -> int:
    model.load_state_dict({k[len("model.") :]: v for k, v in tensors.items() if k.startswith("model.")})
    if optimizer is not None and meta.get("optimizer"):
        _restore_optimizer(optimizer, tensors, meta["optimizer"])
    if "rng.torch" in tensors:
        torch.set_rng_state(tensors["rng.torch"])
    return int(meta["step"])


def export_weights(model: torch.nn.Module, config_dict: dict, path: str | os.PathLike, info: dict, half: bool = False) -> Path:
    """Ship-ready weights: ``NAME.safetensors`` (model only) and ``NAME.json`` (config + info).

    ``half`` stores floating tensors as float16 (half the size; they load back into float32)."""
    path = Path(path)
    tensors = {k: v.detach().contiguous() for k, v in model.state_dict().items()}
    if half:
        tensors = {k: v.half() if v.is_floating_point() else v for k, v in tensors.items()}
    atomic_write(path, lambda f: f.write(_safetensors_bytes(tensors)))
    meta = {"model": config_dict, **info, "dtype": "float16" if half else "float32"}
    atomic_write(path.with_suffix(".json"), lambda f: f.write(json.dumps(meta, indent=1, sort_keys=True).encode()))
    return path


__all__ = ["export_weights", "load_checkpoint", "restore", "save_checkpoint"]


def model_from_run(run_dir: Path):
    """The model of a run's latest checkpoint and its info (for shipping an unfinished run)."""
    from drivingscene.models.model import DrivingSceneModel
    from drivingscene.train.config import TrainConfig

    loaded = load_checkpoint(run_dir)
    if loaded is None:
        raise InputError(f"{run_dir}: expected a training run folder with latest.json")
    meta, tensors = loaded
    from drivingscene.train.data import list_pairs, with_data_size

    config = TrainConfig.from_dict(json.loads((run_dir / "config.json").read_text()))
    if config.model.input_size is None:  # runs started before the size was recorded
        config = with_data_size(config, list_pairs(config.data))
    model = DrivingSceneModel(config.model)
    restore(model, None, meta, tensors)
    info = {k: meta[k] for k in ("stage", "lpips", "world") if k in meta}
    return model, {**info, "steps": int(meta["step"])}
