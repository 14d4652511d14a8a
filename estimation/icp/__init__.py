"""The ICP tracker of Lu et al. 2022: rod poses from RGB-D frames and cable lengths.

Reference: S. Lu, W. R. Johnson III, K. Wang, X. Huang, J. Booth, R. Kramer-Bottiglio
and K. Bekris, "6N-DoF pose tracking for tensegrity robots", International Symposium
on Robotics Research (ISRR), 2022; Springer Proceedings in Advanced Robotics, 2023.
"""

from estimation.icp.estimator import IcpEstimator
from estimation.icp.tracker import IcpParams, IcpTracker, TrackResult

__all__ = ["IcpEstimator", "IcpParams", "IcpTracker", "TrackResult"]
