"""Estimates do not depend on the clock's origin (issue 13).

One simulated run is recorded to a bag, then copied with every stamp (log times, header
stamps, the stamp of each UWB exchange) moved: by about 12 days, and into Unix time. The UKF and the
ICP tracker over the copy must give the very same estimates, bit for bit, offline and
through the env's ``driver="bag:PATH"``: they count time in integer nanoseconds.

Samples carry float seconds, which in Unix time hold a stamp to about 240 ns: the shift
into Unix time keeps this bag's period ends and frames exact, one of 1 ns more does not,
and there the UKF's periods still differ (an expected failure).
"""

from __future__ import annotations

import warnings
from dataclasses import fields, is_dataclass
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
import pytest
from rosbags.rosbag2 import Reader, StoragePlugin, Writer

import tensegrity_gym  # noqa: F401  (registers the envs)
from estimation.icp import IcpEstimator
from estimation.ukf import UkfEstimator
from hardware.bag import BagReader
from hardware.bag import messages as m
from hardware.recording import BagSink, RecordingBackend
from tensegrity_gym.model.description import load_robot
from tensegrity_gym.sim.backend import SimBackend

if TYPE_CHECKING:
    from tensegrity_gym.model.estimate import Estimate
    from tensegrity_gym.model.protocols import Estimator

ENV = "tensegrity_gym/ThreeBarRoll-v0"
STEPS = 14  # control periods recorded
UNIX = 1_700_000_000 * 10**9  # ns: a shift to the clock of a robot stamped in Unix time
DAYS = 1_000_000 * 10**9  # ns: about 12 days, where float seconds still hold every ns
UNIX_ODD = UNIX + 1  # ns: stamps that float seconds of Unix time cannot hold
_IMAGE = "sensor_msgs/msg/Image"


def _record(folder: Path) -> Path:
    """A short run of random commands with camera frames: ``folder/episode_000``."""
    d = load_robot("three_bar")
    backend = RecordingBackend(SimBackend(d, camera=True), BagSink(folder, {"env": ENV}))
    rng = np.random.default_rng(3)
    backend.reset(rng)
    lo, hi, _ = d.motor_limits
    for _ in range(STEPS):
        backend.step(rng.uniform(lo, hi))
    backend.close()
    return folder / "episode_000"


def _shift_times(msg: Any, ns: int) -> None:
    """Move every ``builtin_interfaces/Time`` in ``msg`` (a rosbags message) by ``ns``."""
    for f in fields(msg):
        value = getattr(msg, f.name)
        if type(value).__name__ == "builtin_interfaces__msg__Time":
            value.sec, value.nanosec = divmod(m.stamp_ns(value.sec, value.nanosec) + ns, 10**9)
        elif is_dataclass(value):
            _shift_times(value, ns)
        elif isinstance(value, list):
            for item in value:
                if is_dataclass(item):
                    _shift_times(item, ns)


def _shifted_header(raw: bytes, ns: int) -> bytes:
    """A CDR message that starts with a std_msgs/Header, its stamp moved by ``ns``."""
    sec = int.from_bytes(raw[4:8], "little", signed=True)
    stamp = m.stamp_ns(sec, int.from_bytes(raw[8:12], "little")) + ns
    sec, nanosec = divmod(stamp, 10**9)
    return (
        raw[:4] + sec.to_bytes(4, "little", signed=True) + nanosec.to_bytes(4, "little") + raw[12:]
    )


def _shift_bag(src: Path, dst: Path, ns: int) -> Path:
    """``src`` copied message by message with every stamp and log time ``ns`` later."""
    store = m.typestore()
    with Reader(src) as reader, Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP) as out:
        conns: dict[str, Any] = {}
        for conn, t, raw in reader.messages():
            data = bytes(raw)
            if conn.msgtype == _IMAGE:
                data = _shifted_header(data, ns)  # large: only its header is touched
            else:
                msg = store.deserialize_cdr(data, conn.msgtype)
                _shift_times(msg, ns)
                data = bytes(store.serialize_cdr(msg, conn.msgtype))
            if conn.topic not in conns:
                conns[conn.topic] = out.add_connection(conn.topic, conn.msgtype, typestore=store)
            out.write(conns[conn.topic], t + ns, data)
    return dst


@cache
def _bags(root: str) -> dict[int, Path]:
    """The recorded bag (key 0) and its shifted copies, by shift (ns)."""
    base = _record(Path(root) / "rec")
    shifted = {s: _shift_bag(base, Path(root) / f"shift_{s}", s) for s in (DAYS, UNIX, UNIX_ODD)}
    return {0: base} | shifted


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> dict[int, Path]:
    return _bags(str(tmp_path_factory.mktemp("clock")))


def _offline(bag: Path, estimator: Estimator) -> list[Estimate]:
    """``estimator`` over the bag's control periods, seeded alike."""
    rng = np.random.default_rng(0)
    with BagReader(bag) as reader:
        periods = reader.periods()
        start = next(periods)
        d, calibration = reader.description, reader.calibration
        out = [estimator.reset(d, calibration, start.samples, start.command, rng)]
        out += [estimator.update(p.samples, p.command) for p in periods]
    return out


def _assert_identical(a: list[Estimate], b: list[Estimate]) -> None:
    assert len(a) == len(b)
    for k, (x, y) in enumerate(zip(a, b, strict=True)):
        for name in ("node_positions", "node_velocities", "com"):
            assert np.array_equal(getattr(x, name), getattr(y, name)), f"update {k}: {name}"
        assert (x.healthy, x.reinitialised) == (y.healthy, y.reinitialised), f"update {k}"


_SHIFTS = [
    pytest.param(DAYS, id="12-days"),
    # The period ends (multiples of 0.1 s) and frames of this bag, moved by a multiple of
    # 2**17 ns, are floats that seconds_to_ns gives back exactly; most stamps are not.
    pytest.param(UNIX, id="unix-time"),
]
_NOT_HELD = pytest.param(
    UNIX_ODD,
    id="unix-time-odd-ns",
    marks=pytest.mark.xfail(
        strict=True,
        reason="samples carry float seconds of absolute time: at 1.7e9 s they hold a "
        "stamp to about 240 ns only (the bag's decoder would have to rebase them)",
    ),
)


@pytest.mark.parametrize("shift", [*_SHIFTS, _NOT_HELD])
def test_the_ukf_offline_does_not_depend_on_the_clock_origin(
    bags: dict[int, Path], shift: int
) -> None:
    base = _offline(bags[0], UkfEstimator())
    assert all(e.is_finite() for e in base) and base[-1].healthy
    _assert_identical(base, _offline(bags[shift], UkfEstimator()))


@pytest.mark.parametrize("shift", _SHIFTS)
def test_the_icp_tracker_offline_does_not_depend_on_the_clock_origin(
    bags: dict[int, Path], shift: int
) -> None:
    base = _offline(bags[0], IcpEstimator())
    assert any(e.healthy for e in base)
    _assert_identical(base, _offline(bags[shift], IcpEstimator()))


def _online(bag: Path, estimator: str) -> tuple[list[Any], list[float]]:
    """Observations and rewards of the env replaying ``bag`` with ``estimator``."""
    env = gym.make(ENV, driver=f"bag:{bag}", estimator=estimator)
    obs, _ = env.reset(seed=0)
    observations, rewards = [obs], []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the replay ignores the policy's actions
        done = False
        while not done:
            obs, reward, terminated, truncated, _ = env.step(env.action_space.sample() * 0)
            observations.append(obs)
            rewards.append(float(reward))
            done = terminated or truncated
    env.close()
    return observations, rewards


@pytest.mark.parametrize("estimator", ["ukf", "icp"])
@pytest.mark.parametrize("shift", _SHIFTS)
def test_a_replayed_bag_gives_the_same_observations_whatever_the_clock_origin(
    bags: dict[int, Path], shift: int, estimator: str
) -> None:
    obs_a, rewards_a = _online(bags[0], estimator)
    obs_b, rewards_b = _online(bags[shift], estimator)
    assert len(obs_a) == STEPS + 1 and rewards_a == rewards_b
    for k, (a, b) in enumerate(zip(obs_a, obs_b, strict=True)):
        assert np.array_equal(a, b), f"step {k}"
