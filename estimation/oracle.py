"""The oracle: hands the simulator's truth over as the estimate (simulation only).

It is the upper bound against which real estimators are measured. It does not fit
the rule that estimators see only samples, by design, and so it is given its truth
source explicitly by whoever builds the env.
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from tensegrity_gym.model.estimate import Estimate
from tensegrity_gym.model.samples import EncoderSample

if TYPE_CHECKING:
    from collections.abc import Callable, Sequence

    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.protocols import SensorCalibration
    from tensegrity_gym.model.samples import GroundTruth, Sample

__all__ = ["OracleEstimator", "latest_rest_lengths"]


def latest_rest_lengths(
    samples: Sequence[Sample], previous: NDArray[np.float64]
) -> NDArray[np.float64]:
    """The newest encoder reading among ``samples`` (m), (m,), else ``previous``."""
    for sample in reversed(samples):
        if isinstance(sample, EncoderSample):
            return sample.rest_lengths
    return previous


class OracleEstimator:
    """Ground truth as the estimate.

    Args:
        truth_source: returns the backend's current ground truth, or None where the
            backend has none (a real robot), which is an error for the oracle.
    """

    needs_camera = False

    def __init__(self, truth_source: Callable[[], GroundTruth | None]) -> None:
        self._truth_source = truth_source
        self._rest_lengths: NDArray[np.float64] = np.zeros(0)
        self._last: Estimate | None = None

    def initialisation_missing(
        self, description: RobotDescription, calibration: SensorCalibration,
        samples: Sequence[Sample],
    ) -> str | None:  # fmt: skip
        """What ``reset`` lacks: ground truth (the simulator's, or motion capture)."""
        if self._truth_source() is None:
            return "no ground truth (the simulator or motion capture) to read the state from"
        return None

    def _estimate(self) -> Estimate:
        truth = self._truth_source()
        if truth is None:
            if self._last is None:
                raise ValueError(
                    "estimator='oracle' needs ground truth (the simulator or motion capture); "
                    "this source has none"
                )
            # A motion-capture frame that did not come: the last state, marked unhealthy.
            return replace(self._last, rest_lengths=self._rest_lengths, healthy=False)
        self._last = Estimate(
            t=truth.t,
            node_positions=truth.node_positions,
            node_velocities=truth.node_velocities,
            com=truth.com,
            rest_lengths=self._rest_lengths,
        )
        return self._last

    def reset(
        self,
        description: RobotDescription,
        calibration: SensorCalibration,
        samples: Sequence[Sample],
        command: NDArray[np.float64],
        rng: np.random.Generator,
    ) -> Estimate:
        self._rest_lengths = latest_rest_lengths(samples, np.asarray(command, dtype=np.float64))
        self._last = None
        return self._estimate()

    def update(self, samples: Sequence[Sample], command: NDArray[np.float64]) -> Estimate:
        self._rest_lengths = latest_rest_lengths(samples, self._rest_lengths)
        return self._estimate()
