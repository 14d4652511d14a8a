"""The proprioceptive estimator of papers/002: shape reconstruction and invariant EKF."""

from estimation.inekf.config import InekfConfig
from estimation.inekf.estimator import InekfEstimator
from estimation.inekf.filter import CorrectionResult, InekfNoise, RightInvariantEkf
from estimation.inekf.shape import ShapeConfig, ShapeReconstructor, ShapeSolution

__all__ = [
    "CorrectionResult",
    "InekfConfig",
    "InekfEstimator",
    "InekfNoise",
    "RightInvariantEkf",
    "ShapeConfig",
    "ShapeReconstructor",
    "ShapeSolution",
]
