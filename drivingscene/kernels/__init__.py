"""The optional compiled CPU kernels: one typed wrapper per op of ``csrc/*.cpp``, and the choice
between them and the torch paths.

Ground floor: imports only torch and the standard library, so that geometry, gaussians, models
and render all reach the kernels here. Each wrapper is named after its op and documents what it
computes, its shapes and dtypes, and the torch function that is its reference path (the tests
compare both). A function with a torch path asks `available` first::

    if kernels.available(kernels.fb_consistent, backend, flow, flow_back):
        return kernels.fb_consistent(flow, flow_back, alpha, beta)
    ...  # the torch path

``backend`` is "auto" (the compiled op for float32 CPU tensors without gradients where the
extension builds), "cpp" (the op, or a RuntimeError) or "torch". The extension is built on first
use (``build.py``: ``DRIVINGSCENE_BUILD_DIR``, ``DRIVINGSCENE_NO_CPP``); any build failure is
logged once and every function keeps its torch path.
"""

from drivingscene.kernels.build import (
    BACKENDS,
    EXTENSION_NAME,
    OPS,
    available,
    build_extension,
    clear_stale_lock,
    default_build_dir,
    load_extension,
)
from drivingscene.kernels.composite import composite_backward, composite_forward
from drivingscene.kernels.flow import (
    epipolar_parallax,
    fb_consistent,
    lift_dense,
    local_cost_volume,
    rig_stereo,
    rigid_flow_dense,
    search_along_rigid,
)
from drivingscene.kernels.matching import (
    plane_sweep_correlate,
    plane_sweep_correlate_backward,
    plane_sweep_volume,
    see_through_votes,
)
from drivingscene.kernels.pairs import find_pairs, splat_boxes
from drivingscene.kernels.solve import own_layer_solve
from drivingscene.kernels.surfels import activate_surfels, extend_along_rays, pixel_footprints, surfel_frames

__all__ = [
    "BACKENDS",
    "EXTENSION_NAME",
    "OPS",
    "activate_surfels",
    "available",
    "build_extension",
    "clear_stale_lock",
    "composite_backward",
    "composite_forward",
    "default_build_dir",
    "epipolar_parallax",
    "extend_along_rays",
    "fb_consistent",
    "find_pairs",
    "lift_dense",
    "load_extension",
    "local_cost_volume",
    "own_layer_solve",
    "pixel_footprints",
    "plane_sweep_correlate",
    "plane_sweep_correlate_backward",
    "plane_sweep_volume",
    "rig_stereo",
    "rigid_flow_dense",
    "search_along_rigid",
    "see_through_votes",
    "splat_boxes",
    "surfel_frames",
]
