"""The unscented Kalman filter of Caluwaerts et al. 2016 over a spring-mass model of the robot.

Reference: K. Caluwaerts, J. Bruce, J. M. Friesen and V. SunSpiral, "State estimation
for tensegrity robots", IEEE International Conference on Robotics and Automation
(ICRA), 2016, pp. 1860-1865.
"""

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
