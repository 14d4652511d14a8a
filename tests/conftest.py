"""Shared fixtures."""

from __future__ import annotations

import os
import sys
from typing import TYPE_CHECKING, Any

# MuJoCo picks its OpenGL platform when it is first imported, and a test module may import
# it before tensegrity_gym.sim.mujoco_world asks for EGL: headless, ask for it here.
if sys.platform.startswith("linux") and not os.environ.get("DISPLAY"):
    os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium as gym
import pytest

import tensegrity_gym

if TYPE_CHECKING:
    from collections.abc import Callable, Iterator

    from hardware.link.process import EmulatorProcess

ENV_IDS = tensegrity_gym.env_ids(hardware=None)
"""Every id: the simulated namespace's and the robot's."""
HARDWARE_IDS = tensegrity_gym.env_ids(hardware=True)
"""Ids of robots on the network: the tests run them against the emulator."""
# The InEKF's three test modules (test_inekf, test_shape, test_inekf_filter) share one worker
# (``pytestmark = INEKF_GROUP``): it compiles the filter's and shape solver's kernels once
# for them (numba, over a minute from a cold cache), where split across workers each
# compiled them. Other modules that run the InEKF still compile on their own worker.
INEKF_GROUP = pytest.mark.xdist_group("inekf")


@pytest.fixture(scope="module")
def emulators() -> Iterator[Callable[[str], EmulatorProcess]]:
    """An emulator process per robot, started on first use, stopped after the module
    (they run in real time: none should outlive the tests that use it)."""
    from hardware.link.process import EmulatorProcess

    started: dict[str, EmulatorProcess] = {}

    def get(robot: str) -> EmulatorProcess:
        if robot not in started:
            started[robot] = EmulatorProcess(robot).start()
        return started[robot]

    yield get
    for process in started.values():
        process.stop()


@pytest.fixture
def make_env(emulators: Callable[[str], EmulatorProcess]) -> Callable[..., gym.Env]:
    """``gym.make`` that points a hardware id at an emulator of its robot."""

    def make(env_id: str, **kwargs: Any) -> gym.Env:
        spec = gym.spec(env_id)
        if spec.nondeterministic:
            kwargs.setdefault("driver", emulators(spec.kwargs["robot"]).address)
        return gym.make(env_id, **kwargs)

    return make


@pytest.fixture
def three_bar_env():
    env = gym.make("tensegrity_gym/ThreeBarRoll-v0")
    yield env
    env.close()
