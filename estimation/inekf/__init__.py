"""The proprioceptive estimator of Tong et al. 2024: shape reconstruction and invariant EKF.

Reference: W. Tong, T.-Y. Lin, J. Mi, Y. Jiang, M. Ghaffari and X. Huang, "Tensegrity
robot proprioceptive state estimation with geometric constraints", arXiv:2410.24226,
2024.
"""

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
