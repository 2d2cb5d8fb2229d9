"""Nothing is overwritten without --force: every command that writes a user path refuses an
existing file with one line and exit code 2 and leaves it untouched; the viewer's exports pick a
free name instead of overwriting; a folder that cannot be written is one clean line."""

from __future__ import annotations

from pathlib import Path

import pytest

from drivingscene.cli import main
from tests.factories import make_pair

OLD = b"old complete content\n"


@pytest.fixture
def scene(tmp_path) -> Path:
    from drivingscene.data import save_frame_pair

    path = tmp_path / "pair.npz"
    save_frame_pair(make_pair(num_views=2, height=12, width=16), path)
    return path


def _refuses(argv, target: Path, capsys, runner=main) -> None:
    target.write_bytes(OLD)
    assert runner(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--force" in err and str(target) in err, err
    assert target.read_bytes() == OLD


def test_commands_refuse_an_existing_file_without_force(scene, tmp_path, capsys):
    out = tmp_path / "exists.npz"
    _refuses(["reconstruct", str(scene), "-o", str(out)], out, capsys)
    _refuses(["oracle", str(scene), "-o", str(out)], out, capsys)
    _refuses(["export", str(scene), "--ply", str(tmp_path / "x.ply")], tmp_path / "x.ply", capsys)
    _refuses(["synth", "--seed", "1", "--res", "48x88", "--out", str(out)], out, capsys)
    _refuses(["import", "rig", str(tmp_path), "-o", str(out)], out, capsys)
    report = tmp_path / "report.md"
    _refuses(["bench", "training", str(tmp_path), "--out", str(report)], report, capsys)
    _refuses(["bench", "raster", "--out", str(report)], report, capsys)


def test_viewer_headless_refuses_existing_outputs(scene, tmp_path, capsys):
    from drivingscene_view.__main__ import main as view_main
    from drivingscene_view.headless import planned_outputs

    target = planned_outputs(tmp_path / "views", [0.0], [], True)[-1]
    target.parent.mkdir()
    _refuses([str(scene), "--method", "oracle", "--headless", "--out", str(tmp_path / "views")], target, capsys, view_main)


def test_viewer_exports_never_overwrite(tmp_path):
    from drivingscene_view.export import free_path

    taken = tmp_path / "view.png"
    taken.write_bytes(OLD)
    assert free_path(taken) == tmp_path / "view-1.png" and taken.read_bytes() == OLD


def test_unwritable_output_is_one_clean_line(scene, tmp_path, capsys):
    blocker = tmp_path / "not_a_folder"
    blocker.write_bytes(OLD)  # a file where the output folder should be (chmod does not stop root)
    assert main(["oracle", str(scene), "-o", str(blocker / "recon.npz")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "could not write it" in err and str(blocker / "recon.npz") in err, err
    assert blocker.read_bytes() == OLD


@pytest.mark.gl
def test_viewer_headless_force_replaces_files_without_deleting_them_first(scene, tmp_path):
    """``--headless --force`` over earlier outputs, killed with SIGKILL at its first rename: every
    earlier file is still there, complete (the old way deleted them all before rendering)."""
    import subprocess
    import sys

    from drivingscene_view.headless import planned_outputs

    out = tmp_path / "views"
    out.mkdir()
    planned = planned_outputs(out, [0.0], ["CAM_0", "CAM_1"], True)
    for p in planned:
        p.write_bytes(OLD)
    code = (
        "import os, signal, sys\n"
        "os.replace = lambda *a, **k: os.kill(os.getpid(), signal.SIGKILL)\n"
        "from drivingscene_view.__main__ import main\n"
        "sys.exit(main(sys.argv[1:]))\n"
    )
    argv = [str(scene), "--method", "oracle", "--headless", "--out", str(out), "--time", "0", "--force"]
    run = subprocess.run(
        [sys.executable, "-c", code, *argv],
        capture_output=True,
        text=True,
        timeout=300,
        env={**__import__("os").environ, "PYOPENGL_PLATFORM": "egl"},
    )
    assert run.returncode == -9, run.stderr  # killed at the first rename
    assert all(p.read_bytes() == OLD for p in planned)
