"""Timestamped raw measurements, in SI units: what a robot's sensors give.

The simulator, a hardware driver and a log replay all produce these same types, so
any estimator runs on any of them. Times are seconds from the source's clock origin,
each a whole number of nanoseconds (``ns_to_seconds(n)``) as ROS stamps are, so a
sample survives a trip through a bag bit for bit. The origin is the robot-clock ns of
time 0, the source's ``Backend.clock_origin_ns`` (0 for the simulator, a bag's first log
time floored to a second, a robot link's wall clock at reset): times stay small, which
float seconds hold to the nanosecond, whatever the robot's clock reads. Quaternions
are (x, y, z, w), rotating body vectors into the world frame (z up).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TypeAlias

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "GROUND_TRUTH",
    "SAMPLE_KINDS",
    "AhrsSample",
    "CableLengthSample",
    "ContactSample",
    "EncoderSample",
    "GroundTruth",
    "ImuSample",
    "RgbdFrame",
    "Sample",
    "UwbRangeSample",
    "ns_to_seconds",
    "seconds_to_ns",
]

FloatArray: TypeAlias = NDArray[np.float64]


def seconds_to_ns(t: float) -> int:
    """The whole number of nanoseconds nearest to ``t`` seconds."""
    return round(t * 1e9)


def ns_to_seconds(ns: int) -> float:
    """Seconds for ``ns`` nanoseconds; ``seconds_to_ns`` inverts it exactly (to 2**53 ns)."""
    return ns / 1e9


@dataclass(frozen=True, slots=True)
class ImuSample:
    """One reading of the IMU on rod ``rod``, in that rod's body frame."""

    t: float
    rod: int
    accel: FloatArray
    """Specific force (m/s^2), (3,): reads +g upward at rest."""
    gyro: FloatArray
    """Angular rate (rad/s), (3,)."""
    mag: FloatArray
    """Magnetic field (T), (3,)."""


@dataclass(frozen=True, slots=True)
class AhrsSample:
    """The orientation an on-board AHRS computed from the IMU of rod ``rod``."""

    t: float
    rod: int
    quaternion: FloatArray
    """Body to world, (x, y, z, w), (4,)."""


@dataclass(frozen=True, slots=True)
class EncoderSample:
    """Motor encoders: the rest lengths of the actuated cables (m), (m,)."""

    t: float
    rest_lengths: FloatArray


@dataclass(frozen=True, slots=True)
class CableLengthSample:
    """On-board stretch sensors: endcap-to-endcap length of every cable (m), (n_cables,)."""

    t: float
    lengths: FloatArray


@dataclass(frozen=True, slots=True)
class UwbRangeSample:
    """One broadcast round of UWB ranging (Caluwaerts et al. 2016, section III).

    Module ids 0..n_nodes-1 are the robot's endcap modules, n_nodes.. are the fixed
    anchors. ``ranges`` are the uncorrected distances m_{j,i} of eq. 6-7: true
    distance plus the per-pair offset o_{j,i} plus noise. Rejected packets are absent.
    """

    t: float
    times: FloatArray
    """Time of each measurement (s), (k,)."""
    pairs: NDArray[np.intp]
    """(initiator, responder) module ids, (k, 2)."""
    ranges: FloatArray
    """(k,) metres."""


@dataclass(frozen=True, slots=True)
class RgbdFrame:
    """A frame of the fixed overhead RGB-D camera."""

    t: float
    rgb: NDArray[np.uint8]
    """(H, W, 3)."""
    depth: NDArray[np.float32]
    """Metric depth along the optical axis (m), (H, W); 0 where there is no return."""


@dataclass(frozen=True, slots=True)
class ContactSample:
    """Endcap-ground contact flags, (n_nodes,)."""

    t: float
    in_contact: NDArray[np.bool_]


Sample: TypeAlias = (
    ImuSample
    | AhrsSample
    | EncoderSample
    | CableLengthSample
    | UwbRangeSample
    | RgbdFrame
    | ContactSample
)

SAMPLE_KINDS: dict[str, type] = {
    "imu": ImuSample,
    "ahrs": AhrsSample,
    "encoders": EncoderSample,
    "cable_lengths": CableLengthSample,
    "uwb": UwbRangeSample,
    "rgbd": RgbdFrame,
    "contacts": ContactSample,
}
"""The name of each kind of sample, as estimators declare what they need."""

GROUND_TRUTH = "ground_truth"
"""Not a sample kind: the requirement of an estimator that reads the true state (the
simulator's, or motion capture's)."""


@dataclass(frozen=True, slots=True)
class GroundTruth:
    """The simulator's true state. Never handed to an estimator as a sample."""

    t: float
    node_positions: FloatArray
    """(n_nodes, 3) metres."""
    node_velocities: FloatArray
    """(n_nodes, 3) m/s."""
    rod_positions: FloatArray
    """Rod centres, (n_rods, 3)."""
    rod_quaternions: FloatArray
    """(n_rods, 4), (x, y, z, w); the body z axis runs from a rod's first node to its second."""
    com: FloatArray
    """Centre of mass, (3,)."""
    rest_lengths: FloatArray
    """True rest lengths of all cables, (n_cables,)."""
