"""Layer 1: state estimators that turn raw samples into an :class:`Estimate`."""

from estimation.oracle import OracleEstimator

__all__ = ["OracleEstimator"]
