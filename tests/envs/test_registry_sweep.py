"""A sweep over the simulated namespace (every id made, reset and stepped, as a user's
``check_env`` loop or a benchmark goes over the registry) reaches for no network: the
robot's ids live in a namespace of their own (``tensegrity_gym_hardware``)."""

from __future__ import annotations

import socket
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import tensegrity_gym


class _NetworkCallError(AssertionError):
    pass


@pytest.fixture
def no_network(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Every socket connection and Zenoh session refused, and listed."""
    calls: list[str] = []

    def refuse(what: str) -> Any:
        def call(*args: Any, **kwargs: Any) -> Any:
            calls.append(what)
            raise _NetworkCallError(f"{what} during a sweep of the simulated namespace")

        return call

    monkeypatch.setattr(socket.socket, "connect", refuse("socket.connect"))
    monkeypatch.setattr(socket, "create_connection", refuse("socket.create_connection"))
    import zenoh

    monkeypatch.setattr(zenoh, "open", refuse("zenoh.open"))
    return calls


def test_the_namespaces_hold_what_they_say() -> None:
    simulated = tensegrity_gym.env_ids()
    robot = tensegrity_gym.env_ids(hardware=True)
    assert simulated and robot and not set(simulated) & set(robot)
    assert all(i.startswith(f"{tensegrity_gym.NAMESPACE}/") for i in simulated)
    assert all(i.startswith(f"{tensegrity_gym.HARDWARE_NAMESPACE}/") for i in robot)
    assert not any("driver" in gym.spec(i).kwargs for i in simulated)
    assert all("driver" in gym.spec(i).kwargs and gym.spec(i).nondeterministic for i in robot)
    assert tensegrity_gym.env_ids(hardware=None) == sorted(simulated + robot)


def test_a_registry_sweep_makes_no_network_call(no_network: list[str]) -> None:
    swept = [i for i in gym.registry if i.startswith(f"{tensegrity_gym.NAMESPACE}/")]
    assert sorted(swept) == tensegrity_gym.env_ids()
    for env_id in swept:
        env = gym.make(env_id)
        try:
            obs, _ = env.reset(seed=0)
            obs, reward, *_ = env.step(env.action_space.sample())
            assert np.all(np.isfinite(obs)) and np.isfinite(reward), env_id
        finally:
            env.close()
    assert no_network == []


def test_the_guard_sees_a_robot_id(no_network: list[str]) -> None:
    """The fixture is not blind: making a robot's id is caught at its first call."""
    robot = tensegrity_gym.env_ids(hardware=True)[0]
    with pytest.raises(Exception):  # noqa: B017 (whatever the driver wraps it in)
        gym.make(robot).reset(seed=0)
    assert no_network
