"""One picture: the viewer's GL path (window and ``--headless``) and the CPU rasterizer that the
benchmarks score draw a reconstruction alike, at a rig camera and at a magnified size, with the
renderer settings each file asks for (the low-pass of ours and of 3DGS files from other tools)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch
from drivingscene_view.__main__ import magnification, main

from drivingscene.export.ply import write_ply
from drivingscene.gaussians.recon import save_reconstruction
from drivingscene.geometry.camera import scale_intrinsics
from drivingscene.methods.oracle import oracle_reconstruction
from drivingscene.render.project import EPS2D, EPS2D_3DGS
from drivingscene.render.scene import LayerBlend, render_gaussians, source_axes
from drivingscene.sources import open_source


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return 10 * math.log10(1.0 / max(float(((a - b) ** 2).mean()), 1e-12))


@pytest.mark.gl
@pytest.mark.parametrize("scale, t", [(1, 0.0), (2, 0.5)])
def test_headless_rig_views_are_the_cpu_rasterizers(synth_pair_96, tmp_path, scale, t):
    recon = oracle_reconstruction(synth_pair_96)
    path = save_reconstruction(recon, tmp_path / "recon.npz")
    out = tmp_path / "views"
    name = recon.camera_names[1]
    argv = [str(path), "--headless", "--out", str(out), "--time", str(t), "--camera", name, "--scale", str(scale), "--no-ply"]
    assert main(argv) == 0
    gl = cv2.cvtColor(cv2.imread(str(out / f"{name}_t{t:.3f}.png")), cv2.COLOR_BGR2RGB).astype(np.float64) / 255
    height, width = recon.image_size
    assert gl.shape == (height * scale, width * scale, 3)
    k = scale_intrinsics(torch.from_numpy(recon.intrinsics[1:2]).float(), scale, scale)

    def cpu(rule: LayerBlend) -> np.ndarray:
        return render_gaussians(
            recon.visible(), t, recon.world_to_cam_at(t)[1:2].float(), k, height * scale, width * scale,
            sky_sh=recon.sky_sh, ground=recon.ground, blend="cameras", source_axes=source_axes(recon), max_layers=256,
            layer_blend=rule,
        ).colors[0].clamp(0, 1).numpy()  # fmt: skip

    same = cpu(LayerBlend())
    assert _psnr(gl, np.round(same * 255) / 255) >= 40.0
    assert same.std() > 0.05
    # the rule is the one both draw with: each layer's surface averaged, not composited
    composited = cpu(LayerBlend(surface_tolerance=0.0))
    assert _psnr(gl, np.round(same * 255) / 255) > _psnr(gl, np.round(composited * 255) / 255) + 3.0


def test_the_low_pass_follows_the_file(tmp_path, synth_pair_96):
    recon = oracle_reconstruction(synth_pair_96)
    ours = write_ply(recon.gaussians, tmp_path / "ours.ply")
    assert open_source(ours).low_pass == EPS2D
    # the same Gaussians in a file from another tool (no DrivingScene comment): 3DGS's 0.3 px^2
    lines = ours.read_bytes().split(b"\n")
    foreign = tmp_path / "foreign.ply"
    foreign.write_bytes(b"\n".join(line for line in lines if not line.startswith(b"comment DrivingScene")))
    assert open_source(foreign).low_pass == EPS2D_3DGS
    assert open_source(save_reconstruction(recon, tmp_path / "recon.npz")).low_pass == EPS2D


def test_scale_is_checked(capsys, tmp_path):
    assert magnification("4") == 4
    for bad in ("0", "9", "2.5"):
        with pytest.raises(Exception):
            magnification(bad)
    with pytest.raises(SystemExit):
        main([str(tmp_path / "x.npz"), "--scale", "2"])  # only with --headless
    assert "--scale" in capsys.readouterr().err
