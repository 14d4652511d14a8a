"""The proprioceptive estimator of papers/002: shape reconstruction and invariant EKF."""

from estimation.inekf.shape import ShapeConfig, ShapeReconstructor, ShapeSolution

__all__ = ["ShapeConfig", "ShapeReconstructor", "ShapeSolution"]
