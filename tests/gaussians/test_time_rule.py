"""The time rule (drivingscene.gaussians.timing) and its four users agree: torch ``Gaussians``, numpy
``SplatArrays``, the viewer's sorter, and the GLSL of the splat shader run on an EGL context."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from drivingscene_view.sorter import SortRequest, _camera_points, depth_order, make_sort_input
from drivingscene_view.splats import SplatArrays

from drivingscene.errors import InputError
from drivingscene.gaussians import timing
from drivingscene.gaussians.core import Gaussians
from drivingscene.gl import load_program, shader_sources
from drivingscene.resources import shader_path

# 0.6: float32(1 - 0.6) differs from 1 - float32(0.6), so the order of rounding is checked too;
# the largest float32 below 0.5 and 0.5 itself are the edges of "nearest".
TIMES = (0.0, 0.25, float(np.nextafter(np.float32(0.5), np.float32(0))), 0.5, 0.6, 0.75, 1.0)
KEYFRAMES = np.array([0, 1, 0, 1, 0, 1, 0, 1])
UNIT_ROWS = slice(4, 8)  # mean 0 and flows of powers of two: the position is the step times the flow, exactly


def _gaussians() -> Gaussians:
    """Static (rows 0-1) and dynamic Gaussians of both keyframes, all in front of `_camera`."""
    gen = torch.Generator().manual_seed(0)
    means = torch.rand(8, 3, generator=gen) - 0.5
    flows = 0.2 * (torch.rand(8, 3, generator=gen) - 0.5)
    flows[:2] = 0.0
    means[UNIT_ROWS] = 0.0
    flows[UNIT_ROWS] = torch.tensor([[0.25, 0.5, -0.125], [0.25, 0.5, -0.125], [-0.5, 0.125, 0.25], [-0.5, 0.125, 0.25]])
    return Gaussians.create(
        means,
        torch.tensor([[1.0, 0, 0, 0]]).expand(8, 4),
        torch.full((8, 3), 0.01),
        torch.full((8,), 0.9),
        torch.full((8, 3), 0.5),
        flows=flows,
        keyframes=torch.from_numpy(KEYFRAMES),
    )


def _expected(t: float, mode: str) -> tuple[np.ndarray, np.ndarray]:
    """The rule as the issue states it, Gaussian by Gaussian: steps and opacity weights ``[N]``, float32
    (t rounded to float32 first)."""
    t32, one = np.float32(t), np.float32(1.0)
    steps = np.array([t32 if k == 0 else one - t32 for k in KEYFRAMES], np.float32)
    if mode == "fade":
        weights = [one - t32 if k == 0 else t32 for k in KEYFRAMES]
    elif mode == "nearest":
        weights = [float(t < 0.5) if k == 0 else float(t >= 0.5) for k in KEYFRAMES]
    else:  # "all" and the layered blends as opacity weights
        weights = [1.0] * len(KEYFRAMES)
    return steps, np.array(weights, np.float32)


def _check_positions(positions: np.ndarray, g: Gaussians, steps: np.ndarray) -> None:
    means, flows = g.means.double().numpy(), g.flows.double().numpy()
    np.testing.assert_allclose(positions, means + steps[:, None] * flows, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(positions[UNIT_ROWS], steps[UNIT_ROWS, None] * flows[UNIT_ROWS])
    np.testing.assert_array_equal(positions[:2], means[:2])  # static: where they are at every t


def _camera_request(t: float, mode: str, z: float = 0.0) -> SortRequest:
    world_to_cam = np.eye(4)
    world_to_cam[2, 3] = z
    return SortRequest(world_to_cam, np.array([[100.0, 0, 100], [0, 100.0, 100], [0, 0, 1]]), 200, 200, t, mode, keys="float")


@pytest.mark.parametrize("mode", timing.BLEND_MODES)
@pytest.mark.parametrize("t", TIMES)
def test_torch_numpy_and_sorter_follow_the_rule(t, mode):
    g = _gaussians()
    steps, weights = _expected(t, mode)
    splats = SplatArrays.from_gaussians(g)
    data = make_sort_input(splats, np.zeros(3))

    np.testing.assert_array_equal(timing.time_steps(KEYFRAMES, t), steps)
    np.testing.assert_array_equal(timing.time_steps(torch.from_numpy(KEYFRAMES), t).numpy(), steps)
    np.testing.assert_array_equal(g.time_weights(t, mode).numpy(), weights)
    np.testing.assert_array_equal(splats.time_weights(t, mode), weights)
    _check_positions(g.means_at(t).numpy(), g, steps)
    _check_positions(splats.means_at(t), g, steps)
    _check_positions(_camera_points(data, _camera_request(t, mode)).T, g, steps)  # identity camera
    # The sorter culls exactly the splats the weights make invisible (opacity 0.9 * weight < 1/255).
    kept = depth_order(data, _camera_request(t, mode, z=5.0))
    assert sorted(kept.tolist()) == np.flatnonzero(weights > 0).tolist()


def test_torch_time_follows_the_dtype_and_a_tensor_t():
    g = _gaussians().to(dtype=torch.float64)
    t = torch.tensor(0.6, dtype=torch.float64)
    assert g.means_at(t).dtype == g.time_weights(t, "fade").dtype == torch.float64
    torch.testing.assert_close(g.time_weights(t, "fade"), torch.where(g.keyframes == 1, t, 1 - t), rtol=0, atol=0)


def test_unknown_blend_mode_names_the_expected_ones():
    g = _gaussians()
    calls = (
        lambda: g.time_weights(0.5, "blend"),
        lambda: SplatArrays.from_gaussians(g).time_weights(0.5, "blend"),
        lambda: timing.shader_blend_code("blend"),
    )
    for call in calls:
        with pytest.raises(InputError, match="expected one of all, fade, nearest, layers, cameras, found 'blend'"):
            call()


def test_shader_codes_cover_every_mode_and_the_layer_pass():
    assert timing.shader_blend_defines() == {"BLEND_ALL": 0, "BLEND_FADE": 1, "BLEND_NEAREST": 2, "BLEND_LAYER": 3}
    codes = {mode: timing.SHADER_BLENDS[timing.shader_blend_code(mode)] for mode in timing.BLEND_MODES}
    assert codes == {"all": "all", "fade": "fade", "nearest": "nearest", "layers": "all", "cameras": "all"}
    assert timing.SHADER_BLENDS[timing.shader_blend_code("cameras", layer=1)] == "layer"


def test_splat_shader_runs_the_shared_glsl():
    """splat.glsl has no time rule of its own: it includes time_rule.glsl, whose blend codes are injected."""
    rule = shader_path("time_rule").read_text()
    splat = shader_path("splat").read_text()
    assert '#include "time_rule.glsl"' in splat
    assert "u_blend ==" not in splat and "1.0 - u_t" not in splat
    vertex = shader_sources("splat", timing.shader_blend_defines())["vertex_shader"]
    assert rule in vertex and "mean_at(pos.xyz, pos.w, motion.xyz, u_t)" in vertex and "time_weight(pos.w, u_t," in vertex
    for name, code in timing.shader_blend_defines().items():
        assert f"#define {name} {code}\n" in vertex


@pytest.fixture(scope="module")
def probe(gl_ctx):
    """``run(t, code, layer) -> (positions [N, 3], steps [N], weights [N])`` from shaders/time_rule_probe.glsl."""
    g = _gaussians()
    vertices = np.concatenate([g.means.numpy(), g.flows.numpy(), KEYFRAMES[:, None].astype(np.float32)], axis=1)
    prog = load_program(gl_ctx, "time_rule_probe", timing.shader_blend_defines(), varyings=["out_mean", "out_step", "out_weight"])
    vbo = gl_ctx.buffer(np.ascontiguousarray(vertices, np.float32).tobytes())
    vao = gl_ctx.vertex_array(prog, [(vbo, "3f 3f 1f", "in_mean", "in_flow", "in_keyframe")])
    out = gl_ctx.buffer(reserve=len(vertices) * 5 * 4)
    fbo = gl_ctx.simple_framebuffer((1, 1))  # surfaceless EGL has no default framebuffer; draws need one

    def run(t: float, code: int, layer: int = 0):
        fbo.use()
        prog["u_t"].value, prog["u_blend"].value, prog["u_layer"].value = t, code, layer
        vao.transform(out, mode=gl_ctx.POINTS, vertices=len(vertices))
        rows = np.frombuffer(out.read(), np.float32).reshape(len(vertices), 5)
        return rows[:, :3], rows[:, 3], rows[:, 4]

    yield run
    for obj in (vao, vbo, out, fbo, prog):
        obj.release()


@pytest.mark.gl
@pytest.mark.parametrize("mode", timing.BLEND_MODES)
@pytest.mark.parametrize("t", TIMES)
def test_glsl_follows_the_rule(probe, t, mode):
    g = _gaussians()
    steps, weights = _expected(t, mode)
    positions, gl_steps, gl_weights = probe(t, timing.shader_blend_code(mode))
    np.testing.assert_array_equal(gl_steps, steps)
    np.testing.assert_array_equal(gl_weights, weights)
    np.testing.assert_array_equal(gl_weights, timing.time_weights(KEYFRAMES, t, mode))
    _check_positions(positions.astype(np.float64), g, steps)


@pytest.mark.gl
@pytest.mark.parametrize("layer", [0, 1])
@pytest.mark.parametrize("t", (0.0, 0.6, 1.0))
def test_glsl_layer_pass_keeps_one_keyframe(probe, t, layer):
    _, _, weights = probe(t, timing.shader_blend_code("layers", layer), layer)
    np.testing.assert_array_equal(weights, (KEYFRAMES == layer).astype(np.float32))
