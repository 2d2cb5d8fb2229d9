"""The benchmark scene (one Gaussian per pixel of 6 surround views) and the `bench raster` command."""

from __future__ import annotations

import pytest
import torch

from drivingscene.bench.raster_speed import measure, surround_scene
from drivingscene.cli import main
from drivingscene.render import rasterize


def test_surround_scene_is_one_pixel_sized_gaussian_per_pixel():
    scene = surround_scene(12, 22)
    n = 6 * 12 * 22
    assert scene["means"].shape == (n, 3) and scene["colors"].shape == (n, 3) and scene["viewmats"].shape == (6, 4, 4)
    # Camera 0's Gaussians project back onto its own pixel grid, with scale ≈ depth / focal.
    cam = scene["means"][: 12 * 22] @ scene["viewmats"][0, :3, :3].T + scene["viewmats"][0, :3, 3]
    uv = cam[:, :2] / cam[:, 2:] * scene["Ks"][0, 0, 0] + scene["Ks"][0, :2, 2]
    v, u = torch.meshgrid(torch.arange(12.0), torch.arange(22.0), indexing="ij")
    torch.testing.assert_close(uv, torch.stack([u, v], -1).reshape(-1, 2), atol=1e-3, rtol=0)
    ratio = scene["scales"][: 12 * 22] * scene["Ks"][0, 0, 0] / cam[:, 2:]
    assert ratio.min() >= 0.8 - 1e-5 and ratio.max() <= 1.2 + 1e-5
    out = rasterize(**scene, max_layers=64, backend="torch")
    assert out.alphas.mean() > 0.95


@pytest.fixture
def restore_threads():
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)  # `--in-process --threads 1` changes this process's setting


def test_measure_and_command_write_a_markdown_table(tmp_path, restore_threads):
    row = measure("8x12", "torch", 8, repeats=1)
    assert row["gaussians"] == 6 * 8 * 12 and row["fwd"] > 0 and row["fwd_bwd"] > 0 and row["peak_fwd_bwd_mib"] >= 0
    out = tmp_path / "raster.md"
    args = ["bench", "raster", "--sizes", "8x12", "--backends", "torch", "--repeats", "1", "--threads", "1"]
    args += ["--max-layers", "4,8", "--in-process", "--out", str(out)]
    assert main(args) == 0
    text = out.read_text()
    assert "| 6×8×12 | 576 | RGB | torch | 4 | 1 |" in text and "| 6×8×12 | 576 | RGB | torch | 8 | 1 |" in text
    assert "Machine:" in text
