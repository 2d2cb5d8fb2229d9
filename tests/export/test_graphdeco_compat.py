"""Our PLYs load in other tools as they are: graphdeco's ``GaussianModel.load_ply`` (re-implemented
here from its source, independently of ``read_ply``) on every kind meant for 3DGS tools, and plain
point readers (plyfile, open3d where installed) on "points"."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from plyfile import PlyData

from drivingscene.export import write_ply
from tests.gaussians.test_core_recon import random_gaussians

SH_C0 = 0.28209479177387814  # graphdeco utils/sh_utils.py


def graphdeco_load_ply(path, max_sh_degree: int = 3) -> dict[str, np.ndarray]:
    """graphdeco-inria/gaussian-splatting ``GaussianModel.load_ply`` followed by its activations
    (``get_xyz``, ``get_scaling`` = exp, ``get_opacity`` = sigmoid, ``get_rotation`` = normalise)."""
    plydata = PlyData.read(str(path))
    element = plydata.elements[0]  # graphdeco reads the first element, whatever its name
    xyz = np.stack((np.asarray(element["x"]), np.asarray(element["y"]), np.asarray(element["z"])), axis=1)
    opacities = np.asarray(element["opacity"])[..., np.newaxis]
    features_dc = np.zeros((xyz.shape[0], 3, 1))
    for i in range(3):
        features_dc[:, i, 0] = np.asarray(element[f"f_dc_{i}"])
    extra_f_names = [p.name for p in element.properties if p.name.startswith("f_rest_")]
    extra_f_names = sorted(extra_f_names, key=lambda x: int(x.split("_")[-1]))
    assert len(extra_f_names) == 3 * (max_sh_degree + 1) ** 2 - 3  # the assertion that rejected SH degree 0
    features_extra = np.zeros((xyz.shape[0], len(extra_f_names)))
    for idx, name in enumerate(extra_f_names):
        features_extra[:, idx] = np.asarray(element[name])
    features_extra = features_extra.reshape((features_extra.shape[0], 3, (max_sh_degree + 1) ** 2 - 1))
    scale_names = sorted((p.name for p in element.properties if p.name.startswith("scale_")), key=lambda x: int(x.split("_")[-1]))
    scales = np.stack([np.asarray(element[name]) for name in scale_names], axis=1)
    rot_names = sorted((p.name for p in element.properties if p.name.startswith("rot")), key=lambda x: int(x.split("_")[-1]))
    rots = np.stack([np.asarray(element[name]) for name in rot_names], axis=1)
    return {
        "xyz": xyz,
        "features_dc": features_dc.transpose(0, 2, 1),  # [N, 1, 3]
        "features_rest": features_extra.transpose(0, 2, 1),  # [N, 15, 3]
        "scaling": np.exp(scales),
        "opacity": 1.0 / (1.0 + np.exp(-opacities[:, 0])),
        "rotation": rots / np.linalg.norm(rots, axis=1, keepdims=True),
    }


@pytest.mark.parametrize("kind, t", [("3dgs", None), ("3dgs", 0.0), ("3dgs", 0.5), ("dynamic", None)])
@pytest.mark.parametrize("degree", [0, 1, 3])
def test_graphdeco_loads_every_3dgs_kind(tmp_path, kind, t, degree):
    g = random_gaussians(40, degree=degree)
    loaded = graphdeco_load_ply(write_ply(g, tmp_path / "g.ply", kind=kind, t=t))
    expected_means = g.means if t is None else g.means_at(t)
    np.testing.assert_allclose(loaded["xyz"], expected_means.numpy(), rtol=0, atol=0)
    np.testing.assert_allclose(loaded["scaling"], g.scales.numpy(), rtol=1e-6)
    np.testing.assert_allclose(loaded["opacity"], g.opacities.numpy(), rtol=1e-6)
    np.testing.assert_allclose(loaded["rotation"], torch.nn.functional.normalize(g.quats, dim=1).numpy(), atol=1e-6)
    sh = g.with_sh_degree(3).sh.numpy()
    np.testing.assert_array_equal(loaded["features_dc"][:, 0], sh[:, 0])
    np.testing.assert_array_equal(loaded["features_rest"], sh[:, 1:])
    rgb = np.clip(0.5 + SH_C0 * loaded["features_dc"][:, 0], 0, 1)  # graphdeco's SH2RGB of the DC term
    np.testing.assert_allclose(rgb, g.colors().numpy(), atol=1e-6)


def test_a_lower_sh_degree_is_what_was_asked_for(tmp_path):
    path = write_ply(random_gaussians(5, degree=3), tmp_path / "g.ply", sh_degree=1)
    with pytest.raises(AssertionError):
        graphdeco_load_ply(path)  # at its default degree 3
    assert graphdeco_load_ply(path, max_sh_degree=1)["features_rest"].shape == (5, 3, 3)


def test_points_read_as_coloured_points(tmp_path):
    g = random_gaussians(30)
    path = write_ply(g, tmp_path / "p.ply", kind="points", t=0.5)
    vertex = PlyData.read(str(path))["vertex"]
    xyz = np.stack([vertex[a] for a in "xyz"], axis=1)
    np.testing.assert_array_equal(xyz, g.means_at(0.5).numpy())
    rgb = np.stack([vertex[c] for c in ("red", "green", "blue")], axis=1)
    np.testing.assert_array_equal(rgb, np.round(g.colors().numpy() * 255).astype(np.uint8))


def test_open3d_reads_points(tmp_path):
    o3d = pytest.importorskip("open3d")
    g = random_gaussians(30)
    cloud = o3d.io.read_point_cloud(str(write_ply(g, tmp_path / "p.ply", kind="points")))
    np.testing.assert_allclose(np.asarray(cloud.points), g.means.numpy(), atol=1e-6)
    np.testing.assert_allclose(np.asarray(cloud.colors), np.round(g.colors().numpy() * 255) / 255, atol=1e-6)
