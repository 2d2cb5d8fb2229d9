"""Checkpoints carry the SHA-256 and size of their weights: a truncated or corrupted latest one is
detected on resume and the previous one used; a training run killed with SIGKILL resumes from its
last complete checkpoint, losing at most one checkpoint interval."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from drivingscene.errors import InputError
from drivingscene.train.checkpoint import load_checkpoint, restore, save_checkpoint
from tests.train.test_trainer import TINY_MODEL, _config, data_dir  # noqa: F401  (fixture)


def _run(tmp_path: Path, steps=(1, 2, 3)) -> Path:
    model = torch.nn.Linear(4, 2)
    optimizer = torch.optim.Adam(model.parameters())
    for step in steps:
        with torch.no_grad():
            model.weight.fill_(float(step))
        save_checkpoint(tmp_path, step, model, optimizer, {"stage": "static"}, keep=2)
    return tmp_path


def test_checkpoints_record_their_hash_and_keep_two(tmp_path):
    _run(tmp_path, steps=(1, 2, 3))
    meta = json.loads((tmp_path / "latest.json").read_text())
    assert meta["step"] == 3 and len(meta["sha256"]) == 64 and meta["bytes"] == (tmp_path / meta["weights"]).stat().st_size
    assert sorted(p.name for p in tmp_path.glob("step_*")) == [
        "step_0000002.json",
        "step_0000002.safetensors",
        "step_0000003.json",
        "step_0000003.safetensors",
    ]
    assert load_checkpoint(tmp_path)[0]["step"] == 3


@pytest.mark.parametrize("damage", ["truncate", "flip", "delete"])
def test_a_damaged_latest_checkpoint_falls_back_to_the_previous(tmp_path, damage, caplog):
    _run(tmp_path)
    weights = tmp_path / "step_0000003.safetensors"
    data = weights.read_bytes()
    if damage == "truncate":
        weights.write_bytes(data[: len(data) // 2])
    elif damage == "flip":
        weights.write_bytes(data[:-8] + bytes(b ^ 0xFF for b in data[-8:]))
    else:
        weights.unlink()
    meta, tensors = load_checkpoint(tmp_path)
    assert meta["step"] == 2 and "not usable" in caplog.text
    model = torch.nn.Linear(4, 2)
    assert restore(model, torch.optim.Adam(model.parameters()), meta, tensors) == 2
    assert torch.all(model.weight == 2.0)


def test_no_intact_checkpoint_is_one_clean_error(tmp_path):
    _run(tmp_path, steps=(1, 2))
    for weights in tmp_path.glob("step_*.safetensors"):
        weights.write_bytes(b"garbage")
    with pytest.raises(InputError, match="none is intact"):
        load_checkpoint(tmp_path)


def test_resume_after_a_corrupted_latest_checkpoint(data_dir, tmp_path):  # noqa: F811
    from drivingscene.train.trainer import train

    out = tmp_path / "run"
    train(_config(data_dir, out, steps=4, ckpt_every=1), show_progress=False)
    latest = out / "step_0000004.safetensors"
    latest.write_bytes(latest.read_bytes()[:100])
    train(_config(data_dir, out, steps=5, ckpt_every=1), resume=True, show_progress=False)
    sessions = [json.loads(line) for line in (out / "sessions.jsonl").read_text().splitlines()]
    assert [s["start_step"] for s in sessions] == [0, 3]
    records = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in records] == [1, 2, 3, 4, 5]


def test_training_killed_with_sigkill_resumes_from_the_last_checkpoint(data_dir, tmp_path):  # noqa: F811
    out, every, steps = tmp_path / "run", 2, 14
    config = tmp_path / "config.json"
    config.write_text(_config(data_dir, out, steps=steps, ckpt_every=every).to_json())
    args = [sys.executable, "-m", "drivingscene", "train", "--stage", "static", "--config", str(config)]
    args += ["--data", str(data_dir), "--out", str(out), "--no-progress"]
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        latest = out / "latest.json"
        if latest.exists() and json.loads(latest.read_text())["step"] >= 2 * every:
            break
        time.sleep(0.05)
    time.sleep(0.3)  # somewhere between checkpoints (or inside the next save)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL, "the run finished before it was killed: make it longer"
    saved = json.loads((out / "latest.json").read_text())["step"]
    logged = max(json.loads(line)["step"] for line in (out / "log.jsonl").read_text().splitlines() if line.endswith("}"))
    resumed = subprocess.run([*args, "--resume"], capture_output=True, text=True, timeout=120)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    start = json.loads((out / "sessions.jsonl").read_text().splitlines()[-1])["start_step"]
    assert start == saved and logged - start <= every
    records = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in records] == list(range(1, steps + 1)) and (out / "model.safetensors").exists()
