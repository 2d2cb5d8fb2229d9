"""Networks: D (depth), P (Gaussian head), R (residual flow) and their composition root."""

from drivingscene.models.model import DrivingSceneModel, ModelConfig

__all__ = ["DrivingSceneModel", "ModelConfig"]
