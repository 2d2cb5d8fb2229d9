"""``drivingscene export`` end to end, with its argument errors."""

from __future__ import annotations

import pytest
import torch

from drivingscene.cli import main
from drivingscene.export import read_ply
from drivingscene.gaussians import Reconstruction, save_reconstruction
from tests.factories import make_pair
from tests.gaussians.test_core_recon import random_gaussians


@pytest.fixture
def recon_path(tmp_path):
    g = random_gaussians(30, degree=1)
    hidden = torch.zeros(30, dtype=torch.bool)
    hidden[:5] = True
    recon = Reconstruction.from_pair(make_pair(num_views=3, height=6, width=8), g, hidden=hidden)
    return save_reconstruction(recon, tmp_path / "recon.npz"), g


def test_export_recon_to_3dgs_at_time_skips_hidden(tmp_path, recon_path, capsys):
    path, g = recon_path
    assert main(["export", str(path), "--ply", str(tmp_path / "o.ply"), "--time", "0.5"]) == 0
    back = read_ply(tmp_path / "o.ply")
    torch.testing.assert_close(back.means, g.means_at(0.5)[5:], rtol=0, atol=0)
    assert "25 Gaussians" in capsys.readouterr().out


def test_export_ply_to_points_and_dynamic(tmp_path, recon_path):
    path, g = recon_path
    assert main(["export", str(path), "--ply", str(tmp_path / "d.ply"), "--kind", "dynamic", "--include-hidden"]) == 0
    torch.testing.assert_close(read_ply(tmp_path / "d.ply").flows, g.flows, rtol=0, atol=0)
    assert main(["export", str(tmp_path / "d.ply"), "--ply", str(tmp_path / "p.ply"), "--kind", "points"]) == 0
    assert (tmp_path / "p.ply").stat().st_size > 30 * 15


def test_export_never_overwrites_without_force(tmp_path, recon_path, capsys):
    path, _ = recon_path
    out = tmp_path / "o.ply"
    out.write_text("keep me")
    assert main(["export", str(path), "--ply", str(out)]) == 2
    assert "exists; pass --force" in capsys.readouterr().err
    assert out.read_text() == "keep me"
    assert main(["export", str(path), "--ply", str(out), "--force"]) == 0


@pytest.mark.parametrize(
    "args, message",
    [
        (["--time", "1.5"], "argument --time: expected a number in [0, 1]"),
        (["--time", "abc"], "argument --time: expected a number in [0, 1], found 'abc'"),
        (["--kind", "mesh"], "argument --kind: invalid choice: 'mesh'"),
    ],
)
def test_bad_arguments_are_one_line(tmp_path, recon_path, capsys, args, message):
    path, _ = recon_path
    with pytest.raises(SystemExit) as info:
        main(["export", str(path), "--ply", str(tmp_path / "o.ply"), *args])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err


def test_missing_source_is_one_line(tmp_path, capsys):
    assert main(["export", str(tmp_path / "nope.npz"), "--ply", str(tmp_path / "o.ply")]) == 2
    assert "nope.npz: file not found" in capsys.readouterr().err


def test_export_out_and_sh_degree(tmp_path, recon_path, capsys):
    """``-o/--out`` like every command (``--ply`` is the same option); ``--sh-degree`` reaches the writer."""
    path, g = recon_path
    assert main(["export", str(path), "-o", str(tmp_path / "a.ply"), "--sh-degree", "0"]) == 0
    assert read_ply(tmp_path / "a.ply").sh_degree == 0
    assert main(["export", str(path), "--out", str(tmp_path / "b.ply"), "--sh-degree", "1"]) == 0
    torch.testing.assert_close(read_ply(tmp_path / "b.ply").sh, g.sh[5:].half().float(), rtol=0, atol=0)  # the file's float16
    with pytest.raises(SystemExit) as info:
        main(["export", str(path), "-o", str(tmp_path / "c.ply"), "--sh-degree", "4"])
    assert info.value.code == 2 and "--sh-degree: invalid choice" in capsys.readouterr().err
