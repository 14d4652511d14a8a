"""The 1.45 m robot as Tong et al. 2024's: motors that hold a minimum tension (the spool reels
in slack, so the encoders read the cable lengths; without it the same gait leaves
cables slack) and one IMU, on the red rod."""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
import pytest

from tensegrity_gym.envs.factory import make_roll_env
from tensegrity_gym.model.description import load_robot
from tensegrity_gym.model.samples import AhrsSample, EncoderSample, ImuSample
from tensegrity_gym.sim.backend import SimBackend
from tensegrity_gym.tasks.gaits import FaceGait

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.protocols import StepResult

STEPS = 80  # control steps of the forward gait (8 s): its first rolls


def slack_prone(d: RobotDescription) -> RobotDescription:
    """``d`` with motors that let their cables go slack."""
    cables = tuple(
        c if c.motor is None else replace(c, motor=replace(c.motor, min_tension=None))
        for c in d.cables
    )
    return replace(d, cables=cables)


def _roll(
    d: RobotDescription,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """``STEPS`` of the robot's forward gait on the oracle; per control step, the
    actuated cables' true endcap distances, the last encoder reading and the motors'
    targets, each (STEPS, m), m."""
    env = make_roll_env(d, estimator="oracle", calibration="true")
    gait = FaceGait(d, env.task)
    distances, readings, commands = [], [], []
    pairs = d.cable_nodes[d.actuated]
    backend, periods = env.backend, []

    def step(targets: NDArray[np.float64]) -> StepResult:  # keeps each period's samples
        periods.append(result := type(backend).step(backend, targets))
        return result

    backend.step = step  # type: ignore[method-assign]
    try:
        obs, _ = env.reset(seed=0)
        for _ in range(STEPS):
            obs, *_ = env.step(gait(obs))
            truth = env.backend.ground_truth()
            assert truth is not None
            x = truth.node_positions
            encoders = [s for s in periods[-1].samples if isinstance(s, EncoderSample)]
            distances.append(np.linalg.norm(x[pairs[:, 0]] - x[pairs[:, 1]], axis=1))
            readings.append(encoders[-1].rest_lengths)
            commands.append(env.backend.world.targets)
    finally:
        env.close()
    return np.array(distances), np.array(readings), np.array(commands)


@pytest.fixture(scope="module")
def large() -> RobotDescription:
    return load_robot("three_bar_large")


def test_the_encoders_give_the_cable_lengths_of_a_taut_robot(large: RobotDescription) -> None:
    distances, readings, targets = _roll(large)
    stretch = distances - readings
    res = large.sensors.encoder.resolution
    # Never slack (past the encoder's step and a physics step of motion): the distance
    # is the reading plus a stretch of at most the gait's tension over the stiffness.
    assert stretch.min() > -res - 0.005, stretch.min()
    assert stretch.max() < 0.1
    # The spools did reel in: cables let out read well short of their targets.
    assert (targets - readings).max() > 0.1


def test_the_same_gait_leaves_slack_prone_cables_slack(large: RobotDescription) -> None:
    distances, readings, _ = _roll(slack_prone(large))
    assert (distances - readings).min() < -0.1  # a decimetre and more
    lo, hi, _ = large.motor_limits
    step = large.sensors.encoder.resolution  # the readings are quantised
    assert np.all((readings >= lo - step) & (readings <= hi + step))


def test_one_imu_on_the_red_rod(large: RobotDescription) -> None:
    # Tong et al. 2024 VI: "An IMU (VN-100) is attached at the center of the bar with red
    # endcaps": its readings and its AHRS are rod 0's only, at the configured rate.
    backend = SimBackend(large)
    try:
        samples = [*backend.reset(np.random.default_rng(0)).samples]
        for _ in range(5):
            samples += backend.step(large.rest_lengths[large.actuated]).samples
    finally:
        backend.close()
    imu = [s for s in samples if isinstance(s, ImuSample)]
    ahrs = [s for s in samples if isinstance(s, AhrsSample)]
    assert {s.rod for s in imu} == {s.rod for s in ahrs} == {0}
    assert len(imu) == len(ahrs) == 1 + round(0.5 * large.sensors.imu.rate)
    # At rest, the accelerometer reads g (specific force, up).
    assert np.linalg.norm(imu[-1].accel) == pytest.approx(large.gravity, abs=0.2)
