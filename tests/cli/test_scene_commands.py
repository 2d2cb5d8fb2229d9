"""``drivingscene validate`` / ``info`` and the CLI's error contract."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from drivingscene.cli import main
from drivingscene.data import save_frame_pair
from drivingscene.data.npz import save_npz


def test_validate_valid_file(tmp_path, small_pair, capsys):
    path = save_frame_pair(small_pair, tmp_path / "ok.npz")
    assert main(["validate", str(path)]) == 0
    assert capsys.readouterr().out.strip() == f"{path}: valid"


def test_validate_prints_one_line_per_problem_and_exits_2(tmp_path, small_pair, capsys):
    arrays = small_pair.to_arrays()
    arrays["intrinsics"] = arrays["intrinsics"].copy()
    arrays["intrinsics"][0, 0, 0] = -1
    arrays["timestamps"] = np.array([3.0, 1.0])
    path = save_npz(tmp_path / "bad.npz", arrays)
    assert main(["validate", str(path)]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 2
    assert lines[0].startswith(f"{path}: intrinsics[0]: expected positive focal lengths")
    assert lines[1].startswith(f"{path}: timestamps: expected finite and increasing")


def test_validate_several_files_reports_each(tmp_path, small_pair, capsys):
    good = save_frame_pair(small_pair, tmp_path / "good.npz")
    assert main(["validate", str(good), str(tmp_path / "missing.npz")]) == 2
    captured = capsys.readouterr()
    assert "good.npz: valid" in captured.out
    assert "missing.npz: <file>: expected a readable .npz scene file, found file not found" in captured.err


def test_info_summarises(tmp_path, small_pair, capsys):
    path = save_frame_pair(small_pair, tmp_path / "s.npz")
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "cameras     3: CAM_0, CAM_1, CAM_2" in out
    assert "image size  16x12" in out
    assert "ego motion  4.00 m (8.00 m/s)" in out
    assert "eval frames 1 at t = 0.500" in out
    assert "valid_mask" not in out and "capture" not in out


def test_info_into_a_closed_pipe_ends_quietly(tmp_path, small_pair):
    """``drivingscene info F | head -1``: no BrokenPipeError traceback, the status of a program the
    closed pipe stopped (141, as `cat`)."""
    path = save_frame_pair(small_pair, tmp_path / "s.npz")
    code = "import sys; from drivingscene.cli import main; sys.exit(main(['info', sys.argv[1]]))"
    proc = subprocess.Popen([sys.executable, "-c", code, str(path)], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()  # the reader is gone before the command writes (it takes a second to import)
    stderr = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 141 and stderr == ""


def test_info_tells_mask_and_capture_times(tmp_path, small_pair, capsys):
    from dataclasses import replace

    import numpy as np

    mask = np.ones((3, 12, 16), bool)
    mask[1, -3:] = False  # a quarter of camera 1
    times = small_pair.timestamps[:, None] + np.array([0.0, 0.02, 0.04])[None]
    pair = replace(small_pair, valid_mask=mask, camera_timestamps=times)
    assert main(["info", str(save_frame_pair(pair, tmp_path / "s.npz"))]) == 0
    out = capsys.readouterr().out
    assert "0.0%, 25.0%, 0.0%" in out and "span 40.0 ms" in out


def test_info_on_bad_file_is_one_line_error(tmp_path, capsys):
    path = tmp_path / "junk.npz"
    path.write_bytes(b"junk")
    assert main(["info", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("drivingscene info: error: ") and str(path) in err and "\n" not in err


def test_unknown_command_is_usage_error(capsys):
    with pytest.raises(SystemExit) as info:
        main(["frobnicate"])
    assert info.value.code == 2


def test_console_script_runs():
    out = subprocess.run([sys.executable, "-m", "drivingscene", "--version"], capture_output=True, text=True, check=True)
    assert out.stdout.startswith("drivingscene ")


@pytest.mark.parametrize(
    ("device", "expected"),
    [("tpu", "--device: expected cpu, cuda or cuda:N, found 'tpu'"), ("cuda", "sees no CUDA GPU; use --device cpu")],
)
def test_reconstruct_device_errors_are_one_line(tmp_path, small_pair, capsys, device, expected):
    import torch

    if device == "cuda" and torch.cuda.is_available():
        pytest.skip("this machine has a CUDA GPU")
    scene = save_frame_pair(small_pair, tmp_path / "scene.npz")
    assert main(["reconstruct", str(scene), "-o", str(tmp_path / "r.npz"), "--device", device]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and expected in err
    assert not (tmp_path / "r.npz").exists()


def test_reconstruct_search_and_ablations_from_the_command_line(tmp_path, synth_pair, capsys):
    """The shipped model: the searched flow is, per pixel, R's flow (refined down to the search's
    proposal level) or a multiple of the rigid flow on the search's grid (--no-parallax: the rigid
    flow as D's depth makes it); --no-search keeps R's (every level); --static-only moves nothing;
    by default parallax explains some of the moving pixels (fewer dynamic Gaussians); --no-match
    keeps D's depth, which matching the keyframes otherwise corrects; moving objects are tracked unless --no-objects;
    --per-pixel keeps a Gaussian per pixel."""
    import numpy as np

    from drivingscene.gaussians.recon import load_reconstruction
    from drivingscene.methods.feedforward import InferenceOptions, load_model, reconstruct
    from drivingscene.models.lift import LiftConfig, MotionSearchConfig
    from drivingscene.models.pipeline import predict_flow

    scene = save_frame_pair(synth_pair, tmp_path / "scene.npz")
    recons = {}
    runs = (
        ("full", ["--no-parallax", "--no-objects"]),  # the search's flow alone: R's or on its grid (below)
        ("r_alone", ["--no-search", "--no-parallax", "--no-objects"]),
        ("static", ["--static-only", "--file-precision", "float32", "--deflate"]),
        ("default", []),
        ("no_match", ["--no-match"]),
        ("no_objects", ["--no-objects"]),
        ("per_pixel", ["--per-pixel"]),
        ("budget", ["--budget", "0.25"]),
    )
    for name, extra in runs:
        assert main(["reconstruct", str(scene), "-o", str(tmp_path / f"{name}.npz"), *extra]) == 0
        recons[name] = load_reconstruction(tmp_path / f"{name}.npz")
    assert not recons["static"].gaussians.dynamic.any() and recons["full"].gaussians.dynamic.any()
    assert recons["default"].gaussians.dynamic.sum() < recons["full"].gaussians.dynamic.sum()
    assert "match_s" in recons["default"].meta["timings"] and "match_s" not in recons["no_match"].meta["timings"]
    assert "objects_s" in recons["default"].meta["timings"] and "objects_s" not in recons["no_objects"].meta["timings"]
    # flat blocks merged by default (gaussians/parsimony.py); --per-pixel keeps one Gaussian per world pixel
    per_pixel = recons["per_pixel"]
    world = np.broadcast_to(True if per_pixel.valid_mask is None else per_pixel.valid_mask, per_pixel.depth.shape)
    assert len(per_pixel.gaussians) == int(world.sum()) and "merge_s" not in per_pixel.meta["timings"]
    assert len(recons["default"].gaussians) < 0.75 * len(per_pixel.gaussians)
    assert len(recons["budget"].gaussians) <= 0.25 * len(per_pixel.gaussians) < len(recons["default"].gaussians)
    assert recons["budget"].meta["per_pixel_gaussians"] == len(per_pixel.gaussians)
    out = capsys.readouterr()
    assert (
        f"{len(recons['budget'].gaussians)} Gaussians ({100 * len(recons['budget'].gaussians) / len(per_pixel.gaussians):.0f} %"
        in out.out
    )
    assert "warning" not in out.err
    # a budget below what the moving objects alone hold is not met: said in one line, the file still written
    assert main(["reconstruct", str(scene), "-o", str(tmp_path / "tiny.npz"), "--budget", "0.01"]) == 0
    assert "warning: --budget 0.01: reached" in capsys.readouterr().err and (tmp_path / "tiny.npz").exists()
    # The file: float16 attributes, stored, by default; float32 and deflated as before issue 48 on request
    import zipfile

    for name, dtype, method in (("default", np.float16, zipfile.ZIP_STORED), ("static", np.float32, zipfile.ZIP_DEFLATED)):
        with zipfile.ZipFile(tmp_path / f"{name}.npz") as zf:
            assert {i.compress_type for i in zf.infolist()} == {method}
            with zf.open("quats.npy") as f:
                assert np.lib.format.read_array(f, allow_pickle=False).dtype == dtype
    matched = recons["default"].depth > 0
    assert not np.allclose(recons["default"].depth[matched], recons["no_match"].depth[matched], rtol=1e-3)
    full, alone = recons["full"], recons["r_alone"]
    rigid = full.rigid_flow
    total, r_total = rigid + full.residual_flow, rigid + alone.residual_flow
    assert not np.allclose(total, r_total, atol=1e-2)
    level = MotionSearchConfig().proposal_level
    no_parallax = InferenceOptions(lift=LiftConfig(epipolar_static=False))
    proposal = reconstruct(load_model(), synth_pair, no_parallax, flow_predictor=lambda m, b, d: predict_flow(m, b, d, level))
    assert not np.allclose(proposal.residual_flow, alone.residual_flow, atol=1e-2)  # R's finest level does change it
    is_r = np.abs(total - (rigid + proposal.residual_flow)).max(-1) < 1e-2
    grid = MotionSearchConfig().scales().numpy()
    ratio = (total * rigid).sum(-1) / np.maximum((rigid * rigid).sum(-1), 1e-9)
    s = grid[np.abs(ratio[..., None] - grid).argmin(-1)]
    on_grid = np.abs(total - s[..., None] * rigid).max(-1) < 1e-2
    assert (is_r | on_grid).all()
    assert on_grid.mean() > 0.5  # most pixels keep a multiple of the rigid flow


def _recon_and_ply(tmp_path):
    from drivingscene.export.ply import write_ply
    from drivingscene.gaussians import Reconstruction, save_reconstruction
    from tests.factories import make_pair
    from tests.gaussians.test_core_recon import random_gaussians

    g = random_gaussians(30, degree=1)
    recon = Reconstruction.from_pair(make_pair(num_views=3, height=6, width=8), g)
    return save_reconstruction(recon, tmp_path / "recon.npz"), write_ply(g, tmp_path / "x.ply"), g


def test_info_and_validate_say_what_a_recon_is(tmp_path, capsys):
    recon, _, g = _recon_and_ply(tmp_path)
    assert main(["info", str(recon)]) == 0
    out = capsys.readouterr().out.strip()
    dynamic = int(g.dynamic.sum())
    assert (
        out
        == f"{recon}: a DrivingScene reconstruction (30 Gaussians ({dynamic} dynamic), SH degree 1; 3 cameras (CAM_0, CAM_1, CAM_2) at 8x6)"
    )
    assert main(["validate", str(recon)]) == 0
    captured = capsys.readouterr()
    assert captured.out.startswith(f"{recon}: a DrivingScene reconstruction") and captured.out.strip().endswith(": valid")
    assert "pickled" not in captured.out + captured.err and "frame-pair" not in captured.err


def test_info_and_validate_say_what_a_ply_is(tmp_path, capsys):
    _, ply, _ = _recon_and_ply(tmp_path)
    assert main(["info", str(ply)]) == 0
    expected = (
        "30 Gaussians (0 dynamic), SH degree 1 (stored as degree 3, the higher bands all zero), frame z-up (DrivingScene's world)"
    )
    assert capsys.readouterr().out.strip() == f"{ply}: a 3DGS PLY, {expected}"  # written padded, graphdeco's layout
    assert main(["validate", str(ply)]) == 0
    assert "a 3DGS PLY" in capsys.readouterr().out
    bad = tmp_path / "bad.ply"
    bad.write_text("ply\nformat junk\n")
    assert main(["validate", str(bad)]) == 2
    assert capsys.readouterr().err.strip().startswith(f"{bad}: expected a PLY file")
    # a point cloud (export --kind points): info says what it holds; validate, that it is no 3DGS input
    from drivingscene.export.ply import write_ply

    _, _, g = _recon_and_ply(tmp_path)
    points = write_ply(g, tmp_path / "points.ply", kind="points")
    assert main(["info", str(points)]) == 0
    out = capsys.readouterr().out.strip()
    assert out.startswith(f"{points}: a point cloud PLY, 30 points with colours (x, y, z, red, green, blue)"), out
    assert main(["validate", str(points)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "expected 3DGS properties" in err and "point cloud" in err
    # written at the Gaussians' own degree, nothing padded: no note
    own = write_ply(g, tmp_path / "own.ply", sh_degree=1)
    assert main(["info", str(own)]) == 0
    assert "SH degree 1, frame z-up" in capsys.readouterr().out
