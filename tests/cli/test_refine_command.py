"""`drivingscene reconstruct --refine SECONDS [--lidar] [--adapt K]`: one-line errors, and a run that
writes a refined reconstruction with its steps and seconds per step in ``meta``."""

from __future__ import annotations

from dataclasses import replace

import pytest

from drivingscene.cli import main
from drivingscene.data import save_frame_pair
from drivingscene.gaussians.recon import load_reconstruction
from tests.eval.test_bench_results import tiny_weights  # noqa: F401  (fixture)
from tests.factories import make_pair


def _run(args: list[str]) -> int:
    """``main``'s exit code, whether it returns it or argparse exits with it."""
    try:
        return main(args)
    except SystemExit as e:
        return int(e.code)


@pytest.fixture
def scenes(tmp_path):
    pair = make_pair(num_views=2, height=24, width=32)
    return save_frame_pair(pair, tmp_path / "scene.npz"), save_frame_pair(replace(pair, gt_depth=None), tmp_path / "nolidar.npz")


@pytest.mark.parametrize(
    "flags, needle",
    [
        (["--refine", "-1"], "--refine"),
        (["--refine", "soon"], "--refine"),
        (["--refine", "inf"], "--refine"),
        (["--lidar"], "--lidar: only with --refine"),
        (["--adapt", "3"], "--adapt: only with --refine"),
        (["--refine", "1", "--adapt", "-2"], "--adapt"),
        (["--refine", "1", "--refine-steps", "0"], "--refine-steps"),
        (["--adapt-share", "0.5"], "--adapt-share: only with --refine"),
        (["--refine", "1", "--adapt-share", "0"], "--adapt-share"),
        (["--refine", "1", "--adapt-scale", "2"], "--adapt-scale"),
        (["--budget", "0"], "--budget"),
        (["--budget", "1.5"], "--budget"),
        (["--budget", "0.3", "--per-pixel"], "--per-pixel and --budget"),
    ],
)
def test_bad_refine_flags_are_one_line_errors(scenes, tmp_path, capsys, flags, needle):
    code = _run(["reconstruct", str(scenes[0]), "-o", str(tmp_path / "r.npz"), *flags])
    err = capsys.readouterr().err.strip()
    assert code == 2 and needle in err and "\n" not in err and "Traceback" not in err
    assert not (tmp_path / "r.npz").exists()


def test_lidar_needs_lidar_in_the_scene(scenes, tmp_path, capsys, tiny_weights):  # noqa: F811
    code = main(
        ["reconstruct", str(scenes[1]), "-o", str(tmp_path / "r.npz"), "--weights", str(tiny_weights), "--refine", "1", "--lidar"]
    )
    err = capsys.readouterr().err.strip()
    assert code == 2 and "--lidar" in err and "gt_depth" in err and "\n" not in err


def test_refined_reconstruction_is_written(scenes, tmp_path, capsys, tiny_weights):  # noqa: F811
    out = tmp_path / "r.npz"
    args = ["reconstruct", str(scenes[0]), "-o", str(out), "--weights", str(tiny_weights)]
    assert main([*args, "--refine", "60", "--refine-steps", "1", "--lidar"]) == 0
    assert "refined" in capsys.readouterr().out
    recon = load_reconstruction(out)
    meta = recon.meta["refinement"]
    assert meta["steps"] == 1 and meta["step_s"] > 0 and meta["budget_s"] == 60
    assert recon.meta["method"] == "drivingscene+refine"
    # adapting D in all of the budget with full-size losses, then one gradient step
    assert (
        main(
            [
                *args,
                "--refine",
                "60",
                "--refine-steps",
                "1",
                "--adapt",
                "1",
                "--adapt-share",
                "1",
                "--adapt-scale",
                "1",
                "--force",
            ]
        )
        == 0
    )
    meta = load_reconstruction(out).meta["refinement"]
    assert meta["adapt"]["steps"] == 1 and meta["steps"] == 1
