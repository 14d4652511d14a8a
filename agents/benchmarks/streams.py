"""Every estimator on sensor streams as a lab's robot gives them.

A simulated stream is perfect in ways a real one is not: every IMU reading arrives, on
time, at the rate the description says; the AHRS knows north; each UWB range is a
line of sight. Here each estimator is replayed on its own robot's runs (own world, the
gait driven by the truth, recorded once) with the streams edited as real hardware
would edit them (:data:`STREAM_FAULTS`: readings lost, late, jittered, biased, coarse;
a heading disturbed by the building's iron; ranges through a body), and scored as on
the cross-world benchmark (:func:`agents.benchmarks.cross_world.score_run`). The edits
draw from a generator seeded per run, so that a figure reproduces.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from agents.benchmarks.cross_world import ESTIMATOR_ROBOTS, score_run, summary
from agents.benchmarks.estimation import record_face_transition
from tensegrity_gym.model.lie import quat_from_rotvec, quat_multiply
from tensegrity_gym.model.samples import (
    AhrsSample,
    EncoderSample,
    ImuSample,
    Sample,
    UwbRangeSample,
)

if TYPE_CHECKING:
    from hardware.recording import RecordedRun

__all__ = ["STREAM_FAULTS", "StreamFault", "bench_streams", "with_fault"]

Edit = Callable[[Sample, np.random.Generator, dict[str, Any]], list[Sample]]
"""A sample as it arrives: none (lost) or one (edited); the generator for draws, and a
dict of its own for each run (what the edit has seen of it so far)."""


@dataclass(frozen=True)
class StreamFault:
    """One way a real stream departs from the simulated one."""

    what: str
    """What a lab would see, one line."""
    edit: Edit


def _kept(s: Sample, rng: np.random.Generator, seen: dict[str, Any]) -> list[Sample]:
    return [s]


def _lost(kind: type, share: float) -> Edit:
    def edit(s: Sample, rng: np.random.Generator, seen: dict[str, Any]) -> list[Sample]:
        return [] if isinstance(s, kind) and rng.random() < share else [s]

    return edit


def _late(kinds: tuple[type, ...], seconds: float, jitter: float = 0.0) -> Edit:
    def edit(s: Sample, rng: np.random.Generator, seen: dict[str, Any]) -> list[Sample]:
        if not isinstance(s, kinds):
            return [s]
        shift = seconds + (rng.uniform(-jitter, jitter) if jitter else 0.0)
        return [cast("Sample", replace(cast("Any", s), t=s.t + shift))]

    return edit


def _every_other_imu() -> Edit:
    def edit(s: Sample, rng: np.random.Generator, seen: dict[str, Any]) -> list[Sample]:
        # an IMU at half the described rate: every other reading of each rod never comes
        if not isinstance(s, ImuSample):
            return [s]
        count = seen[f"imu/{s.rod}"] = seen.get(f"imu/{s.rod}", -1) + 1
        return [] if count % 2 else [s]

    return edit


_GYRO_BIAS = np.array([0.02, -0.015, 0.01])  # rad/s
_ACCEL_BIAS = np.array([0.3, -0.2, 0.25])  # m/s^2


def _biased(s: Sample, rng: np.random.Generator, seen: dict[str, Any]) -> list[Sample]:
    if isinstance(s, ImuSample):
        return [replace(s, gyro=s.gyro + _GYRO_BIAS, accel=s.accel + _ACCEL_BIAS)]
    return [s]


def _coarse_encoders(s: Sample, rng: np.random.Generator, seen: dict[str, Any]) -> list[Sample]:
    if isinstance(s, EncoderSample):
        return [replace(s, rest_lengths=np.round(s.rest_lengths, 3))]
    return [s]


def _heading(rate: float, offset: float, rod: int | None) -> Edit:
    """AHRS headings turned about z by ``offset + rate * t`` (rad, rad/s; t from the
    run's first AHRS reading, whatever the clock's origin), on ``rod`` (None: every
    rod)."""

    def edit(s: Sample, rng: np.random.Generator, seen: dict[str, Any]) -> list[Sample]:
        if not isinstance(s, AhrsSample) or (rod is not None and s.rod != rod):
            return [s]
        t0 = seen.setdefault("t0", s.t)
        turn = quat_from_rotvec(np.array([0.0, 0.0, offset + rate * (s.t - t0)]))
        return [replace(s, quaternion=quat_multiply(turn, s.quaternion))]

    return edit


def _through_a_body(s: Sample, rng: np.random.Generator, seen: dict[str, Any]) -> list[Sample]:
    if not isinstance(s, UwbRangeSample):
        return [s]
    longer = np.where(rng.random(len(s.ranges)) < 0.1, 0.3, 0.0)
    return [replace(s, ranges=s.ranges + longer)]


STREAM_FAULTS: dict[str, StreamFault] = {
    "clean": StreamFault("the stream as simulated", _kept),
    "imu_lost_fifth": StreamFault("a fifth of the IMU readings lost", _lost(ImuSample, 0.2)),
    "imu_half_rate": StreamFault(
        "the IMU at half the rate the description says", _every_other_imu()
    ),
    "imu_bias": StreamFault(
        "IMU biases beyond the description's (gyro 0.02 rad/s, accelerometer 0.3 m/s^2)",
        _biased,
    ),
    "imu_late": StreamFault(
        "IMU stamps 10 ms late against the other sensors'", _late((ImuSample, AhrsSample), 0.01)
    ),
    "time_jitter": StreamFault(
        "IMU and encoder stamps jittered by up to 2 ms",
        _late((ImuSample, AhrsSample, EncoderSample), 0.0, 0.002),
    ),
    "encoders_late": StreamFault("encoder stamps 20 ms late", _late((EncoderSample,), 0.02)),
    "encoders_coarse": StreamFault("encoders read to the millimetre", _coarse_encoders),
    "heading_drift": StreamFault(
        "every AHRS heading drifting 1 degree a second (iron in the building)",
        _heading(np.radians(1.0), 0.0, None),
    ),
    "heading_off_one_rod": StreamFault(
        "one rod's AHRS heading 30 degrees off", _heading(0.0, np.radians(30.0), 1)
    ),
    "uwb_through_a_body": StreamFault("a tenth of the UWB ranges 0.3 m long", _through_a_body),
    "uwb_sparse": StreamFault("four in five UWB rounds lost", _lost(UwbRangeSample, 0.8)),
}
"""The stream faults by name."""


def with_fault(run: RecordedRun, fault: StreamFault, seed: int) -> RecordedRun:
    """``run`` with every step's samples as ``fault`` lets them arrive (in time order),
    its draws from a generator seeded with ``seed``; ``run`` itself is left as it is."""
    rng = np.random.default_rng(seed)
    seen: dict[str, Any] = {}

    def arrive(samples: list[Sample]) -> list[Sample]:
        out = [edited for s in samples for edited in fault.edit(s, rng, seen)]
        return sorted(out, key=lambda s: s.t)

    start = replace(run.start, samples=arrive(run.start.samples))
    return replace(run, start=start, steps=[replace(st, samples=arrive(st.samples))
                                            for st in run.steps])  # fmt: skip


def bench_streams(
    estimators: tuple[str, ...] = ("ukf", "inekf"),
    faults: tuple[str, ...] = tuple(STREAM_FAULTS),
    seeds: tuple[int, ...] = (0, 1, 2),
    steps: int = 300,
) -> dict[str, Any]:
    """Each estimator on its robot's rolling and turning runs (own world; the robots of
    :data:`~agents.benchmarks.cross_world.ESTIMATOR_ROBOTS`), each stream fault applied:
    ``rows[estimator][fault]`` the means and maxima over the runs."""
    unknown = [f for f in faults if f not in STREAM_FAULTS]
    if unknown:
        raise ValueError(
            f"unknown stream fault {unknown[0]!r}; choose from {sorted(STREAM_FAULTS)}"
        )
    start = time.perf_counter()
    rows: dict[str, dict[str, Any]] = {}
    for e in estimators:
        runs = {
            (motion, seed): record_face_transition(
                env_id, seed, steps, gait=gait, calibration="true"
            )
            for motion, (env_id, gait) in ESTIMATOR_ROBOTS[e].items()
            for seed in seeds
        }
        rows[e] = {
            name: summary([
                score_run(with_fault(run, STREAM_FAULTS[name], 1000 * key[1] + i), e, key[1])
                for i, (key, run) in enumerate(runs.items())
            ])
            for name in faults
        }  # fmt: skip
    return {
        "seeds": list(seeds),
        "steps": steps,
        "faults": {name: STREAM_FAULTS[name].what for name in faults},
        "rows": rows,
        "wall_s": round(time.perf_counter() - start, 1),
    }
