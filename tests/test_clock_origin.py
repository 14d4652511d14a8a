"""Estimates do not depend on the clock's origin (issue 13).

One simulated run is recorded to a bag, then copied with every stamp (log times, header
stamps, the stamp of each UWB exchange) moved: by about 12 days, and into Unix time, and
jittered by up to 1 us. The UKF and the ICP tracker over a copy must give the very same
estimates, bit for bit, offline and through the env's ``driver="bag:PATH"``, as over the
bag it was moved from: they count time in integer nanoseconds, and the bag's decoder
hands out seconds from its clock origin (the first log time floored to a second), which
float seconds hold to the nanosecond whatever the robot's clock reads. Recording a
replayed copy writes its absolute stamps back.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
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
from hardware.bag import ReplayBackend
from hardware.bag import messages as m
from hardware.bag.assembler import header_stamp
from hardware.recording import BagSink, RecordingBackend, hold_command
from tensegrity_gym.model.description import load_robot
from tensegrity_gym.sim.backend import SimBackend

if TYPE_CHECKING:
    from tensegrity_gym.model.estimate import Estimate
    from tensegrity_gym.model.protocols import Estimator

ENV = "tensegrity_gym/ThreeBarRoll-v0"
STEPS = 14  # control periods recorded
UNIX = 1_700_000_000 * 10**9  # ns: a shift to the clock of a robot stamped in Unix time
DAYS = 1_000_000 * 10**9  # ns: about 12 days, where float seconds still hold every ns
_IMAGE = "sensor_msgs/msg/Image"


def _record(folder: Path) -> Path:
    """A short run of random commands with camera frames: ``folder/episode_000``."""
    d = load_robot("three_bar")
    # Stamped from 0 (not the wall clock, as a recording is by default), so that the
    # copies below are moved by known amounts.
    sink = BagSink(folder, {"env": ENV}, wall_clock=False)
    backend = RecordingBackend(SimBackend(d, camera=True), sink)
    rng = np.random.default_rng(3)
    backend.reset(rng)
    lo, hi, _ = d.motor_limits
    for _ in range(STEPS):
        backend.step(rng.uniform(lo, hi))
    backend.close()
    return folder / "episode_000"


Move = Callable[[int], int]
"""A new stamp (ns) for each old one."""


def _jitter(ns: int) -> int:
    """A stamp moved by up to 1 us, differently from one microsecond to the next."""
    return ns + (ns // 1000 * 37) % 997


def _move_times(msg: Any, move: Move) -> None:
    """Move every ``builtin_interfaces/Time`` in ``msg`` (a rosbags message)."""
    for f in fields(msg):
        value = getattr(msg, f.name)
        if type(value).__name__ == "builtin_interfaces__msg__Time":
            value.sec, value.nanosec = divmod(move(m.stamp_ns(value.sec, value.nanosec)), 10**9)
        elif is_dataclass(value):
            _move_times(value, move)
        elif isinstance(value, list):
            for item in value:
                if is_dataclass(item):
                    _move_times(item, move)


def _moved_header(raw: bytes, move: Move) -> bytes:
    """A CDR message that starts with a std_msgs/Header, its stamp moved."""
    sec = int.from_bytes(raw[4:8], "little", signed=True)
    stamp = move(m.stamp_ns(sec, int.from_bytes(raw[8:12], "little")))
    sec, nanosec = divmod(stamp, 10**9)
    header = sec.to_bytes(4, "little", signed=True) + nanosec.to_bytes(4, "little")
    return raw[:4] + header + raw[12:]


def _move_bag(src: Path, dst: Path, move: Move) -> Path:
    """``src`` copied message by message with every stamp and log time moved."""
    store = m.typestore()
    with Reader(src) as reader, Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP) as out:
        conns: dict[str, Any] = {}
        for conn, t, raw in reader.messages():
            data = bytes(raw)
            if conn.msgtype == _IMAGE:
                data = _moved_header(data, move)  # large: only its header is touched
            else:
                msg = store.deserialize_cdr(data, conn.msgtype)
                _move_times(msg, move)
                data = bytes(store.serialize_cdr(msg, conn.msgtype))
            if conn.topic not in conns:
                conns[conn.topic] = out.add_connection(conn.topic, conn.msgtype, typestore=store)
            out.write(conns[conn.topic], move(t), data)
    return dst


@cache
def _bags(root: str) -> dict[str, Path]:
    """The recorded bag (``"base"``) and its copies with moved stamps, by name."""
    folder = Path(root)
    base = _record(folder / "rec")
    moves: dict[str, Move] = {
        "12-days": lambda ns: ns + DAYS,
        "unix-time": lambda ns: ns + UNIX,
        "jittered": _jitter,
        "jittered-unix-time": lambda ns: _jitter(ns) + UNIX,
    }
    return {"base": base} | {name: _move_bag(base, folder / name, f) for name, f in moves.items()}


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    return _bags(str(tmp_path_factory.mktemp("clock")))


def _offline(bag: Path, estimator: Estimator) -> list[Estimate]:
    """``estimator`` over the bag's control periods as agents.recordings.offline runs it."""
    backend = ReplayBackend(bag)
    rng = np.random.default_rng(0)
    start = backend.reset(rng)
    d = backend.description
    out = [estimator.reset(d, backend.calibration, start.samples, hold_command(d), rng)]
    while (command := backend.next_command) is not None:
        out.append(estimator.update(backend.step(command).samples, command))
    backend.close()
    return out


def _assert_identical(a: list[Estimate], b: list[Estimate]) -> None:
    assert len(a) == len(b)
    for k, (x, y) in enumerate(zip(a, b, strict=True)):
        for name in ("node_positions", "node_velocities", "com"):
            assert np.array_equal(getattr(x, name), getattr(y, name)), f"update {k}: {name}"
        assert (x.healthy, x.reinitialised) == (y.healthy, y.reinitialised), f"update {k}"


_SHIFTED = ["12-days", "unix-time", "jittered-unix-time"]
"""Copies whose estimates must be those of the bag they were moved from (:func:`_source`).
Float seconds of Unix time would hold a stamp to about 240 ns only; the reader's clock
origin keeps every stamp, jittered or not, to the nanosecond."""


def _source(shifted: str) -> str:
    """The bag a copy was moved from: the jittered one for a jittered copy."""
    return "jittered" if shifted.startswith("jittered") else "base"


@pytest.mark.parametrize("shifted", _SHIFTED)
def test_the_ukf_offline_does_not_depend_on_the_clock_origin(
    bags: dict[str, Path], shifted: str
) -> None:
    base = _offline(bags[_source(shifted)], UkfEstimator())
    assert all(e.is_finite() for e in base) and base[-1].healthy
    _assert_identical(base, _offline(bags[shifted], UkfEstimator()))


@pytest.mark.parametrize("shifted", _SHIFTED)
def test_the_icp_tracker_offline_does_not_depend_on_the_clock_origin(
    bags: dict[str, Path], shifted: str
) -> None:
    base = _offline(bags[_source(shifted)], IcpEstimator())
    assert any(e.healthy for e in base)
    _assert_identical(base, _offline(bags[shifted], IcpEstimator()))


def test_a_bag_hands_out_times_from_its_first_whole_second(bags: dict[str, Path]) -> None:
    origins = {name: ReplayBackend(bag).clock_origin_ns for name, bag in bags.items()}
    assert origins == {
        "base": 0,
        "12-days": DAYS,
        "unix-time": UNIX,
        "jittered": 0,
        "jittered-unix-time": UNIX,
    }


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
@pytest.mark.parametrize("shifted", _SHIFTED)
def test_a_replayed_bag_gives_the_same_observations_whatever_the_clock_origin(
    bags: dict[str, Path], shifted: str, estimator: str
) -> None:
    obs_a, rewards_a = _online(bags[_source(shifted)], estimator)
    obs_b, rewards_b = _online(bags[shifted], estimator)
    assert len(obs_a) == STEPS + 1 and rewards_a == rewards_b
    for k, (a, b) in enumerate(zip(obs_a, obs_b, strict=True)):
        assert np.array_equal(a, b), f"step {k}"


def _stamps(bag: Path, skip: frozenset[str]) -> list[tuple[str, int, list[int]]]:
    """(topic, log time, stamps) of each message outside ``skip``, in log-time order:
    its header stamp where it has a header, and the stamp of each UWB exchange (ns)."""
    store = m.typestore()
    out = []
    with Reader(bag) as reader:
        for conn, t, raw in reader.messages():
            if conn.topic in skip:
                continue
            stamps = [] if conn.msgtype == m.STRING else [header_stamp(raw)]
            if conn.msgtype == m.UWB_RANGES:
                msg = store.deserialize_cdr(raw, m.UWB_RANGES)
                stamps += [m.stamp_ns(r.stamp.sec, r.stamp.nanosec) for r in msg.ranges]
            out.append((conn.topic, t, stamps))
    return sorted(out, key=lambda x: (x[1], x[0], x[2]))


@pytest.mark.parametrize("shifted", ["unix-time", "jittered-unix-time"])
def test_recording_a_replayed_bag_writes_its_absolute_stamps_again(
    bags: dict[str, Path], shifted: str, tmp_path: Path
) -> None:
    replay = ReplayBackend(bags[shifted])
    backend = RecordingBackend(replay, BagSink(tmp_path, {"env": ENV}))
    assert backend.clock_origin_ns == UNIX
    start = backend.reset(np.random.default_rng(0))
    assert 0 <= min(s.t for s in start.samples) < 1.0  # small times, from the origin
    while (command := replay.next_command) is not None:
        backend.step(command)
    backend.close()
    # The recorder logs each command at the end of the period before it, which the
    # jittered copy moved; everything else is at its original time and stamp.
    skip = frozenset({m.COMMAND_TOPIC} if shifted.startswith("jittered") else ())
    original = _stamps(bags[shifted], skip)
    assert original == _stamps(tmp_path / "episode_000", skip)
    assert min(t for _, t, _ in original) >= UNIX
