"""What the robot's sensors can physically report: bounds on every raw measurement.

A measurement outside these bounds is not noise but a broken or misconfigured stream
(ranges in millimetres, a stuck module reporting 100 m, an IMU read with the wrong
scale): no filter should fuse it, and no re-initialisation should fit to it. The bounds
are computed once from the robot description and the sensor calibration, in SI units,
and are generous on purpose: on simulated rolling they leave a factor of three or more
between the largest reading seen and the bound (measured: 3-bar node-node ranges at
most 0.44 m against 1.3 m, cable readings 0.28 m against 1.0 m, accelerations
68 m/s^2 against 157 m/s^2). Each check is vectorised over a batch of readings and
says, per reading, whether it is plausible and, if not, the first reason why.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from collections.abc import Sequence

    from numpy.typing import ArrayLike, NDArray

    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.protocols import SensorCalibration

__all__ = ["PlausibilityBounds", "Verdict"]

SPEED_OF_LIGHT = 299_792_458.0
"""m/s."""

RANGE_NOISE_SIGMAS = 8.0
"""UWB noise margin in standard deviations of a range. The range noise of SDS-TWR with
stamps of std sigma_t is about c sigma_t (measured in the simulator: 0.027 m for 0.03 m
predicted); 8 of them is never reached by noise over a lifetime of ranging."""

RANGE_OFFSET_TOLERANCE = 0.1
"""m, added to the UWB noise margin: what the self-calibration of the pair offsets
o_ij (Caluwaerts et al. 2016 section III-C) may be off by, and multipath shortening a range."""

CABLE_NOISE_SIGMAS = 8.0
"""Cable-sensor noise margin in standard deviations of a reading."""

FULL_SCALE_MARGIN = 0.02
"""Relative margin over an IMU's full scale: a saturated reading is exactly the full
scale, and the scale factor calibration that converts counts to SI may add a percent."""

QUATERNION_NORM_TOLERANCE = 0.01
"""How far from 1 an AHRS quaternion's norm may be. Fixed-point AHRS outputs (2^-14 per
count) are within 1e-3; a garbled or wrongly scaled one is not."""

ENCODER_RANGE_MARGIN = 0.1
"""Share of a motor's rest-length span it may read beyond its limits (overshoot,
encoder offset)."""


@dataclass(frozen=True, eq=False)
class Verdict:
    """Which readings of a batch are plausible, and why the others are not."""

    plausible: NDArray[np.bool_]
    """(k,) True for a reading to use."""
    reasons: dict[str, NDArray[np.bool_]]
    """Kind -> (k,) readings rejected for it; disjoint (the first reason checked wins),
    only kinds that rejected something. Absent readings (NaN cables) are in neither."""

    def counts(self) -> dict[str, int]:
        """Rejected readings by kind."""
        return {kind: int(np.count_nonzero(mask)) for kind, mask in self.reasons.items()}


def _judge(present: NDArray[np.bool_], failures: Sequence[tuple[str, ArrayLike]]) -> Verdict:
    """The verdict of checks applied in order; ``present``: (k,) readings that exist,
    each failure (k,) True where a reading fails it."""
    left = present.copy()
    reasons: dict[str, NDArray[np.bool_]] = {}
    for kind, failure in failures:
        bad = np.asarray(failure, dtype=bool)
        hit = left & bad
        if hit.any():
            reasons[kind] = hit
        left &= ~bad
    return Verdict(left, reasons)


def _all_within(x: NDArray[np.float64], bound: float) -> bool:
    """True if every entry of ``x`` is finite with a magnitude of at most ``bound``."""
    if x.size == 0:
        return True
    largest = float(np.abs(x).max())
    return largest <= bound and math.isfinite(largest)  # NaN compares False


def _rows(values: ArrayLike, width: int) -> NDArray[np.float64]:
    """``values`` as (k, width) floats; a (width,) vector is one row."""
    return np.asarray(values, dtype=np.float64).reshape(-1, width)


@dataclass(frozen=True, eq=False)
class PlausibilityBounds:
    """Physical bounds on the raw measurements of one robot in one arena (SI units).

    Build it with :meth:`from_robot`; the fields say what each bound is and why.
    """

    n_nodes: int
    uwb_offsets: NDArray[np.float64]
    """Pair offsets o_ij (m), (n_modules, n_modules), subtracted before bounding."""
    range_tolerance: float
    """m: noise margin of a UWB range; a range corrected by o_ij below -this is negative."""
    node_range_max: float
    """m: the longest node-node range. The rods hold the nodes apart and the cables only
    pull them together, so no two nodes (and no two modules, which sit on the rods
    between them) lie further apart than the rods laid end to end: the sum of the rod
    lengths, three times the diameter of the 3-bar prism. Plus the noise margin."""
    anchor_range_max: float
    """m: the longest node-anchor range. The robot may roll out of the anchors' layout:
    its modules are allowed anywhere within D + span of the anchors' convex hull, D the
    layout's extent (the largest anchor-anchor distance, 4.2 m for the 3-bar's arena)
    and span the rod span above; an anchor then lies at most 2 D + span away (9.8 m for
    the 3-bar, 36 m for SUPERball). Plus the noise margin."""
    cable_tolerance: float
    """m: noise margin of a cable reading; a reading below -this is negative."""
    cable_length_max: float
    """m: the longest cable reading: a taut cable's ends are two nodes (at most the rod
    span apart, as for the ranges), a slack one reads its rest length (at most the
    motor's largest) plus the slack bias. Plus the noise margin."""
    accel_full_scale: float
    """m/s^2 per axis, with :data:`FULL_SCALE_MARGIN`."""
    gyro_full_scale: float
    """rad/s per axis, with :data:`FULL_SCALE_MARGIN`."""
    quaternion_norm_tolerance: float
    """How far an AHRS quaternion's norm may be from 1."""
    rest_length_min: NDArray[np.float64]
    """m, (m,): lowest encoder reading per actuated cable, margin included."""
    rest_length_max: NDArray[np.float64]
    """m, (m,): highest encoder reading per actuated cable, margin included."""

    @classmethod
    def from_robot(
        cls, description: RobotDescription, calibration: SensorCalibration
    ) -> PlausibilityBounds:
        """The bounds for ``description``'s robot ranging against ``calibration``'s anchors."""
        d = description
        s = d.sensors
        anchors = np.asarray(calibration.anchors, dtype=np.float64).reshape(-1, 3)
        extent = 0.0
        if len(anchors) > 1:
            extent = float(np.max(np.linalg.norm(anchors[:, None] - anchors[None], axis=-1)))
        span = float(sum(r.length for r in d.rods))
        range_tol = (
            RANGE_NOISE_SIGMAS * SPEED_OF_LIGHT * s.uwb.timestamp_noise + RANGE_OFFSET_TOLERANCE
        )
        cable_tol = CABLE_NOISE_SIGMAS * s.cable_length.noise
        longest_rest = max(
            (c.motor.max_rest_length if c.motor is not None else c.rest_length) for c in d.cables
        )
        lo, hi, _ = d.motor_limits
        margin = ENCODER_RANGE_MARGIN * (hi - lo) + s.encoder.resolution
        full_scale = 1.0 + FULL_SCALE_MARGIN
        return cls(
            n_nodes=d.n_nodes,
            uwb_offsets=np.asarray(calibration.uwb_offsets, dtype=np.float64),
            range_tolerance=range_tol,
            node_range_max=span + range_tol,
            anchor_range_max=2.0 * extent + span + range_tol,
            cable_tolerance=cable_tol,
            cable_length_max=max(span, longest_rest + s.cable_length.slack_bias) + cable_tol,
            accel_full_scale=s.imu.accel_full_scale * full_scale,
            gyro_full_scale=s.imu.gyro_full_scale * full_scale,
            quaternion_norm_tolerance=QUATERNION_NORM_TOLERANCE,
            rest_length_min=_shortest_readings(d, lo - margin),
            rest_length_max=hi + margin,
        )

    @property
    def n_modules(self) -> int:
        return int(self.uwb_offsets.shape[0])

    def uwb(self, pairs: ArrayLike, ranges: ArrayLike) -> Verdict:
        """UWB ranges m_ij (m), (k,), of module pairs (k, 2), offsets o_ij included.

        Kinds: ``uwb_bad_pair`` (a module id out of range, or a module ranging itself),
        ``uwb_range_not_finite``, ``uwb_range_negative``, ``uwb_range_too_long``.
        """
        p = np.asarray(pairs, dtype=np.intp).reshape(-1, 2)
        r = np.asarray(ranges, dtype=np.float64).reshape(-1)
        valid = (p >= 0).all(axis=1) & (p < self.n_modules).all(axis=1) & (p[:, 0] != p[:, 1])
        safe = np.where(valid[:, None], p, 0)
        corrected = r - self.uwb_offsets[safe[:, 0], safe[:, 1]]
        to_anchor = (safe >= self.n_nodes).any(axis=1)
        limit = np.where(to_anchor, self.anchor_range_max, self.node_range_max)
        return _judge(
            np.ones(len(r), dtype=bool),
            [
                ("uwb_bad_pair", ~valid),
                ("uwb_range_not_finite", ~np.isfinite(r)),
                ("uwb_range_negative", corrected < -self.range_tolerance),
                ("uwb_range_too_long", corrected > limit),
            ],
        )

    def imu(self, accel: ArrayLike, gyro: ArrayLike) -> Verdict:
        """Raw IMU readings: specific force (m/s^2) and rate (rad/s), each (k, 3).

        Kinds: ``imu_not_finite``, ``accel_over_full_scale``, ``gyro_over_full_scale``.
        """
        a, w = _rows(accel, 3), _rows(gyro, 3)
        if _all_within(a, self.accel_full_scale) and _all_within(w, self.gyro_full_scale):
            return Verdict(np.ones(len(a), dtype=bool), {})  # the common case, at once
        finite = np.isfinite(a).all(axis=1) & np.isfinite(w).all(axis=1)
        return _judge(
            np.ones(len(a), dtype=bool),
            [
                ("imu_not_finite", ~finite),
                ("accel_over_full_scale", (np.abs(a) > self.accel_full_scale).any(axis=1)),
                ("gyro_over_full_scale", (np.abs(w) > self.gyro_full_scale).any(axis=1)),
            ],
        )

    def ahrs(self, quaternions: ArrayLike) -> Verdict:
        """AHRS orientations (x, y, z, w), (k, 4). Kinds: ``ahrs_not_finite``,
        ``ahrs_not_unit``."""
        q = _rows(quaternions, 4)
        finite = np.asarray(np.isfinite(q).all(axis=1))
        norm = np.linalg.norm(np.where(finite[:, None], q, 0.0), axis=1)
        return _judge(
            np.ones(len(q), dtype=bool),
            [
                ("ahrs_not_finite", ~finite),
                ("ahrs_not_unit", np.abs(norm - 1.0) > self.quaternion_norm_tolerance),
            ],
        )

    def cables(self, lengths: ArrayLike) -> Verdict:
        """Cable-length readings (m), any shape, judged entry by entry (flattened).

        NaN means no reading and is neither plausible nor rejected. Kinds:
        ``cable_negative``, ``cable_too_long`` (infinities fall in these too).
        """
        x = np.asarray(lengths, dtype=np.float64).reshape(-1)
        return _judge(
            ~np.isnan(x),
            [
                ("cable_negative", x < -self.cable_tolerance),
                ("cable_too_long", x > self.cable_length_max),
            ],
        )

    def encoders(self, rest_lengths: ArrayLike) -> Verdict:
        """Encoder readings: rest lengths (m) of the actuated cables, (k, m).

        Kinds: ``encoder_not_finite``, ``encoder_out_of_range``.
        """
        x = _rows(rest_lengths, len(self.rest_length_min))
        if bool(np.all(x >= self.rest_length_min)) and bool(np.all(x <= self.rest_length_max)):
            return Verdict(np.ones(len(x), dtype=bool), {})  # NaN fails both: not here
        outside = (x < self.rest_length_min) | (x > self.rest_length_max)
        return _judge(
            np.ones(len(x), dtype=bool),
            [
                ("encoder_not_finite", ~np.isfinite(x).all(axis=1)),
                ("encoder_out_of_range", outside.any(axis=1)),
            ],
        )


def _shortest_readings(d: RobotDescription, lowest: NDArray[np.float64]) -> NDArray[np.float64]:
    """The shortest plausible encoder readings (m), (m,): ``lowest`` (the motor's range
    less a margin), except where the motor holds a minimum tension and so reels in slack
    below its range, down to where the endcaps touch (their radii together, less that
    tension's stretch)."""
    least = d.motor_min_stretch
    pairs = d.cable_nodes[d.actuated]
    touching = d.node_radii[pairs].sum(axis=1) - np.nan_to_num(least)
    return np.where(np.isnan(least), lowest, touching)
