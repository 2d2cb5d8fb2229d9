"""DrivingScene: feed-forward dynamic 3D Gaussians from one pair of surround-view frames.

Axis letters, used in every shape comment and docstring of the package:

- ``T`` time (keyframes: T = 2; evaluation frames: M)
- ``V`` views (cameras of the rig)
- ``N`` Gaussians
- ``H``, ``W`` image height and width in pixels
- ``C`` channels
- ``K`` spherical-harmonic coefficients per colour channel
- ``B`` batch

Conventions, declared once:

- Quaternions are ``(w, x, y, z)``.
- Cameras use OpenCV axes: x right, y down, z forward. Pixel ``(u, v)`` has its centre at
  integer coordinates, so the top-left pixel centre is ``(0, 0)``.
- The ego frame is x forward, y left, z up; the world frame is z up.
- 4x4 rigid transforms are named ``a_to_b`` and map points in frame ``a`` to frame ``b``.
- Units are metres and seconds; time inside the library is normalised, ``t = 0`` at keyframe 0
  and ``t = 1`` at keyframe 1.
- Images are float in [0, 1] inside the library and uint8 only at file boundaries.
"""

from drivingscene.errors import DrivingSceneError, InputError, SceneFormatError

__version__ = "0.1.0"

__all__ = ["DrivingSceneError", "InputError", "SceneFormatError", "__version__"]
