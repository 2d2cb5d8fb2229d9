"""Lens distortion removed with OpenCV: a distorted camera becomes a pinhole camera of the same size.

Models (coefficients in OpenCV's order):

- ``"none"``: already a pinhole image; nothing is resampled.
- ``"opencv"``: the Brown-Conrady model of ``cv2.undistort``, k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4
  [tx ty]]]] (4, 5, 8, 12 or 14 numbers). The new camera matrix is ``cv2.getOptimalNewCameraMatrix``
  with alpha 0 (every output pixel has a source), made square: the larger of its two focal lengths
  on both axes, which zooms in a little further about the principal point, so pixels stay square and
  every pixel still has a source.
- ``"fisheye"``: ``cv2.fisheye`` (equidistant with k1..k4, 4 numbers); the new camera matrix is
  ``cv2.fisheye.estimateNewCameraMatrixForUndistortRectify`` with balance 0.

Output pixels whose source lies outside the image are invalid (``valid`` False), as are those that
the camera's own mask marks as not the world (the mask is drawn on the distorted image).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

DISTORTION_MODELS = ("none", "opencv", "fisheye")
# Numbers of coefficients each model accepts.
COEFF_COUNTS = {"none": (0,), "opencv": (4, 5, 8, 12, 14), "fisheye": (4,)}


@dataclass(frozen=True)
class Undistortion:
    """A camera of ``size`` (H, W) resampled to a pinhole camera of the same size."""

    intrinsics: np.ndarray  # [3, 3] float64 of the pinhole (output) image, pixels
    maps: tuple[np.ndarray, np.ndarray] | None  # cv2.remap x and y maps [H, W] float32; None: no resampling
    valid: np.ndarray  # [H, W] bool: output pixels with a source pixel that sees the world

    @classmethod
    def make(
        cls,
        intrinsics: np.ndarray,  # [3, 3] of the distorted image, pixels
        model: str,
        coeffs: np.ndarray,  # [n] in OpenCV's order
        size: tuple[int, int],  # (H, W)
        mask: np.ndarray | None = None,  # [H, W] bool on the distorted image, True = the world
    ) -> Undistortion:
        """Raises ValueError for an unknown model or a wrong number of coefficients."""
        if model not in DISTORTION_MODELS:
            raise ValueError(f"expected a distortion model among {', '.join(DISTORTION_MODELS)}, found {model!r}")
        coeffs = np.asarray(coeffs, dtype=np.float64).reshape(-1)
        if model != "none" and len(coeffs) not in COEFF_COUNTS[model]:
            counts = " or ".join(str(c) for c in COEFF_COUNTS[model])
            raise ValueError(f"expected {counts} coefficients for model {model!r}, found {len(coeffs)}")
        height, width = size
        k = np.asarray(intrinsics, dtype=np.float64)
        world = np.ones(size, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
        if model == "none" or not np.any(coeffs):
            return cls(k.copy(), None, world)
        if model == "opencv":
            new_k, _ = cv2.getOptimalNewCameraMatrix(k, coeffs, (width, height), 0, (width, height))
            new_k = np.array(new_k, dtype=np.float64)
            new_k[0, 0] = new_k[1, 1] = max(new_k[0, 0], new_k[1, 1])  # square pixels (module docstring)
            maps = cv2.initUndistortRectifyMap(k, coeffs, None, new_k, (width, height), cv2.CV_32FC1)
        else:
            new_k = cv2.fisheye.estimateNewCameraMatrixForUndistortRectify(k, coeffs, (width, height), np.eye(3), balance=0.0)
            new_k = np.array(new_k, dtype=np.float64)
            maps = cv2.fisheye.initUndistortRectifyMap(k, coeffs, np.eye(3), new_k, (width, height), cv2.CV_32FC1)
        map_x, map_y = maps
        # the pixel's source centre lies on the image (within half a pixel of its border)
        inside = (map_x >= -0.5) & (map_x <= width - 0.5) & (map_y >= -0.5) & (map_y <= height - 0.5)
        inside &= np.isfinite(map_x) & np.isfinite(map_y)
        if mask is not None:
            seen = cv2.remap(world.astype(np.float32), map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
            inside &= seen > 0.5
        return cls(new_k, (map_x, map_y), inside)

    def image(self, image: np.ndarray) -> np.ndarray:
        """uint8 ``[H, W, 3]`` distorted -> uint8 ``[H, W, 3]`` pinhole (bilinear; edges replicated)."""
        if self.maps is None:
            return image
        return cv2.remap(image, self.maps[0], self.maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
