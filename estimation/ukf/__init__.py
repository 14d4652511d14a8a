"""The unscented Kalman filter of papers/000 over a spring-mass model of the robot."""

from estimation.ukf.estimator import UkfConfig, UkfDiagnostics, UkfEstimator
from estimation.ukf.filter import UnscentedKalmanFilter, UpdateResult
from estimation.ukf.sigma_points import SigmaPointParams
from estimation.ukf.spring_mass import SpringMassModel, SpringMassParams

__all__ = [
    "SigmaPointParams",
    "SpringMassModel",
    "SpringMassParams",
    "UkfConfig",
    "UkfDiagnostics",
    "UkfEstimator",
    "UnscentedKalmanFilter",
    "UpdateResult",
]
