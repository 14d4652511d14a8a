"""The IMU term of identification (issue 16): the bag's accelerometer and gyro readings
against those of the simulator replaying one control period from each recorded state.

Node positions sampled at the control rate (10 Hz) hardly show the cables' damping:
the rods' vibrations at the cables' own frequencies (25 Hz and up for the 3-bar robot)
die out within tens of milliseconds, between two samples. The IMU samples them (200 Hz),
and replayed over one period from a recorded state, the simulator's readings follow the
recorded ones until the rolling's chaos sets in, so that damping and stiffness show.

A rod's spin about its own axis is not in the recorded endcap positions, so the
readings are compared by what does not depend on it: the specific force along the rod,
its magnitude across the rod, and the angular rate's magnitude across the rod. The spin
rate itself (the gyro's reading along the rod) starts the replay: a rolling rod spins,
and a replay that started it still would drag its endcaps over the ground.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from tensegrity_gym.model.lie import quat_conjugate, quat_rotate
from tensegrity_gym.model.samples import ImuSample

if TYPE_CHECKING:
    from collections.abc import Sequence

    from numpy.typing import NDArray

    from hardware.recording import RecordedRun, RecordedStep
    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.sim.world import Snapshot

__all__ = [
    "ImuReadings",
    "imu_features",
    "imu_readings",
    "imu_term",
    "readings_of_replay",
    "spin_track",
    "window_scores",
    "without_imu",
]

SATURATED = 0.98
"""Share of the full scale from which a recorded reading counts as clipped, and is left
out (the simulator's readings cannot be clipped in the recorded rod's frame)."""


@dataclass(frozen=True)
class ImuReadings:
    """The recorded IMU readings of one control period, as the replay compares them."""

    rods: NDArray[np.intp]
    """(q,) the rods that carry an IMU."""
    steps: NDArray[np.intp]
    """(s,) physics steps after the period's start at which each reading was taken."""
    span: int
    """Physics steps over which the accelerometer averages (one IMU sample interval)."""
    features: NDArray[np.float64]
    """(s, q, 3) :func:`imu_features` of the readings: m/s^2, m/s^2, rad/s."""
    valid: NDArray[np.bool_]
    """(s, q) readings within :data:`SATURATED` of the sensor's full scale on no axis."""


def imu_features(accel: NDArray[np.float64], gyro: NDArray[np.float64]) -> NDArray[np.float64]:
    """(..., 3) what of body-frame readings (..., 3) the rod's spin angle leaves alone:
    the specific force along the rod (body z, m/s^2), its magnitude across the rod
    (m/s^2), and the angular rate's magnitude across the rod (rad/s)."""
    return np.stack(
        [
            accel[..., 2],
            np.hypot(accel[..., 0], accel[..., 1]),
            np.hypot(gyro[..., 0], gyro[..., 1]),
        ],
        axis=-1,
    )


def _imu_samples(steps: Sequence[RecordedStep]) -> list[ImuSample]:
    return [s for step in steps for s in step.samples if isinstance(s, ImuSample)]


def without_imu(run: RecordedRun) -> RecordedRun:
    """``run`` as a bag without its IMU topic would give it."""

    def strip(step: RecordedStep) -> RecordedStep:
        return replace(step, samples=[s for s in step.samples if not isinstance(s, ImuSample)])

    return replace(run, start=strip(run.start), steps=[strip(s) for s in run.steps])


def spin_track(run: RecordedRun) -> NDArray[np.float64]:
    """(periods + 1, r): each rod's spin rate about its own axis (rad/s, the gyro's
    body z reading) by the latest reading at the end of each period (the start first);
    0 for a rod without an IMU, or before its first reading."""
    out = np.zeros((len(run.steps) + 1, run.description.n_rods))
    last = np.zeros(run.description.n_rods)
    for k, step in enumerate([run.start, *run.steps]):
        for s in _imu_samples([step]):
            last[s.rod] = s.gyro[2]
        out[k] = last
    return out


def imu_readings(
    run: RecordedRun, period: int, t_start: float, time_step: float
) -> ImuReadings | None:
    """The readings taken in ``run``'s period ``period`` (which starts at ``t_start``,
    s) whose averaging interval lies within it, on every IMU at once; None where there
    are none (a bag without an IMU topic)."""
    d = run.description
    rods = np.asarray(d.imu_rods, dtype=np.intp)
    config = d.sensors.imu
    span = max(1, round(1.0 / (config.rate * time_step)))
    n_steps = round(run.control_period / time_step)
    by_step: dict[int, dict[int, ImuSample]] = {}
    for s in _imu_samples(run.steps[period : period + 2]):  # a late reading: the next step
        j = round((s.t - t_start) / time_step)
        if span <= j <= n_steps:
            by_step.setdefault(j, {})[s.rod] = s
    steps = sorted(j for j, got in by_step.items() if all(int(r) in got for r in rods))
    if not steps or len(rods) == 0:
        return None
    accel = np.array([[by_step[j][int(r)].accel for r in rods] for j in steps])
    gyro = np.array([[by_step[j][int(r)].gyro for r in rods] for j in steps])
    valid = (np.abs(accel).max(axis=-1) < SATURATED * config.accel_full_scale) & (
        np.abs(gyro).max(axis=-1) < SATURATED * config.gyro_full_scale
    )
    return ImuReadings(
        rods, np.asarray(steps, dtype=np.intp), span, imu_features(accel, gyro), valid
    )


def readings_of_replay(
    description: RobotDescription,
    readings: ImuReadings,
    start_velocity: NDArray[np.float64],
    snapshots: dict[int, Snapshot],
    time_step: float,
) -> NDArray[np.float64]:
    """(s, q, 3) :func:`imu_features` the IMUs would read, without noise or bias, in a
    replay whose rods' centres started at ``start_velocity`` (r, 3; m/s) and whose
    state after each physics step j (of ``time_step`` s) is ``snapshots[j]`` (those of
    ``readings.steps`` and ``readings.steps - readings.span``, step 0 aside)."""
    rods = readings.rods

    def velocity(j: int) -> NDArray[np.float64]:
        v = start_velocity if j == 0 else np.asarray(snapshots[j].rod_linear_velocities)
        return np.asarray(v, dtype=np.float64)[rods]

    gravity = np.array([0.0, 0.0, -description.gravity])
    dt = readings.span * time_step
    # The mean acceleration over the sample interval, as the sensor model measures it.
    accel = np.array([(velocity(j) - velocity(j - readings.span)) / dt for j in readings.steps])
    quats = np.array([np.asarray(snapshots[j].rod_quaternions)[rods] for j in readings.steps])
    omega = np.array([np.asarray(snapshots[j].rod_angular_velocities)[rods]
                      for j in readings.steps])  # fmt: skip
    inverse = quat_conjugate(quats)
    return imu_features(quat_rotate(inverse, accel - gravity), quat_rotate(inverse, omega))


def window_scores(
    description: RobotDescription,
    windows: Sequence[ImuReadings],
    replayed: Sequence[NDArray[np.float64]],
) -> NDArray[np.float64]:
    """(w,) each window's mean squared difference between replayed and recorded
    features, each in units of its sensor's noise (dimensionless); 1e12 where the
    replay is not finite."""
    config = description.sensors.imu
    noise = np.maximum([config.accel_noise, config.accel_noise, config.gyro_noise], 1e-6)
    out = []
    for w, sim in zip(windows, replayed, strict=True):
        if not np.all(np.isfinite(sim)):
            out.append(1e12)
            continue
        r = (sim - w.features)[w.valid] / noise
        out.append(float(np.mean(r**2)) if r.size else 0.0)
    return np.asarray(out)


def imu_term(scores: NDArray[np.float64]) -> float:
    """The cost of the windows' scores (w,): the log of their mean (1e12 at most each).

    The mean, not a mean of logs as for a likelihood whose noise each window had its
    own of: the few periods in which the robot lands on a face depart from their
    replay the most (contact is where rolling is chaotic), and a log per window, which
    makes little of them, drew the fitted damping 5 % and more off the recording's
    (3-bar bag, 50 ms windows), while the mean's least lay on it."""
    return float(np.log(np.mean(np.minimum(scores, 1e12)) + 1e-12)) if len(scores) else 0.0
