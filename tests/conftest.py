"""Shared fixtures."""

from __future__ import annotations

import gymnasium as gym
import pytest

import tensegrity_gym  # noqa: F401  (registers the envs)

ENV_IDS = sorted(env_id for env_id in gym.registry if env_id.startswith("tensegrity_gym/"))


@pytest.fixture
def three_bar_env():
    env = gym.make("tensegrity_gym/ThreeBarRoll-v0")
    yield env
    env.close()
