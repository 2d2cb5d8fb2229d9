"""Dynamic Gaussians, reconstructions (recon.npz), per-pixel assembly, budget and the oracle."""

from drivingscene.gaussians.assembly import gaussians_from_pixels
from drivingscene.gaussians.core import Gaussians, rgb_to_sh0, sh0_to_rgb
from drivingscene.gaussians.recon import Reconstruction, load_reconstruction, save_reconstruction

__all__ = [
    "Gaussians",
    "Reconstruction",
    "gaussians_from_pixels",
    "load_reconstruction",
    "rgb_to_sh0",
    "save_reconstruction",
    "sh0_to_rgb",
]
