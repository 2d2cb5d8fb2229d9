"""PLY: standard 3DGS layout, exact round trips, other tools' files, malformed files."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from drivingscene.errors import InputError
from drivingscene.export import read_ply, write_ply
from drivingscene.export.ply import ply_up_axis
from tests.gaussians.test_core_recon import random_gaussians

FIELDS = ("means", "quats", "log_scales", "opacity_logits", "sh")


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_3dgs_round_trip_is_bit_exact(tmp_path, degree):
    g = random_gaussians(64, degree=degree)
    back = read_ply(write_ply(g, tmp_path / "g.ply"))
    for name in FIELDS:
        torch.testing.assert_close(getattr(back, name), getattr(g, name), rtol=0, atol=0)
    assert not back.dynamic.any()  # the standard layout has no flow


def test_rewriting_a_read_file_gives_identical_bytes(tmp_path):
    first = write_ply(random_gaussians(30, degree=2), tmp_path / "a.ply")
    second = write_ply(read_ply(first), tmp_path / "b.ply")
    assert first.read_bytes() == second.read_bytes()


def test_header_is_the_standard_layout(tmp_path):
    path = write_ply(random_gaussians(5, degree=1), tmp_path / "g.ply", sh_degree=1)
    ply = PlyData.read(str(path))
    names = [p.name for p in ply["vertex"].properties]
    expected = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    expected += [f"f_rest_{i}" for i in range(9)] + ["opacity", "scale_0", "scale_1", "scale_2"]
    expected += ["rot_0", "rot_1", "rot_2", "rot_3"]
    assert names == expected
    assert ply.byte_order == "<" and not ply.text
    assert all(p.val_dtype in ("f4", "float32") for p in ply["vertex"].properties)


def test_f_rest_is_grouped_by_channel_and_activations_are_stored_raw(tmp_path):
    g = random_gaussians(3, degree=1)
    vertex = PlyData.read(str(write_ply(g, tmp_path / "g.ply", sh_degree=1)))["vertex"]
    # 3 higher-order coefficients per channel: f_rest_0..2 red, 3..5 green, 6..8 blue.
    np.testing.assert_array_equal(vertex["f_rest_0"], g.sh[:, 1, 0].numpy())
    np.testing.assert_array_equal(vertex["f_rest_3"], g.sh[:, 1, 1].numpy())
    np.testing.assert_array_equal(vertex["f_rest_8"], g.sh[:, 3, 2].numpy())
    np.testing.assert_allclose(1 / (1 + np.exp(-vertex["opacity"])), g.opacities.numpy(), rtol=1e-6)
    np.testing.assert_allclose(np.exp(vertex["scale_1"]), g.scales[:, 1].numpy(), rtol=1e-6)
    np.testing.assert_array_equal(vertex["rot_0"], g.quats[:, 0].numpy())  # w first


@pytest.mark.parametrize("kind", ["3dgs", "dynamic"])
def test_sh_is_padded_to_degree_3_by_default_in_graphdeco_order(tmp_path, kind):
    g = random_gaussians(4, degree=1)
    vertex = PlyData.read(str(write_ply(g, tmp_path / "g.ply", kind=kind)))["vertex"]
    rest = sorted(int(p.name.split("_")[-1]) for p in vertex.properties if p.name.startswith("f_rest_"))
    assert rest == list(range(45))
    # graphdeco: f_rest_{c * 15 + k} is channel c's coefficient k + 1; bands 2 and 3 are zero.
    for c in range(3):
        for k in range(15):
            expected = g.sh[:, k + 1, c].numpy() if k < 3 else np.zeros(4, np.float32)
            np.testing.assert_array_equal(vertex[f"f_rest_{c * 15 + k}"], expected)
    assert read_ply(tmp_path / "g.ply").sh_degree == 1  # trailing zero bands dropped on reading


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_degree_chooses_the_written_degree(tmp_path, degree):
    g = random_gaussians(6, degree=2)
    path = write_ply(g, tmp_path / "g.ply", sh_degree=degree)
    names = [p.name for p in PlyData.read(str(path))["vertex"].properties]
    assert sum(n.startswith("f_rest_") for n in names) == 3 * (degree + 1) ** 2 - 3
    back = read_ply(path)
    torch.testing.assert_close(back.sh, g.with_sh_degree(min(degree, 2)).sh, rtol=0, atol=0)


def test_sh_degree_is_checked(tmp_path):
    g = random_gaussians(3)
    with pytest.raises(InputError, match="--sh-degree: expected 0 to 3"):
        write_ply(g, tmp_path / "g.ply", sh_degree=4)
    with pytest.raises(InputError, match="points PLY"):
        write_ply(g, tmp_path / "p.ply", kind="points", sh_degree=0)


def test_dynamic_round_trip_keeps_flow_keyframe_and_camera(tmp_path):
    g = random_gaussians(40, degree=1)
    back = read_ply(write_ply(g, tmp_path / "d.ply", kind="dynamic"))
    for name in FIELDS + ("flows", "keyframes", "cameras"):
        torch.testing.assert_close(getattr(back, name), getattr(g, name), rtol=0, atol=0)


def test_time_moves_dynamic_gaussians(tmp_path):
    g = random_gaussians(40)
    back = read_ply(write_ply(g, tmp_path / "t.ply", t=0.5))
    torch.testing.assert_close(back.means, g.means_at(0.5), rtol=0, atol=0)
    with pytest.raises(InputError, match="omit --time"):
        write_ply(g, tmp_path / "x.ply", kind="dynamic", t=0.5)


def test_points_are_plain_coloured_vertices(tmp_path):
    g = random_gaussians(20)
    vertex = PlyData.read(str(write_ply(g, tmp_path / "p.ply", kind="points")))["vertex"]
    assert [p.name for p in vertex.properties] == ["x", "y", "z", "red", "green", "blue"]
    assert vertex["red"].dtype == np.uint8
    np.testing.assert_array_equal(vertex["green"], np.round(g.colors()[:, 1].numpy() * 255).astype(np.uint8))
    with pytest.raises(InputError, match="plain point cloud"):
        read_ply(tmp_path / "p.ply")


def _foreign_ply(path, n=10, rest=45, extra=("filter_3D",), text=False, drop=()):
    """A file laid out like other tools write them (extra properties, any order of extras)."""
    rng = np.random.default_rng(1)
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(rest)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3", *extra]
    names = [n_ for n_ in names if n_ not in drop]
    arr = np.empty(n, dtype=[(name, "<f4") for name in names])
    for name in names:
        arr[name] = rng.normal(size=n).astype(np.float32)
    PlyData([PlyElement.describe(arr, "vertex")], text=text).write(str(path))
    return arr


@pytest.mark.parametrize("rest, degree", [(0, 0), (9, 1), (24, 2), (45, 3)])
def test_reads_files_from_other_tools(tmp_path, rest, degree):
    arr = _foreign_ply(tmp_path / "f.ply", rest=rest)
    g = read_ply(tmp_path / "f.ply")
    assert g.sh_degree == degree and len(g) == 10
    np.testing.assert_array_equal(g.opacity_logits.numpy(), arr["opacity"])
    if rest:
        np.testing.assert_array_equal(g.sh[:, 1, 2].numpy(), arr[f"f_rest_{2 * rest // 3}"])


def test_reads_ascii_ply(tmp_path):
    arr = _foreign_ply(tmp_path / "a.ply", rest=9, text=True)
    np.testing.assert_array_equal(read_ply(tmp_path / "a.ply").means[:, 2].numpy(), arr["z"])


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda p: p.write_bytes(b"hello"), "expected a PLY file"),
        (lambda p: None, "file not found"),
        (lambda p: _foreign_ply(p, drop=("opacity",)), "expected 3DGS properties opacity"),
        (lambda p: _foreign_ply(p, rest=7), "expected 0, 9, 24 or 45 f_rest_"),
        (lambda p: _foreign_ply(p, rest=10, drop=("f_rest_3",)), "numbered from 0"),
    ],
)
def test_malformed_files_give_one_line_errors(tmp_path, make, message):
    path = tmp_path / "bad.ply"
    make(path)
    with pytest.raises(InputError, match=message) as info:
        read_ply(path)
    assert "\n" not in str(info.value) and str(path) in str(info.value)


def test_nan_and_zero_quaternion_rejected(tmp_path):
    path = tmp_path / "nan.ply"
    arr = _foreign_ply(path)
    arr["x"][3] = np.nan
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(path))
    with pytest.raises(InputError, match="property 'x': expected finite"):
        read_ply(path)
    arr["x"][3] = 0
    for i in range(4):
        arr[f"rot_{i}"][0] = 0
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(path))
    with pytest.raises(InputError, match="non-zero quaternions"):
        read_ply(path)


def test_no_vertex_element(tmp_path):
    path = tmp_path / "face.ply"
    PlyData([PlyElement.describe(np.zeros(2, dtype=[("a", "<f4")]), "face")]).write(str(path))
    with pytest.raises(InputError, match="expected a 'vertex' element"):
        read_ply(path)


def test_the_header_states_the_frame(tmp_path):
    g = random_gaussians(5)
    ours = write_ply(g, tmp_path / "ours.ply")
    assert b"comment DrivingScene frame z-up\n" in ours.read_bytes()[:400] and ply_up_axis(ours) == "z"
    y_down = write_ply(g, tmp_path / "y.ply", kind="points", up="-y")
    assert ply_up_axis(y_down) == "-y"
    text = ours.read_bytes()
    older = tmp_path / "older.ply"  # written before the frame was stated: ours, z-up
    older.write_bytes(text.replace(b"comment DrivingScene frame z-up\n", b"comment DrivingScene\n"))
    assert ply_up_axis(older) == "z"
    foreign = tmp_path / "foreign.ply"  # another tool's: y-down
    foreign.write_bytes(text.replace(b"comment DrivingScene frame z-up\n", b"comment made by another tool\n"))
    assert ply_up_axis(foreign) == "-y"
    bad = tmp_path / "bad.ply"
    bad.write_bytes(text.replace(b"frame z-up", b"frame x-up"))
    with pytest.raises(InputError, match="expected one of z-up, y-down"):
        ply_up_axis(bad)
    with pytest.raises(InputError, match="up axis"):
        write_ply(g, tmp_path / "x.ply", up="y")
