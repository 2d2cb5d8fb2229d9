"""SIGKILL at any moment: ``drivingscene reconstruct`` and ``drivingscene export`` killed at spread
times, deterministically as each stage of the reconstruction starts, and inside the write leave
the target as it was (absent, or the old complete file under --force) or as the complete new file,
byte for byte the reference output.
Only hidden temporary files (``.NAME.PID.XXXX.tmp``), never the user's name, can be left over,
and the next write of the same target removes them."""

from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from drivingscene.data import atomic
from drivingscene.data.atomic import atomic_write_text

OLD = b"old complete content\n"
# Runs the command with a hook that kills the process with SIGKILL inside the write of TARGET:
# mid_write (half the bytes written), before_rename (all written and synced), after_rename; or
# stage:NAME, as the reconstruction's stage NAME starts (methods/feedforward.py STAGES).
HOOK = r"""
import os, signal, sys
from pathlib import Path
import drivingscene.data.atomic as atomic
import drivingscene.methods.feedforward as feedforward
from drivingscene.cli import main

mode, target, argv = sys.argv[1], Path(sys.argv[2]).resolve(), sys.argv[3:]
real_open, real_replace = open, os.replace

def die():
    os.kill(os.getpid(), signal.SIGKILL)

class Killing:
    def __init__(self, f):
        self.f, self.n = f, 0
    def __enter__(self):
        return self
    def __exit__(self, *exc):
        self.f.close()
    def __getattr__(self, name):
        return getattr(self.f, name)
    def write(self, data):
        data = bytes(data)
        if self.n + len(data) > 100_000:
            self.f.write(data[: len(data) // 2])
            self.f.flush()
            die()
        self.n += len(data)
        return self.f.write(data)

def hooked_open(path, *args, **kw):
    f = real_open(path, *args, **kw)
    return Killing(f) if mode == "mid_write" and Path(path).name.startswith("." + target.name + ".") else f

def hooked_replace(src, dst):
    if Path(dst).resolve() != target:
        return real_replace(src, dst)
    if mode == "before_rename":
        die()
    real_replace(src, dst)
    if mode == "after_rename":
        die()

real_reporter = feedforward._stage_reporter

def hooked_reporter(progress, num_views):
    report = real_reporter(progress, num_views)
    def hooked(stage):
        if mode == f"stage:{stage}":
            die()
        report(stage)
    return hooked

atomic.open = hooked_open
os.replace = hooked_replace
feedforward._stage_reporter = hooked_reporter
sys.exit(main(argv))
"""


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    """A small pair (3 cameras, 48x88), tiny weights, and the reference outputs of each command."""
    import torch
    from safetensors.torch import save_file

    from drivingscene.data import save_frame_pair
    from drivingscene.models.depth import DepthConfig
    from drivingscene.models.model import DrivingSceneModel, ModelConfig
    from drivingscene.models.residual_flow import FlowConfig
    from tests.factories import make_pair

    folder = tmp_path_factory.mktemp("kill")
    torch.manual_seed(0)
    config = ModelConfig(
        depth=DepthConfig(width=8, decoder_channels=(8, 8, 16, 16, 32)), flow=FlowConfig(channels=(8, 8, 16, 16), hidden=8)
    )
    save_file({k: v.contiguous() for k, v in DrivingSceneModel(config).state_dict().items()}, str(folder / "tiny.safetensors"))
    (folder / "tiny.json").write_text(json.dumps({"model": config.to_dict()}))
    save_frame_pair(make_pair(num_views=3, height=48, width=88, seed=1), folder / "pair.npz")
    for name in ("recon.npz", "ref.ply", "ref_points.ply"):
        tic = time.perf_counter()
        assert subprocess.run(command(folder, name), cwd=folder, capture_output=True, timeout=120).returncode == 0
        DURATION[name.endswith(".npz")] = time.perf_counter() - tic
    return folder


DURATION = {}  # seconds of the reference run: True reconstruct, False export


def command(folder: Path, out: str) -> list[str]:
    cli = [sys.executable, "-m", "drivingscene"]
    if out.endswith(".npz"):
        return [*cli, "reconstruct", "pair.npz", "-o", out, "--weights", "tiny.safetensors", "--threads", "1", "--force"]
    kind = "points" if "points" in out else "3dgs"
    return [*cli, "export", "recon.npz", "--ply", out, "--kind", kind, "--force"]


def reference(folder: Path, out: str) -> bytes:
    name = "recon.npz" if out.endswith(".npz") else "ref_points.ply" if "points" in out else "ref.ply"
    return (folder / name).read_bytes()


def assert_old_or_new(folder: Path, out: str, had_old: bool) -> str:
    """The target is absent (when there was none), the old file, or the complete new one; only
    hidden temporary files are left beside it. Returns which."""
    target = folder / out
    left = [p.name for p in folder.iterdir() if p.name.startswith(f".{out}.")]
    assert all(n.startswith(f".{out}.") and n != out for n in left)
    if not target.exists():
        assert not had_old, "the old file was lost"
        return "absent"
    data = target.read_bytes()
    if data == OLD:
        assert had_old
        return "old"
    assert same_output(data, reference(folder, out), out), f"{out}: neither the old file nor the complete new one"
    return "new"


def same_output(data: bytes, ref: bytes, out: str) -> bool:
    """PLY byte for byte; recon.npz array by array (it loads completely), its meta without the timings."""
    if not out.endswith(".npz"):
        return data == ref
    with np.load(io.BytesIO(data), allow_pickle=False) as a, np.load(io.BytesIO(ref), allow_pickle=False) as b:
        arrays, expected = {k: a[k] for k in a.files}, {k: b[k] for k in b.files}
    metas = [json.loads(str(d.pop("meta"))) for d in (arrays, expected)]
    for meta in metas:
        meta.pop("timings", None)
    return (
        metas[0] == metas[1] and arrays.keys() == expected.keys() and all(np.array_equal(arrays[k], expected[k]) for k in arrays)
    )


def prepare(folder: Path, out: str, had_old: bool) -> None:
    for p in folder.glob(f".{out}.*"):
        p.unlink()
    (folder / out).unlink(missing_ok=True)
    if had_old:
        (folder / out).write_bytes(OLD)


# (target, fraction of the reference run's time, an old file there): spread over the runs
# (interpreter and torch start, reading, the networks, writing; ~3 s each here).
TIMED = [
    ("out.npz", 0.15, False),
    ("out.npz", 0.5, True),
    ("out.npz", 0.7, False),
    ("out.npz", 0.85, True),
    ("out.npz", 1.0, True),
    ("out.ply", 0.3, True),
    ("out.ply", 0.6, False),
    ("out.ply", 0.85, True),
    ("out_points.ply", 0.7, False),
]


def test_killed_at_spread_times(work):
    outcomes = []
    for out, fraction, had_old in TIMED:
        seconds = fraction * DURATION[out.endswith(".npz")]
        prepare(work, out, had_old)
        proc = subprocess.Popen(command(work, out), cwd=work, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(seconds)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=60)
        outcomes.append((out, round(seconds, 2), assert_old_or_new(work, out, had_old)))
    print(outcomes)


INSIDE = [(out, mode) for out in ("out.npz", "out.ply") for mode in ("mid_write", "before_rename", "after_rename")]


@pytest.mark.parametrize("stage", ["static", "match", "flow", "assembly"])
def test_killed_as_a_stage_starts(work, stage):
    """Killed while the model runs (the timed kills above may all land after it on a loaded machine):
    the old file stays, whole, and nothing of the new one appears."""
    out = "out.npz"
    prepare(work, out, had_old=True)
    argv = command(work, out)[3:]
    proc = subprocess.run([sys.executable, "-c", HOOK, f"stage:{stage}", out, *argv], cwd=work, capture_output=True, timeout=120)
    assert proc.returncode == -signal.SIGKILL, proc.stderr.decode()[-2000:]
    assert assert_old_or_new(work, out, had_old=True) == "old"
    assert not list(work.glob(f".{out}.*"))  # killed before the write began


@pytest.mark.parametrize(("out", "mode"), [*INSIDE, ("out_points.ply", "mid_write")])
def test_killed_inside_the_write(work, out, mode):
    prepare(work, out, had_old=True)
    argv = command(work, out)[3:]
    proc = subprocess.run([sys.executable, "-c", HOOK, mode, out, *argv], cwd=work, capture_output=True, timeout=120)
    assert proc.returncode == -signal.SIGKILL, proc.stderr.decode()[-2000:]
    expected = "new" if mode == "after_rename" else "old"
    assert assert_old_or_new(work, out, had_old=True) == expected
    leftovers = list(work.glob(f".{out}.*"))
    assert bool(leftovers) == (mode != "after_rename")  # a killed writer's temporary file, hidden
    old = time.time() - 2 * atomic.STALE_SECONDS
    for p in leftovers:
        os.utime(p, (old, old))
    atomic_write_text(work / "scratch" / ".." / out, "next write")  # the next write of the target cleans up
    assert list(work.glob(f".{out}.*")) == []
