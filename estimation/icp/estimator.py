"""The ICP tracker behind the :class:`Estimator` protocol (``estimator="icp"``)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from estimation.health import EstimatorHealth, HealthParams
from estimation.icp.tracker import IcpParams, IcpTracker
from estimation.oracle import latest_rest_lengths
from tensegrity_gym.model.estimate import Estimate
from tensegrity_gym.model.kinematics import center_of_mass
from tensegrity_gym.model.lie import matrix_to_quat
from tensegrity_gym.model.samples import (
    CableLengthSample,
    RgbdFrame,
    ns_to_seconds,
    seconds_to_ns,
)

if TYPE_CHECKING:
    from collections.abc import Sequence

    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.protocols import SensorCalibration
    from tensegrity_gym.model.samples import Sample

__all__ = ["IcpEstimator", "structure_problem"]


def structure_problem(description: RobotDescription) -> str | None:
    """Why the tracker cannot serve ``description``, or None where it can: it follows
    the three rods of a 3-bar prism (Lu et al. 2022), each told apart by its colour; on
    a six-rod robot it loses track (SUPERball: re-initialisations and a CoM error of
    centimetres, against millimetres on the 3-bar)."""
    n = description.n_rods
    if n != 3:
        return (
            f"the RGB-D tracker follows the three rods of a 3-bar prism; this robot has {n} "
            "rods, on which it loses track"
        )
    return None


HEALTH = HealthParams(max_prediction_time=0.0, healthy_when_reinitialised=True)
"""Every update must track a frame; one that re-initialised from a fresh frame has."""


class IcpEstimator:
    """Rod poses from the RGB-D camera and cable lengths (Lu et al. 2022).

    Node velocities are finite differences between frames. A period without a usable
    frame (none, no depth, no colour) keeps the last estimate and reports unhealthy; a
    lost track re-initialises from colour segmentation at the next frame that allows it,
    and says so (``reinitialised``). :attr:`health` counts the losses by cause
    (``"fitness"``, ``"jump"``, ``"out of view"``...: :attr:`TrackResult.cause`).
    """

    needs_camera = True

    def __init__(self, params: IcpParams | None = None) -> None:
        self.params = params or IcpParams()
        self.tracker: IcpTracker | None = None
        self._rng: np.random.Generator | None = None
        self._nodes: NDArray[np.float64] | None = None
        self._velocities: NDArray[np.float64] | None = None
        self._t_ns = 0
        """When the last frame was tracked (ns)."""
        self._rest = np.zeros(0)
        self._cables: NDArray[np.float64] | None = None
        self._need_init = True
        self.health = EstimatorHealth(HEALTH)

    def initialisation_missing(
        self,
        description: RobotDescription,
        calibration: SensorCalibration,
        samples: Sequence[Sample],
    ) -> str | None:
        """What ``reset`` lacks to place the rods: an RGB-D frame with colour and depth,
        and a cable-length reading (which end of a rod is which)."""
        frames = [s for s in samples if isinstance(s, RgbdFrame)]
        if not any(f.rgb.size and f.depth.size for f in frames):
            return "no RGB-D frame with colour and depth (the ICP tracker places the rods by it)"
        if not any(isinstance(s, CableLengthSample) for s in samples):
            return "no cable-length reading (the ICP tracker tells the rods' ends apart by it)"
        return None

    @property
    def reinitialisations(self) -> int:
        """Tracks lost since the reset (each asks for a re-initialisation)."""
        return self.health.reinitialisations

    def _estimate(self, tracked: bool) -> Estimate:
        assert self.tracker is not None and self._nodes is not None
        d = self.tracker.description
        v = self._velocities if self._velocities is not None else np.zeros_like(self._nodes)
        self.health.predicted(0, corrected=tracked)
        estimate = Estimate(
            t=ns_to_seconds(self._t_ns),
            node_positions=self._nodes.copy(),
            node_velocities=v.copy(),
            com=center_of_mass(self._nodes, d.node_masses),
            rest_lengths=self._rest.copy(),
            rod_quaternions=(
                matrix_to_quat(self.tracker.rotations) if self.tracker.nodes is not None else None
            ),
        )
        return self.health.fill(estimate)

    def reset(
        self,
        description: RobotDescription,
        calibration: SensorCalibration,
        samples: Sequence[Sample],
        command: NDArray[np.float64],
        rng: np.random.Generator,
    ) -> Estimate:
        self.tracker = IcpTracker(description, calibration, self.params)
        self._rng = rng
        self._rest = latest_rest_lengths(samples, np.asarray(command, dtype=np.float64))
        self._cables = None
        self._nodes = description.initial_positions.copy()
        self._velocities = None
        self._need_init = True
        self._t_ns = 0
        self.health = EstimatorHealth(HEALTH)
        return self._estimate(self._consume(samples))

    def _consume(self, samples: Sequence[Sample]) -> bool:
        """Take the period's samples; True if a frame was tracked (or initialised)."""
        assert self.tracker is not None and self._rng is not None
        tracked = False
        for s in samples:
            if isinstance(s, CableLengthSample):
                self._cables = s.lengths
            elif isinstance(s, RgbdFrame):
                tracked = self._frame(s) or tracked
        return tracked

    def _frame(self, frame: RgbdFrame) -> bool:
        assert self.tracker is not None and self._rng is not None and self._nodes is not None
        if not np.any(frame.depth > 0):
            return False
        before, t_ns = self._nodes.copy(), seconds_to_ns(frame.t)
        if self._need_init:
            if not self.tracker.initialise(frame, self._cables, self._rng):
                return False
            self._need_init = False
            if self.health.pending is not None:
                self.health.reinitialised(placed=True)
            assert self.tracker.nodes is not None
            self._nodes, self._t_ns, self._velocities = self.tracker.nodes.copy(), t_ns, None
            return True
        result = self.tracker.track(frame, self._cables, self._rng)
        if result.lost:
            self._need_init = True
            self.health.request_reinitialisation(result.cause)
            return False
        self._nodes = result.nodes.copy()
        dt = ns_to_seconds(t_ns - self._t_ns)
        self._velocities = (self._nodes - before) / dt if dt > 0 else None
        self._t_ns = t_ns
        return True

    def update(self, samples: Sequence[Sample], command: NDArray[np.float64]) -> Estimate:
        if self.tracker is None:
            raise RuntimeError("call reset() before update()")
        self._rest = latest_rest_lengths(samples, self._rest)
        return self._estimate(self._consume(samples))
