"""Refinement from scratch: the per-scene optimisation a user would run without our model.

The starting point has no learnt part: every input pixel becomes a Gaussian (the oracle's assembly,
`methods/oracle.py`) at the depth where its ray meets the road plane (the ego frame's z = 0),
``far`` metres where it does not (a backdrop), or, with LiDAR, at the depth of the nearest LiDAR
return in its image; nothing moves. Test-time refinement (`methods/refine/__init__.py`: its depth sweep
first, then gradient steps on depth, colour, opacity and scale) then fits it to the two keyframes
within a budget of seconds, exactly as it refines the model's reconstruction.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from drivingscene.data.frame_pair import FramePair
from drivingscene.gaussians.recon import Reconstruction


def flat_initialisation(pair: FramePair, far: float = 40.0, lidar: np.ndarray | None = None) -> Reconstruction:
    """Per-pixel Gaussians at the road plane (else ``far``), or at the nearest return of ``lidar``
    ``[2, V, H, W]`` (0: no return) in images that have any; static, colours as the pixels."""
    from drivingscene.data.road_plane import road_plane_depth
    from drivingscene.eval.baselines import nearest_return_depth
    from drivingscene.methods.oracle import oracle_reconstruction

    depth = road_plane_depth(pair, far=far)
    if lidar is not None:
        nearest = nearest_return_depth(lidar)
        depth = np.where(nearest > 0, nearest, depth).astype(np.float32)
    start = replace(pair, gt_depth=depth, gt_flow=None, gt_scene_flow=None, gt_dynamic=None)
    recon = oracle_reconstruction(start, use_scene_flow=False, refine=0)
    recon.meta["method"] = "flat-init" if lidar is None else "lidar-init"
    return recon


def refine_from_scratch(pair: FramePair, seconds: float, lidar: np.ndarray | None = None) -> Reconstruction:
    """`flat_initialisation` refined for ``seconds`` (no model)."""
    from drivingscene.methods.refine import RefineConfig, refine

    return refine(None, pair, flat_initialisation(pair, lidar=lidar), RefineConfig(seconds=seconds))
