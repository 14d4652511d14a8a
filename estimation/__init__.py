"""Layer 1: state estimators that turn raw samples into an :class:`Estimate`."""

from estimation.oracle import OracleEstimator
from estimation.ukf import UkfConfig, UkfEstimator

__all__ = ["OracleEstimator", "UkfConfig", "UkfEstimator"]
