"""The training loop: seeded, resumable, optionally distributed (torchrun, gloo on CPU).

    drivingscene train --stage static  --data DIR --out runs/static
    drivingscene train --stage dynamic --data DIR --out runs/dynamic --init runs/static/model.safetensors
    torchrun --nproc-per-node 2 -m drivingscene train ...   (DistributedDataParallel)

Every ``ckpt_every`` steps the weights, optimiser state and RNG state are saved atomically
(safetensors + JSON); ``--resume`` continues from the last complete checkpoint after a kill.
Logs are JSON lines appended to ``OUT/log.jsonl`` (a kill can tear the last line: readers skip a
line that does not parse, and the next append starts a new line); the resolved config is ``OUT/config.json`` (with the
precision chosen for this machine: ``amp``, and ``amp_auto`` when it was not forced).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import math
import os
import time
from dataclasses import replace
from pathlib import Path

import torch
import torch.distributed as dist
from tqdm import tqdm

from drivingscene.data.npz import atomic_write
from drivingscene.errors import InputError
from drivingscene.models.model import DrivingSceneModel
from drivingscene.train.checkpoint import export_weights, load_checkpoint, restore, save_checkpoint
from drivingscene.train.config import TrainConfig
from drivingscene.train.data import PairSequence, list_pairs, with_data_size
from drivingscene.train.stages import TrainStep, is_finite
from drivingscene.train.validate import validate

log = logging.getLogger(__name__)
MAX_BAD_STEPS = 20


def _distributed() -> tuple[int, int]:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("gloo")
    return (dist.get_rank(), world) if world > 1 else (0, 1)


def _trainable(model: DrivingSceneModel, stage: str) -> list[torch.nn.Parameter]:
    frozen = {
        "static": (model.flow_net,),
        "dynamic": (model.depth_net, model.gaussian_head),
        "joint": (),
        "gaussians": (model.depth_net, model.flow_net),
        "depth": (model.gaussian_head, model.flow_net),
    }[stage]
    for module in (model.depth_net, model.gaussian_head, model.flow_net):
        module.requires_grad_(module not in frozen)
    return [p for p in model.parameters() if p.requires_grad]


def _param_groups(model: DrivingSceneModel, params: list[torch.nn.Parameter], config: TrainConfig) -> list[dict]:
    """Adam groups: R at ``flow_lr`` (when set), everything else at ``lr``."""
    flow = {id(p) for p in model.flow_net.parameters()}
    groups = [
        {"params": [p for p in params if id(p) not in flow], "lr": config.lr},
        {"params": [p for p in params if id(p) in flow], "lr": config.flow_lr or config.lr},
    ]
    return [g for g in groups if g["params"]]


# Convolutions whose new input channels come after the old ones, so old weights still apply to them.
WIDENED_INPUTS = ("depth_net.encoder.stem.0.weight",)


def _widened(loaded: torch.Tensor, own: torch.Tensor) -> torch.Tensor:
    """A convolution weight that gained input channels (D's encoder with the road prior: 3 -> 5)
    starts with the loaded weights on the old channels and 0 on the new ones, so the network
    computes what it did until training uses them; any other shape is returned as loaded."""
    if loaded.ndim != 4 or own.ndim != 4 or loaded.shape[0] != own.shape[0] or loaded.shape[2:] != own.shape[2:]:
        return loaded
    if own.shape[1] <= loaded.shape[1]:
        return loaded
    out = torch.zeros_like(own)
    out[:, : loaded.shape[1]] = loaded.to(own.dtype)
    return out


def _load_init(model: DrivingSceneModel, path: str) -> None:
    from safetensors.torch import load_file

    try:
        state = load_file(path)
    except (OSError, ValueError) as e:
        raise InputError(f"{path}: --init: expected a .safetensors weights file: {e}") from None
    state = {k[len("model.model.") :] if k.startswith("model.model.") else k: v for k, v in state.items()}
    own = model.state_dict()
    state = {k: _widened(v, own[k]) if k in WIDENED_INPUTS and k in own else v for k, v in state.items()}
    reshaped = sorted(k for k, v in state.items() if k in own and own[k].shape != v.shape)
    if reshaped:  # e.g. stage 2 with a differently shaped R on stage 1's weights: those stay fresh
        log.warning(
            "%s: --init: %d tensors of another shape left at initialisation: %s", path, len(reshaped), ", ".join(reshaped)
        )
        state = {k: v for k, v in state.items() if k not in reshaped}
    missing, unexpected = model.load_state_dict(state, strict=False)
    if unexpected or len(missing) == len(model.state_dict()):
        raise InputError(f"{path}: --init: weights do not match the model ({len(unexpected)} unexpected tensors)")


def _prepare_out(config: TrainConfig, resume: bool, rank: int):
    out = Path(config.out)
    ckpt = load_checkpoint(out) if resume else None
    if resume and ckpt is None:
        raise InputError(f"{out}: --resume: no checkpoint there (latest.json missing)")
    if not resume and (out / "latest.json").exists():
        raise InputError(f"{out}: a run is already there; pass --resume to continue it or choose another --out")
    if ckpt is not None:
        saved = TrainConfig.from_dict(json.loads((out / "config.json").read_text()))
        if saved.model.input_size is None:  # runs saved before input_size existed trained at the data size
            saved = replace(saved, model=replace(saved.model, input_size=config.model.input_size))
        if saved.model != config.model or saved.stage != config.stage:
            raise InputError(f"{out}/config.json: --resume: the saved stage/model config differs from this command's")
    if rank == 0:
        out.mkdir(parents=True, exist_ok=True)
        atomic_write(out / "config.json", lambda f: f.write(config.to_json().encode()))
    return out, ckpt


@contextlib.contextmanager
def run_lock(out: Path, rank: int = 0):
    """Hold ``out/train.lock`` (an exclusive lock the system drops when the process ends, kill -9
    included) while a trainer writes the run folder: a second trainer on it, ``--resume`` or not,
    is refused with a line naming the first one's process. Ranks other than 0 write nothing."""
    if rank != 0:
        yield
        return
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "train.lock", "a+") as f:
        try:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            f.seek(0)
            holder = f.read().strip() or "unknown"
            raise InputError(
                f"{out}: another trainer (pid {holder}) is writing this run folder; let it finish or stop it, then --resume"
            ) from None
        f.seek(0)
        f.truncate()
        f.write(f"{os.getpid()}\n")
        f.flush()
        try:
            yield
        finally:
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)


def train(config: TrainConfig, resume: bool = False, show_progress: bool = True) -> Path:
    """Run (or resume) a training job; returns the exported weights path. One trainer per run
    folder (`run_lock`)."""
    files = list_pairs(config.data)
    config = with_data_size(config, files).resolve_precision()  # amp: bf16 where the CPU does it natively
    rank, world = _distributed()
    with run_lock(Path(config.out), rank):
        return _train(config, files, resume, show_progress, rank, world)


def _train(config: TrainConfig, files: list[Path], resume: bool, show_progress: bool, rank: int, world: int) -> Path:
    torch.set_num_threads(config.threads)
    torch.manual_seed(config.seed + rank)
    out, ckpt = _prepare_out(config, resume, rank)
    model = DrivingSceneModel(config.model)
    if config.init and ckpt is None:
        _load_init(model, config.init)
    params = _trainable(model, config.stage)
    from drivingscene.eval.lpips import load_perceptual

    perceptual = load_perceptual(config.lpips)
    step_module = TrainStep(model, config, perceptual)
    runner = step_module
    if world > 1:
        runner = torch.nn.parallel.DistributedDataParallel(step_module, find_unused_parameters=True)
    optimizer = torch.optim.Adam(_param_groups(model, params, config))
    # Seed again: building the perceptual metric draws random numbers only the first time in a
    # process (it is cached), and the loop's draws must not depend on that (exact resume).
    torch.manual_seed(config.seed + rank)
    start = restore(model, optimizer, *ckpt) if ckpt is not None else 0
    if rank == 0:
        if start:
            _truncate_log(out / "log.jsonl", start)
        _record_session(out, start, world, config)
    data = PairSequence(files, config.seed, rank, world)
    val_files = list_pairs(config.val_data)[: config.val_pairs] if config.val_data and rank == 0 else []
    info = {"stage": config.stage, "lpips": perceptual.name, "world": world}
    bar = tqdm(
        range(start, config.steps), initial=start, total=config.steps, disable=not show_progress or rank != 0, desc=config.stage
    )
    if start == 0 and val_files and config.init:  # the starting weights' scores, for comparison
        record = {"step": 0, "time": round(time.time(), 1), "val": validate(model, val_files, config)}
        keep_best(out, model, config, 0, record["val"], info)
        _append_log(out, record)
    bad = 0
    for step in bar:
        model.train()
        tic = time.perf_counter()
        optimizer.zero_grad(set_to_none=True)
        loss_sum, terms_sum = 0.0, {}
        for slot in range(config.batch_pairs):
            loss, terms = runner(data.get(step, slot, config.batch_pairs), step)
            if not is_finite(loss):
                break
            (loss / config.batch_pairs).backward()
            loss_sum += float(loss.detach()) / config.batch_pairs
            for k, v in terms.items():
                terms_sum[k] = terms_sum.get(k, 0.0) + float(v.detach()) / config.batch_pairs
        if not is_finite(torch.tensor(loss_sum)) or len(terms_sum) == 0:
            bad += 1
            log.warning("step %d: non-finite loss, skipped (%d in a row)", step, bad)
            if bad >= MAX_BAD_STEPS:
                raise RuntimeError(f"training diverged: {bad} non-finite steps in a row at step {step}")
            continue
        bad = 0
        torch.nn.utils.clip_grad_norm_(params, 10.0)
        optimizer.step()
        seconds = time.perf_counter() - tic
        if rank == 0:
            _after_step(config, out, model, optimizer, step + 1, loss_sum, terms_sum, seconds, info, val_files, bar)
    if rank == 0:
        save_checkpoint(out, config.steps, model, optimizer, info, config.keep_checkpoints)
        export_weights(model, config.model.to_dict(), out / "model.safetensors", {**info, "steps": config.steps})
    if world > 1:
        dist.barrier()
        dist.destroy_process_group()
    return out / "model.safetensors"


def _truncate_log(path: Path, step: int) -> None:
    """Drop log records after ``step`` (the checkpoint a resume starts from): those steps are
    trained again, and the log must describe the weights the run ends with."""
    if not path.exists():
        return
    lines = path.read_text().splitlines()
    kept = [line for line in lines if (record := parse_jsonl_line(line)) is not None and record.get("step", 0) <= step]
    if len(kept) != len(lines):
        atomic_write(path, lambda f: f.write("".join(line + "\n" for line in kept).encode()))


def _record_session(out: Path, start: int, world: int, config: TrainConfig) -> None:
    """One line per start or resume in ``OUT/sessions.jsonl``: when, from which step, on what."""
    from drivingscene.machine import cpu_model, usable_cores

    record = {
        "time": round(time.time(), 1),
        "start_step": start,
        "cpu": cpu_model(),
        "cores": usable_cores(),
        "torch": torch.__version__,
        "threads": config.threads,
        "processes": world,
        "amp": config.amp,
    }
    append_jsonl(out / "sessions.jsonl", record)


# The validation score that `keep_best` ranks checkpoints by, and its sign (+1: higher is better):
# the in-between frame's PSNR, and for D alone its depth error.
BEST_KEY = {"depth": ("depth_abs_rel", -1)}
BEST_DEFAULT = ("psnr", 1)


def keep_best(out: Path, model, config, step: int, val: dict, info: dict) -> bool:
    """Export the weights as ``best.safetensors`` (+ ``best.json`` with the step and its validation)
    when their validation ``BEST_KEY`` beats the one kept so far (also across ``--resume``): the
    rolling step checkpoints keep only the last few, and validation is noisy from one evaluation to
    the next. Returns whether it was kept."""
    key, sign = BEST_KEY.get(config.stage, BEST_DEFAULT)
    score = val.get(key)
    if score is None or not math.isfinite(score):
        return False
    kept = out / "best.json"
    if kept.exists():
        previous = json.loads(kept.read_text()).get("val", {}).get(key)
        if previous is not None and sign * previous >= sign * score:
            return False
    export_weights(model, config.model.to_dict(), out / "best.safetensors", {**info, "steps": step, "val": val})
    return True


def _append_log(out: Path, record: dict) -> None:
    append_jsonl(out / "log.jsonl", record)


def append_jsonl(path: Path, record: dict) -> None:
    """Append one JSON line; after a torn last line (a killed run) start a new line first, so only
    the torn record is lost. Append-only logs are the one place writes are not atomic renames."""
    with open(path, "a+b") as f:
        if f.seek(0, os.SEEK_END) > 0:
            f.seek(-1, os.SEEK_END)
            if f.read(1) != b"\n":
                f.write(b"\n")
        f.write((json.dumps(record) + "\n").encode())
        f.flush()


def parse_jsonl_line(line: str) -> dict | None:
    """The record of one log line, or None for a blank or torn one (a run killed mid-append)."""
    try:
        record = json.loads(line)
    except ValueError:
        return None
    return record if isinstance(record, dict) else None


def _after_step(config, out, model, optimizer, step, loss, terms, seconds, info, val_files, bar) -> None:
    record = {
        "step": step,
        "time": round(time.time(), 1),
        "loss": loss,
        "seconds": round(seconds, 3),
        **{k: round(v, 6) for k, v in terms.items()},
    }
    if step % config.val_every == 0 and val_files:
        record["val"] = validate(model, val_files, config)
        keep_best(out, model, config, step, record["val"], info)
        model.train()
    if step % config.log_every == 0 or "val" in record:
        _append_log(out, record)
        bar.set_postfix(loss=f"{loss:.4f}", s_per_step=f"{seconds:.2f}")
    if step % config.ckpt_every == 0:
        save_checkpoint(out, step, model, optimizer, info, config.keep_checkpoints)
