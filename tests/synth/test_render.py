"""The GL passes against closed-form geometry: a ground plane seen by the rig, a translating box."""

from __future__ import annotations

import numpy as np
import pytest

from drivingscene.synth.meshes import MeshBuilder, box, merge
from drivingscene.synth.motion import planar_pose
from drivingscene.synth.render import View
from drivingscene.synth.rig import make_rig

pytestmark = pytest.mark.gl


def _plane(half: float = 500.0) -> np.ndarray:
    b = MeshBuilder()
    b.add(box(-half, half, -half, half, -1.0, 0.0, faces="+z")["+z"], "asphalt", (0.3, 0.3, 0.3))
    return b.build()


def _view(rig, ego_to_world, static_to_world, agents=None):
    agents = np.zeros((0, 4, 4)) if agents is None else agents
    return View(ego_to_world[None] @ rig.cam_to_ego, static_to_world, agents)


def test_depth_of_a_ground_plane_is_the_ray_plane_intersection(renderer):
    rig = make_rig(48, 80)
    ground_to_world = planar_pose(5.0, 7.0, 0.3, 3.0)  # ground plane at world z = 3
    ego_to_world = planar_pose(37.0, -12.0, 0.7, 3.0)
    gpu = renderer.upload(_plane(), [])
    try:
        view = _view(rig, ego_to_world, ground_to_world)
        now, other, flow3 = renderer.render_geometry(gpu, view, view, rig.intrinsics, (48, 80))
    finally:
        gpu.release()
    v, u = np.mgrid[0:48, 0:80].astype(np.float64)
    rays = np.einsum("kij,hwj->khwi", np.linalg.inv(rig.intrinsics), np.stack([u, v, np.ones_like(u)], -1))
    cams = ego_to_world[None] @ rig.cam_to_ego
    down = np.einsum("kj,khwj->khw", cams[:, 2, :3], rays)  # world z of each ray direction
    height = cams[:, 2, 3] - 3.0
    depth = np.where(down < 0, height[:, None, None] / -np.minimum(down, -1e-12), 0.0)
    near = (depth > 0) & (depth < 150)
    covered = other[..., 3] > 0.5
    assert near.sum() > 1000 and np.all(covered[near]) and not np.any(covered[down > 0])
    np.testing.assert_allclose(
        now[..., 2][near], depth[near], rtol=1e-4
    )  # float32 interpolation of a 1 km quad at grazing angles
    np.testing.assert_allclose(
        now[..., :3][near], (rays * depth[..., None])[near], rtol=1e-4, atol=2e-4
    )  # half a pixel would be ~0.5 m here
    assert np.all(flow3[covered] == 0) and not np.any(now[..., 3][covered])  # static


def test_moving_box_has_its_translation_as_scene_flow(renderer):
    rig = make_rig(40, 64)
    b = MeshBuilder()
    b.add(merge(*box(-1, 1, -1, 1, 0, 2).values()), "car_paint", (0.5, 0.1, 0.1))
    gpu = renderer.upload(_plane(), [b.build()])
    ego = planar_pose(0.0, 0.0, 0.0)
    now_pose = planar_pose(8.0, 0.5, 0.2)
    other_pose = planar_pose(9.5, -0.3, 0.2)
    try:
        now, other, flow3 = renderer.render_geometry(
            gpu,
            _view(rig, ego, np.eye(4), now_pose[None]),
            _view(rig, ego, np.eye(4), other_pose[None]),
            rig.intrinsics,
            (40, 64),
        )
    finally:
        gpu.release()
    front = rig.camera_names.index("CAM_FRONT")
    moving = now[front, ..., 3] > 0.5
    assert moving.sum() > 50
    np.testing.assert_allclose(flow3[front][moving][:, :3], np.tile([1.5, -0.8, 0.0], (moving.sum(), 1)), atol=1e-5)
    assert np.all(flow3[front][moving][:, 3] == 1)  # object id 1
    back = rig.camera_names.index("CAM_BACK")
    assert not np.any(now[back, ..., 3] > 0.5)  # the box is ahead: not in the back camera
