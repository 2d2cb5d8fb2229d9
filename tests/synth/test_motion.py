"""Exact motion: constant-curvature paths, the road frame, movers (pure numpy)."""

from __future__ import annotations

import numpy as np
import pytest

from drivingscene.synth.motion import Mover, Path, RoadFrame, arc_offset


@pytest.mark.parametrize("curvature", [0.0, 1 / 37.0, -1 / 150.0])
def test_arc_offset_matches_numerical_integration(curvature):
    u = np.linspace(0, 30, 30001)
    heading = curvature * u
    x = np.concatenate([[0], np.cumsum((np.cos(heading[1:]) + np.cos(heading[:-1])) / 2 * np.diff(u))])
    y = np.concatenate([[0], np.cumsum((np.sin(heading[1:]) + np.sin(heading[:-1])) / 2 * np.diff(u))])
    fwd, left = arc_offset(u[::1000], curvature)
    np.testing.assert_allclose(fwd, x[::1000], atol=1e-6)
    np.testing.assert_allclose(left, y[::1000], atol=1e-6)


def test_path_is_continuous_and_turns_a_quarter():
    radius = 7.0
    path = Path(3.0, -2.0, 0.4, ((10.0, 0.0), (np.pi / 2 * radius, 1 / radius), (20.0, 0.0)))
    for joint in (10.0, 10.0 + np.pi / 2 * radius):
        a, b = np.array(path.pose(joint - 1e-9)), np.array(path.pose(joint + 1e-9))
        np.testing.assert_allclose(a, b, atol=1e-7)
    assert path.pose(100.0)[2] - path.pose(0.0)[2] == pytest.approx(np.pi / 2)
    # unit speed: small steps cover their length
    for u in (5.0, 12.0, 25.0):
        a, b = np.array(path.pose(u)[:2]), np.array(path.pose(u + 1e-4)[:2])
        assert np.linalg.norm(b - a) == pytest.approx(1e-4, rel=1e-6)


@pytest.mark.parametrize("curvature", [0.0, 1 / 200.0, -1 / 170.0])
def test_road_frame_round_trip_and_lanes_keep_their_offset(curvature):
    road = RoadFrame(curvature)
    for s, d in [(10.0, 3.0), (-50.0, -7.0), (120.0, 20.0)]:
        x, y = road.to_xy(s, d)
        assert road.to_sd(float(x), float(y)) == pytest.approx((s, d), abs=1e-9)
    for forward in (True, False):
        lane = road.lane_path(-1.75 if forward else 1.75, 5.0, forward)
        for u in (-20.0, 0.0, 33.0):
            x, y, heading = lane.pose(u)
            s, d = road.to_sd(x, y)
            assert d == pytest.approx(-1.75 if forward else 1.75, abs=1e-9)
            expected = road.heading(s) + (0 if forward else np.pi)
            assert np.cos(heading - expected) == pytest.approx(1.0, abs=1e-12)


def test_mover_speed_and_reference_time():
    mover = Mover(RoadFrame(1 / 80).lane_path(-1.6, 0.0), speed=9.0, u0=2.0, t_ref=13.5)
    a, b = mover.position(13.5), mover.position(13.6)
    assert np.linalg.norm(b - a) == pytest.approx(0.9, rel=1e-4)
    np.testing.assert_allclose(mover.road_pose(13.5)[:2, 3], mover.path.pose(2.0)[:2])
