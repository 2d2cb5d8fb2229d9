"""Pure geometry functions (torch, any float dtype): rigid transforms, quaternions (w, x, y, z),
pose interpolation, pinhole cameras and flow."""

from drivingscene.geometry.camera import pixel_grid, project, scale_intrinsics, unproject
from drivingscene.geometry.flow import backward_warp, forward_backward_consistency, rigid_flow
from drivingscene.geometry.se3 import (
    interpolate_pose,
    invert_rigid,
    matrix_to_quat,
    quat_multiply,
    quat_to_matrix,
    slerp,
    transform_points,
)

__all__ = [
    "backward_warp",
    "forward_backward_consistency",
    "interpolate_pose",
    "invert_rigid",
    "matrix_to_quat",
    "pixel_grid",
    "project",
    "quat_multiply",
    "quat_to_matrix",
    "rigid_flow",
    "scale_intrinsics",
    "slerp",
    "transform_points",
    "unproject",
]
