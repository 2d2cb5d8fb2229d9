"""``drivingscene-view`` command line: one-line errors with exit code 2, and the headless renderer."""

from __future__ import annotations

import cv2
import pytest
from drivingscene_view.__main__ import main

from drivingscene.data import save_frame_pair
from drivingscene.export.ply import read_ply
from drivingscene.gaussians.recon import save_reconstruction
from tests.app.scenes import street_recon
from tests.factories import make_pair


def _error(capsys, argv) -> str:
    with pytest.raises(SystemExit) as info:
        code = main(argv)
        raise SystemExit(code)
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("drivingscene-view: error: ")
    return err


@pytest.fixture
def recon_file(tmp_path):
    return save_reconstruction(street_recon(), tmp_path / "recon.npz")


def test_usage_errors_are_one_line(capsys, tmp_path, recon_file):
    assert "--out" in _error(capsys, [str(recon_file), "--headless"])
    assert "[0, 1]" in _error(capsys, [str(recon_file), "--headless", "--out", str(tmp_path), "--time", "1.5"])
    assert "WIDTHxHEIGHT" in _error(capsys, [str(recon_file), "--size", "big"])
    assert "invalid choice" in _error(capsys, [str(recon_file), "--method", "magic"])
    assert "file not found" in _error(capsys, [str(tmp_path / "missing.npz"), "--headless", "--out", str(tmp_path / "o")])


def test_window_without_display_is_a_one_line_error(capsys, monkeypatch, recon_file):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert "--headless" in _error(capsys, [str(recon_file)])


@pytest.mark.gl
def test_headless_renders_views_and_a_ply(capsys, tmp_path, recon_file):
    out = tmp_path / "out"
    assert main([str(recon_file), "--headless", "--out", str(out), "--time", "0.5", "--camera", "CAM_1", "--size", "64x48"]) == 0
    assert "wrote 3 files" in capsys.readouterr().out
    assert cv2.imread(str(out / "CAM_1_t0.500.png")).shape == (24, 32, 3)
    assert cv2.imread(str(out / "overview_t0.500.png")).shape == (48, 64, 3)
    assert len(read_ply(out / "gaussians_t0.500.ply")) == 600
    # Existing outputs: refused without --force, replaced with it.
    assert "--force" in _error(capsys, [str(recon_file), "--headless", "--out", str(out), "--time", "0.5", "--camera", "CAM_1"])
    assert (
        main([str(recon_file), "--headless", "--out", str(out), "--time", "0.5", "--camera", "CAM_1", "--force", "--no-ply"]) == 0
    )
    # replaced in place (atomically, never deleted first): no second name beside the first
    assert sorted(p.name for p in out.iterdir()) == ["CAM_1_t0.500.png", "gaussians_t0.500.ply", "overview_t0.500.png"]
    assert "unknown camera" in _error(capsys, [str(recon_file), "--headless", "--out", str(out), "--camera", "CAM_9"])


@pytest.mark.gl
def test_headless_scene_without_weights(capsys, tmp_path):
    scene = save_frame_pair(make_pair(num_views=2, height=24, width=32), tmp_path / "scene.npz")
    weights = ["--weights", str(tmp_path / "none.safetensors")]
    err = _error(capsys, [str(scene), "--headless", "--out", str(tmp_path / "a"), "--method", "model", *weights])
    assert "model weights not found" in err
    assert main([str(scene), "--headless", "--out", str(tmp_path / "b"), "--time", "0", "--no-ply", *weights]) == 0
    captured = capsys.readouterr()
    assert "oracle" in captured.err and captured.err.count("\n") == 1  # auto: a one-line note, then the oracle
    assert len(list((tmp_path / "b").glob("*.png"))) == 3
