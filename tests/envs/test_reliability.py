"""Reliability of the env (issue 12): every argument of ``make`` is checked by name, the
reward is bounded by what the robot can travel, a simulation that blows up while
settling is reported as such, and a failed reset leaves nothing half done (no command
from a dead episode, the motors stopped, Gymnasium's checker re-armed)."""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
import pytest
import yaml

from hardware.link import DriverTimeouts, LinkError, ZenohDriver
from hardware.link.process import EmulatorProcess, free_port
from tensegrity_gym.envs.factory import make_env
from tensegrity_gym.model.description import load_robot, robot_document
from tensegrity_gym.model.estimate import Estimate
from tensegrity_gym.model.samples import ImuSample
from tensegrity_gym.sim.backend import SettleError, SimBackend
from tensegrity_gym.tasks.roll import RollTask

if TYPE_CHECKING:
    from collections.abc import Sequence
    from pathlib import Path

    from numpy.typing import NDArray

ENV_ID = "tensegrity_gym/ThreeBarRoll-v0"
HARDWARE_ID = "tensegrity_gym_hardware/ThreeBarRoll-v0"
THREE_BAR = load_robot("three_bar")


# ------------------------------------------------------------------ make's arguments

BAD_ARGUMENTS = [
    ("goal_heading", math.nan),
    ("goal_heading", math.inf),
    ("goal_distance", math.nan),
    ("goal_distance", math.inf),
    ("goal_distance", 0.0),
    ("ctrl_cost", math.nan),
    ("ctrl_cost", -math.inf),
    ("ctrl_cost", -0.1),
    ("spawn_radius", math.nan),
    ("spawn_radius", math.inf),
    ("spawn_radius", -1.0),
    ("control_period", math.nan),
    ("control_period", math.inf),
    ("control_period", 0.0),
    ("time_step", math.nan),
    ("time_step", math.inf),
    ("time_step", 0.0),
    ("time_step", 0.5),  # longer than the control period
    ("ctrl_cost", "cheap"),
    ("spawn_radius", True),
    ("render_mode", "vr"),
    ("record_dir", 3),
]


@pytest.mark.parametrize(("name", "value"), BAD_ARGUMENTS)
def test_every_argument_of_make_is_checked_by_name(name: str, value: object) -> None:
    with pytest.raises(ValueError, match=f"{name}=") as info:
        gym.make(ENV_ID, estimator="oracle", **{name: value})
    assert "\n" not in str(info.value)


def test_valid_arguments_still_pass() -> None:
    env = gym.make(
        ENV_ID, estimator="oracle", goal_heading=None, goal_distance=1.0, ctrl_cost=0.0,
        spawn_radius=0.5, control_period=0.05, time_step=0.001,
    )  # fmt: skip
    obs, _ = env.reset(seed=0)
    assert np.all(np.isfinite(obs))
    env.close()


class _ClosingSim(SimBackend):
    """A simulator that counts its ``close`` calls."""

    closed = 0

    def close(self) -> None:
        type(self).closed += 1
        super().close()


def test_a_make_that_fails_after_the_backend_is_up_closes_it(tmp_path: Path) -> None:
    """A record_dir that cannot be made (a file is in the way) fails ``make`` after the
    backend started; the backend (a simulator, a link session) is closed, not leaked."""
    blocked = tmp_path / "runs"
    blocked.write_text("not a folder")
    backend = _ClosingSim(THREE_BAR)
    _ClosingSim.closed = 0
    with pytest.raises(OSError):
        make_env(THREE_BAR, estimator="oracle", driver=backend, record_dir=blocked)
    assert _ClosingSim.closed == 1


# ------------------------------------------------------------------------- reward


def _estimate(com: Sequence[float]) -> Estimate:
    c = np.asarray(com, dtype=np.float64)
    nodes = THREE_BAR.initial_positions - THREE_BAR.initial_positions.mean(axis=0) + c
    return Estimate(0.0, nodes, np.zeros_like(nodes), c, THREE_BAR.rest_lengths[:6])


def test_a_step_beyond_what_the_robot_can_travel_earns_no_reward() -> None:
    task = RollTask(THREE_BAR, control_period=0.1)
    assert 0.1 < task.max_step < 1.0  # metres in a 0.1 s period for a 0.33 m robot
    a = np.zeros(6, dtype=np.float32)
    start = _estimate([0.0, 0.0, 0.1])
    assert task.implausible_step(start, _estimate([0.05, 0.0, 0.1])) is None
    assert task.reward(start, _estimate([0.05, 0.0, 0.1]), a) > 0.0
    for far in ([1.0e4, 0.0, 0.1], [-5.0e10, 0.0, 0.1], [0.0, 3.0, 0.1]):
        reason = task.implausible_step(start, _estimate(far))
        assert reason is not None and "cannot travel" in reason
        assert task.reward(start, _estimate(far), a) == 0.0
    assert task.implausible_step(start, _estimate([math.nan, 0.0, 0.1])) is not None
    # A restarted estimator's jump, however short, is not the robot's motion.
    restarted = dataclasses.replace(_estimate([0.05, 0.0, 0.1]), reinitialised=True)
    assert "started again" in (task.implausible_step(start, restarted) or "")


class _JumpingEstimator:
    """The oracle, with its CoM thrown kilometres away from step ``at`` on."""

    needs_camera = False

    def __init__(self, at: int) -> None:
        self.at, self.updates = at, 0
        self.inner: Any = None
        self.truth: Any = None

    def reset(self, description: Any, calibration: Any, samples: Any, command: Any,
              rng: Any) -> Estimate:  # fmt: skip
        from estimation.oracle import OracleEstimator

        self.inner = OracleEstimator(self.truth)
        self.updates = 0
        return self.inner.reset(description, calibration, samples, command, rng)

    def update(self, samples: Any, command: NDArray[np.float64]) -> Estimate:
        self.updates += 1
        e = self.inner.update(samples, command)
        if self.updates < self.at:
            return e
        shift = np.array([5.0e3, -2.0e3, 0.0]) * (self.updates - self.at + 1)
        return Estimate(e.t, e.node_positions + shift, e.node_velocities, e.com + shift,
                        e.rest_lengths)  # fmt: skip


def test_the_env_zeroes_and_explains_an_implausible_reward() -> None:
    estimator = _JumpingEstimator(at=3)
    env = gym.make(ENV_ID, estimator=estimator)
    estimator.truth = env.unwrapped.backend.ground_truth  # type: ignore[attr-defined]
    env.reset(seed=0)
    rewards, reasons = [], []
    for _ in range(5):
        _, reward, _, _, info = env.step(env.action_space.sample())
        rewards.append(reward)
        reasons.append(info["reward_rejected"])
    env.close()
    assert reasons[:2] == [None, None] and all(abs(r) < 5.0 for r in rewards[:2])
    assert all(r == 0.0 for r in rewards[2:]), rewards
    assert all(r is not None and "cannot travel" in r for r in reasons[2:]), reasons


class _GenerousTask(RollTask):
    """A task (a lab's own, say) whose reward forgets to zero an implausible step."""

    def reward(self, previous: Estimate, estimate: Estimate, action: NDArray[np.float32]) -> float:
        return 5.0


def test_the_env_zeroes_an_implausible_step_whatever_the_task_rewards() -> None:
    """``info["reward_rejected"]`` and the reward agree: the env, not only the built-in
    tasks, gives an implausible step 0."""
    estimator = _JumpingEstimator(at=2)
    env = gym.make(ENV_ID, estimator=estimator)
    inner: Any = env.unwrapped
    estimator.truth = inner.backend.ground_truth
    inner.task = _GenerousTask(THREE_BAR)
    env.reset(seed=0)
    steps = [env.step(env.action_space.sample()) for _ in range(3)]
    env.close()
    assert [s[4]["reward_rejected"] is None for s in steps] == [True, False, False]
    assert [s[1] for s in steps] == [5.0, 0.0, 0.0]


# ------------------------------------------------------------- settling blows up


def _robot_file(tmp_path: Path, edit: Any) -> Path:
    doc = copy.deepcopy(robot_document(THREE_BAR))
    edit(doc)
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def _slow_sensors(doc: dict[str, Any]) -> None:
    for sensor in ("imu", "encoder", "contact"):
        doc["sensors"][sensor]["rate"] = 10.0


def _stiff(doc: dict[str, Any]) -> None:
    doc["cables"][2]["stiffness"] = 1.0e12


def _weightless(doc: dict[str, Any]) -> None:
    doc["rods"][1]["mass"] = 1.0e-9


@pytest.mark.parametrize(
    ("edit", "time_step", "needles"),
    [
        (_slow_sensors, 0.02, ["time_step=0.02", "lower time_step"]),
        (_stiff, 0.001, ["cables[2]", "stiffness 1e+12"]),
        (_weightless, 0.001, ["'green'", "1e-09", "masses"]),
    ],
    ids=["time_step", "stiffness", "mass"],
)
@pytest.mark.parametrize("estimator", ["ukf", "oracle"])
def test_a_simulation_that_blows_up_while_settling_is_reported_at_reset(
    tmp_path: Path, edit: Any, time_step: float, needles: list[str], estimator: str
) -> None:
    path = _robot_file(tmp_path, edit)
    env = gym.make(ENV_ID, robot=str(path), estimator=estimator, time_step=time_step)
    with pytest.raises(SettleError, match="diverged while the robot settled") as info:
        env.reset(seed=0)
    for needle in needles:
        assert needle in str(info.value), str(info.value)
    assert str(path) in str(info.value)
    env.close()


def test_a_sensor_faster_than_the_physics_is_refused(tmp_path: Path) -> None:
    path = _robot_file(tmp_path, lambda doc: doc["sensors"]["imu"].update(rate=2000.0))
    with pytest.raises(ValueError, match=r"sensors\.imu\.rate=2000 Hz is above the physics"):
        gym.make(ENV_ID, robot=str(path), estimator="oracle")
    with pytest.raises(ValueError, match=r"sensors\.imu\.rate=200 Hz"):
        SimBackend(THREE_BAR, time_step=0.02, control_period=0.1)


# --------------------------------------------------------------- a failed reset


class _FlakyBackend:
    """A simulated robot whose first ``failures`` resets raise, counting steps and stops."""

    def __init__(self, failures: int) -> None:
        self.inner = SimBackend(THREE_BAR)
        self.description = THREE_BAR
        self.control_period = self.inner.control_period
        self.failures, self.steps, self.stops = failures, 0, 0

    @property
    def calibration(self) -> Any:
        return self.inner.calibration

    def reset(self, rng: np.random.Generator, *, ready: Any = None) -> Any:
        if self.failures > 0:
            self.failures -= 1
            raise ConnectionError("the robot is not up yet")
        return self.inner.reset(rng)

    def step(self, targets: NDArray[np.float64]) -> Any:
        self.steps += 1
        return self.inner.step(targets)

    def stop(self) -> None:
        self.stops += 1

    def ground_truth(self) -> Any:
        return self.inner.ground_truth()

    def render(self, width: int, height: int) -> Any:
        return self.inner.render(width, height)

    def close(self) -> None:
        self.inner.close()


def test_a_failed_first_reset_leaves_the_env_usable_with_the_env_checker() -> None:
    backend = _FlakyBackend(failures=1)
    env = gym.make(ENV_ID, driver=backend, estimator="oracle")  # passive checker on
    with pytest.raises(ConnectionError):
        env.reset(seed=0)
    assert backend.stops >= 1
    with pytest.raises(RuntimeError, match="call reset"):
        env.step(env.action_space.sample())
    assert backend.steps == 0  # no command from an episode that never began
    env.reset(seed=0)
    for _ in range(3):
        obs, reward, *_ = env.step(env.action_space.sample())
        assert np.all(np.isfinite(obs)) and np.isfinite(reward)
    assert backend.steps == 3
    env.close()


def test_a_failed_later_reset_does_not_step_the_previous_episode() -> None:
    backend = _FlakyBackend(failures=0)
    env = gym.make(ENV_ID, driver=backend, estimator="oracle")
    env.reset(seed=0)
    env.step(env.action_space.sample())
    backend.failures = 1
    with pytest.raises(ConnectionError):
        env.reset(seed=1)
    with pytest.raises(RuntimeError, match="call reset"):
        env.step(env.action_space.sample())
    assert backend.steps == 1
    env.close()


def test_an_error_outside_the_env_in_the_stack_stops_the_motors(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The robot's id (a simulated one has no motors, and no StopOnError: docs/envs.md)."""
    backend = _FlakyBackend(failures=0)
    env = gym.make(HARDWARE_ID, driver=backend, estimator="oracle")
    env.reset(seed=0)

    def broken_step(self: Any, action: Any) -> Any:
        self.env.step(action)
        raise TypeError("a wrapper failed after the env returned")

    monkeypatch.setattr(gym.wrappers.TimeLimit, "step", broken_step)
    stops = backend.stops
    with pytest.raises(TypeError, match="wrapper failed"):
        env.step(env.action_space.sample())
    assert backend.stops == stops + 1
    monkeypatch.undo()
    env.close()


def test_an_env_made_before_the_robot_is_up_works_once_it_is() -> None:
    port = free_port()
    driver = ZenohDriver(
        THREE_BAR, f"zenoh/tcp/127.0.0.1:{port}", timeouts=DriverTimeouts(connect=3.0)
    )
    env = gym.make("tensegrity_gym_hardware/ThreeBarRoll-v0", driver=driver, estimator="ukf")
    try:
        with pytest.raises(LinkError):
            env.reset(seed=0)
        with EmulatorProcess("three_bar", port=port):
            env.reset(seed=0)
            for _ in range(3):
                obs, reward, _, _, info = env.step(env.action_space.sample())
                assert np.all(np.isfinite(obs)) and np.isfinite(reward)
            assert not info["link_stalled"]
    finally:
        env.close()


def test_the_simulated_imu_saturates_at_its_full_scale() -> None:
    """An IMU reports no more than its full scale: with a 2 m/s^2 accelerometer at rest
    (gravity alone reads 9.81 m/s^2) readings are clipped there."""
    imu = replace(THREE_BAR.sensors.imu, accel_full_scale=2.0, gyro_full_scale=1e-3)
    d = replace(THREE_BAR, sensors=replace(THREE_BAR.sensors, imu=imu))
    backend = SimBackend(d)
    backend.reset(np.random.default_rng(0))
    samples = [s for s in backend.step(d.rest_lengths[d.actuated]).samples
               if isinstance(s, ImuSample)]  # fmt: skip
    backend.close()
    accel = np.array([s.accel for s in samples])
    gyro = np.array([s.gyro for s in samples])
    assert np.abs(accel).max() == 2.0 and np.abs(gyro).max() == 1e-3


def test_the_oracle_without_ground_truth_says_so_and_survives_a_dropped_frame() -> None:
    from estimation.oracle import OracleEstimator

    backend = SimBackend(THREE_BAR)
    start = backend.reset(np.random.default_rng(0))
    frames: list[Any] = [None]
    oracle = OracleEstimator(lambda: frames[-1])
    calibration = backend.calibration
    command = THREE_BAR.rest_lengths[THREE_BAR.actuated]
    missing = oracle.initialisation_missing(THREE_BAR, calibration, start.samples)
    assert missing is not None and "ground truth" in missing
    with pytest.raises(ValueError, match="needs ground truth"):
        oracle.reset(THREE_BAR, calibration, start.samples, command, np.random.default_rng(0))
    frames.append(backend.ground_truth())
    assert oracle.initialisation_missing(THREE_BAR, calibration, start.samples) is None
    first = oracle.reset(THREE_BAR, calibration, start.samples, command, np.random.default_rng(0))
    assert first.healthy
    frames.append(None)  # a motion-capture frame that did not come
    held = oracle.update(backend.step(command).samples, command)
    backend.close()
    assert not held.healthy
    np.testing.assert_array_equal(held.com, first.com)


def test_commands_outside_the_motor_range_in_a_bag_are_counted(tmp_path: Path) -> None:
    from tests.hardware.test_bag_robustness import _edit_every, _rewrite

    env = gym.make(ENV_ID, estimator="oracle", record_dir=tmp_path / "runs", max_episode_steps=4)
    env.reset(seed=0)
    for _ in range(4):
        env.step(env.action_space.sample())
    env.close()

    def stretch(msg: Any) -> None:
        position = np.array(msg.position)
        position[0] = 5.0  # m: far beyond the motor's 0.24 m
        msg.position = position

    bag = _rewrite(tmp_path / "runs" / "episode_000", tmp_path / "wild",
                   _edit_every("/commands/rest_length_targets", stretch))  # fmt: skip
    replay = gym.make(ENV_ID, estimator="oracle", driver=f"bag:{bag}")
    _, info = replay.reset(seed=0)
    assert info["bag_out_of_range"] == {}
    counts = [replay.step(replay.action_space.sample())[4]["bag_out_of_range"] for _ in range(4)]
    replay.close()
    assert counts[-1] == {"command": 4}, counts


def test_a_jumped_estimate_neither_pays_nor_ends_a_roll_episode() -> None:
    """With a goal distance, an estimate thrown kilometres along the heading does not
    count as progress: the episode is not terminated as done, info's progress stays."""
    estimator = _JumpingEstimator(at=3)
    env = gym.make(ENV_ID, estimator=estimator, goal_distance=0.3)
    estimator.truth = env.unwrapped.backend.ground_truth  # type: ignore[attr-defined]
    env.reset(seed=0)
    for _ in range(5):
        _, _, terminated, _, info = env.step(env.action_space.sample())
        assert not terminated
        assert abs(info["progress"]) < 0.3, info["progress"]
    env.close()
