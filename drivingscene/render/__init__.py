"""Differentiable 3D Gaussian rasterization on CPU (torch, optional compiled pair finding).

``rasterize`` renders colour, expected depth and alpha for a batch of cameras;
``rasterize_reference`` is the float64 brute-force renderer it is tested against; ``eval_sh``
evaluates 3DGS spherical harmonics; ``project_gaussians`` is the EWA projection step.
"""

from drivingscene.render.project import Projection, covariances_3d, project_gaussians
from drivingscene.render.rasterize import DEFAULT_MAX_LAYERS, RenderOutput, rasterize
from drivingscene.render.reference import rasterize_reference
from drivingscene.render.sh import eval_sh, rgb_to_sh, sh_to_color

__all__ = [
    "DEFAULT_MAX_LAYERS",
    "Projection",
    "RenderOutput",
    "covariances_3d",
    "eval_sh",
    "project_gaussians",
    "rasterize",
    "rasterize_reference",
    "rgb_to_sh",
    "sh_to_color",
]
