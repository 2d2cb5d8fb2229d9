"""``drivingscene bench command`` and ``bench runtimes``: bad arguments are one-line errors before
anything is timed (the benchmarks themselves are commands, never timed tests)."""

from __future__ import annotations

import pytest

from drivingscene.cli import main


def test_bench_command_missing_scene_is_one_line(tmp_path, capsys):
    assert main(["bench", "command", "--scene", str(tmp_path / "nope.npz")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "nope.npz: --scene: file not found" in err


@pytest.mark.parametrize("bench", ["command", "runtimes"])
def test_bench_runs_must_be_positive(bench, capsys):
    with pytest.raises(SystemExit) as info:
        main(["bench", bench, "--runs", "0"])
    assert info.value.code == 2 and "--runs" in capsys.readouterr().err


def test_bench_command_times_the_reconstruct_command_in_fresh_processes(monkeypatch, tmp_path):
    """What each row runs: ``drivingscene reconstruct`` on the scene with today's file and the old
    one's flags, the wall time against the reconstruction's own time read back from the file."""
    import json

    import numpy as np

    from drivingscene.bench import command
    from drivingscene.data.npz import save_npz

    calls = []

    def fake_wall(argv):
        calls.append(argv)
        if "-o" in argv:
            save_npz(argv[argv.index("-o") + 1], {"meta": np.array(json.dumps({"timings": {"total_s": 1.0}}))})
        return 3.0 if "--deflate" in argv else 2.0

    monkeypatch.setattr(command, "_wall", fake_wall)
    rows, startup = command.measure(tmp_path / "scene.npz", 2)
    assert [r["wall"] for r in rows] == [2.0, 3.0] and [r["rest"] for r in rows] == [1.0, 2.0]
    recon_calls = [a for a in calls if "reconstruct" in a and "--help" not in a]
    assert len(recon_calls) == 2 * (1 + 2)  # one warm-up and two timed runs per row
    assert sum("--deflate" in a and "float32" in a for a in recon_calls) == 3
    assert set(startup) == {
        "python -c 'import torch'",
        "python -c 'import drivingscene.methods.feedforward'",
        "drivingscene reconstruct --help",
    }


def test_bench_runtimes_rows_without_onnxruntime(monkeypatch):
    """torch in both layouts (and under bf16 autocast where the CPU does bf16 natively) and
    TorchScript are timed on the shipped model's encoder and decoder; without OpenVINO and ONNX
    Runtime their rows say how to install them instead of a figure."""
    import sys

    from drivingscene.bench import runtimes
    from drivingscene.precision import auto_amp

    monkeypatch.setitem(sys.modules, "onnxruntime", None)  # import fails as where it is not installed
    monkeypatch.setitem(sys.modules, "openvino", None)
    rows, shape = runtimes.measure(None, 1, 2)
    timed = 4 if auto_amp("cpu") else 3
    assert shape[0] == 12 and len(rows) == timed + 2
    assert all(r["s"] > 0 for r in rows[:timed]) and rows[0]["diff"] < 1e-4 and rows[1]["diff"] == 0.0
    assert any("bf16 autocast" in r["runtime"] for r in rows) == auto_amp("cpu")
    missing = rows[timed:]
    assert all(r["s"] is None and "not installed" in r["runtime"] for r in missing)
    assert [r["runtime"].split()[0] for r in missing] == ["OpenVINO", "ONNX"]
