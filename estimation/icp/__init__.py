"""The ICP tracker of papers/003: rod poses from RGB-D frames and cable lengths."""

from estimation.icp.estimator import IcpEstimator
from estimation.icp.tracker import IcpParams, IcpTracker, TrackResult

__all__ = ["IcpEstimator", "IcpParams", "IcpTracker", "TrackResult"]
