"""The training config's precision: None = decided for the machine, recorded resolved, old configs load."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from drivingscene import precision
from drivingscene.precision import ENV_VAR, CpuPrecision
from drivingscene.train.config import TrainConfig

RUNS = Path(__file__).parents[2] / "docs" / "training-runs"


@pytest.fixture
def machine(monkeypatch):
    monkeypatch.delenv(ENV_VAR, raising=False)

    def use(bf16: bool):
        decision = CpuPrecision(bf16, ("avx512_bf16",) if bf16 else (), "AVX512" if bf16 else "AVX2", "test")
        monkeypatch.setattr(precision, "machine_cpu_decision", lambda: decision)

    return use


def test_default_is_auto_and_resolves_per_machine(machine):
    assert TrainConfig().amp is None
    machine(False)
    resolved = TrainConfig().resolve_precision()
    assert (resolved.amp, resolved.amp_auto) == (False, True)
    machine(True)
    assert TrainConfig().resolve_precision().amp is True
    assert resolved.resolve_precision().amp is True  # an automatic choice is made again on another machine


def test_forced_choice_is_kept(machine, monkeypatch):
    machine(False)
    assert TrainConfig(amp=True).resolve_precision() == TrainConfig(amp=True)
    machine(True)
    assert TrainConfig(amp=False).resolve_precision().amp is False
    monkeypatch.setenv(ENV_VAR, "0")
    assert (TrainConfig().resolve_precision().amp, TrainConfig().resolve_precision().amp_auto) == (False, False)


def test_resolved_config_round_trip(machine):
    machine(False)
    auto = TrainConfig().resolve_precision()
    data = json.loads(auto.to_json())
    assert data["amp"] is False and data["amp_auto"] is True  # config.json records the choice made
    assert TrainConfig.from_dict(data).amp is None  # loaded, it is decided again
    forced = json.loads(TrainConfig(amp=True).resolve_precision().to_json())
    assert TrainConfig.from_dict(forced).amp is True
    assert TrainConfig.from_dict(TrainConfig().to_dict()) == TrainConfig()


def test_old_configs_load():
    """Saved before the choice was automatic: ``amp: true`` was the default (auto now), false was --no-amp.
    Saved after: ``amp_auto`` says whether ``amp`` was the machine's choice (made again on loading)."""
    old_runs = 0
    for path in sorted(RUNS.glob("*/config.json")):
        data = json.loads(path.read_text())
        config = TrainConfig.from_dict(data)
        if "amp_auto" in data:
            assert config.amp is (None if data["amp_auto"] else data["amp"]), path
            continue
        old_runs += 1
        assert config.amp is (None if data["amp"] else False), path
    assert old_runs > 0
    old = {k: v for k, v in TrainConfig().to_dict().items() if k != "amp_auto"}
    assert TrainConfig.from_dict({**old, "amp": False}).amp is False
    assert TrainConfig.from_dict({**old, "amp": True}).amp is None


def test_a_run_records_the_choice_made(machine, tmp_path):
    from drivingscene.data import save_frame_pair
    from drivingscene.train.trainer import train
    from tests.factories import make_pair
    from tests.train.test_trainer import TINY_MODEL

    machine(False)
    save_frame_pair(make_pair(num_views=3, height=32, width=48), tmp_path / "pair_000000.npz")
    out = tmp_path / "run"
    config = TrainConfig(data=str(tmp_path), out=str(out), steps=1, lpips="stlpips", model=TINY_MODEL, threads=1)
    train(config, show_progress=False)
    saved = json.loads((out / "config.json").read_text())
    assert saved["amp"] is False and saved["amp_auto"] is True
    assert json.loads((out / "sessions.jsonl").read_text().splitlines()[-1])["amp"] is False
