"""``--amp`` / ``--no-amp``: default auto (None), either flag forces, not both."""

from __future__ import annotations

import pytest

from drivingscene.cli import build_parser

COMMANDS = {
    "reconstruct": ["reconstruct", "scene.npz", "-o", "recon.npz"],
    "train": ["train", "--stage", "static", "--data", "d", "--out", "o"],
    "bench inference": ["bench", "inference"],
}


@pytest.mark.parametrize("command", COMMANDS)
@pytest.mark.parametrize("flags, amp", [([], None), (["--amp"], True), (["--no-amp"], False)])
def test_amp_flags_parse(command, flags, amp):
    assert build_parser().parse_args(COMMANDS[command] + flags).amp is amp


@pytest.mark.parametrize("command", COMMANDS)
def test_amp_flags_exclude_each_other(command, capsys):
    with pytest.raises(SystemExit) as e:
        build_parser().parse_args(COMMANDS[command] + ["--amp", "--no-amp"])
    assert e.value.code == 2 and "not allowed with argument" in capsys.readouterr().err


def test_train_flags_reach_the_config(monkeypatch, tmp_path):
    """The CLI's choice becomes the config's ``amp`` (None = the machine's), also over a --config file."""
    import json

    import drivingscene.train.trainer as trainer
    from drivingscene.cli import main
    from drivingscene.train.config import TrainConfig

    seen = []
    monkeypatch.setattr(trainer, "train", lambda config, **kw: seen.append(config) or tmp_path / "w.safetensors")
    saved = tmp_path / "config.json"
    saved.write_text(json.dumps({**TrainConfig().to_dict(), "amp": False, "amp_auto": True}))
    base = ["train", "--stage", "static", "--data", str(tmp_path), "--out", str(tmp_path / "run")]
    for flags, amp in ([], None), (["--amp"], True), (["--no-amp"], False), (["--config", str(saved)], None):
        assert main(base + flags) == 0
        assert seen[-1].amp is amp
