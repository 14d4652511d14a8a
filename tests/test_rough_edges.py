"""What a new user hit (issue 19): a closed env, reset options, a headless check_env,
PyBullet's banner, the command line's help and a failed ``record``."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from tensegrity_gym.envs.safety import StopOnError
from tensegrity_gym.sim.backend import SimBackend

ROLL = "tensegrity_gym/ThreeBarRoll-v0"


def test_step_and_reset_after_close_raise_and_close_twice_is_harmless() -> None:
    env = gym.make(ROLL)
    assert isinstance(env, StopOnError)
    env.reset(seed=0)
    env.step(env.action_space.sample())
    env.close()
    env.close()  # harmless
    with pytest.raises(RuntimeError, match="step: the env was closed"):
        env.step(env.action_space.sample())
    with pytest.raises(RuntimeError, match="reset: the env was closed"):
        env.reset(seed=0)
    backend = env.unwrapped.backend
    assert isinstance(backend, SimBackend)
    assert backend._world is None  # no new world was built behind the user's back
    env.close()


def test_a_closed_backend_builds_no_new_world() -> None:
    env = gym.make(ROLL)
    env.reset(seed=0)
    backend = env.unwrapped.backend
    backend.close()
    backend.close()
    with pytest.raises(RuntimeError, match="step: the env was closed"):
        backend.step(np.zeros(backend.description.n_actuated) + 0.1)
    with pytest.raises(RuntimeError, match="reset: the env was closed"):
        backend.reset(np.random.default_rng(0))
    with pytest.raises(RuntimeError, match="the env was closed"):
        _ = backend.world
    env.close()
