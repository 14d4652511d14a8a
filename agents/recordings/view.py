"""``tensegrity-gym view``: watch a run live in Foxglove.

A simulation driven by a policy (the robot's face gait, random actions, or a training
run), a robot on the network (``driver``), or a recorded bag replayed, runs with
``render_mode="foxglove"``: a Foxglove
WebSocket server at ``ws://localhost:PORT`` streams the run's topics (the robot as
markers, ``/tf``, the URDF, the sensors, the estimate) as it goes, in real time or at
``speed``. Open Foxglove, connect to the address, and load
``examples/foxglove_layout.json``.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

import gymnasium as gym

from agents.recordings.offline import make_policy, policy_env_kwargs
from hardware.viewer import DEFAULT_PORT

if TYPE_CHECKING:
    from pathlib import Path

__all__ = ["view"]

log = logging.getLogger(__name__)


def view(
    env_id: str,
    policy: str = "scripted",
    *,
    bag: Path | None = None,
    driver: str | None = None,
    port: int = DEFAULT_PORT,
    speed: float = 1.0,
    episodes: int = 0,
    steps: int | None = None,
    seed: int = 0,
    estimator: str = "ukf",
) -> int:
    """Stream ``episodes`` episodes (0: until interrupted) of ``policy`` on ``env_id``
    (on the robot at ``driver``, ``"zenoh/tcp/HOST:PORT"``, where given), or of ``bag``
    replayed (its own commands drive it), to a Foxglove live view on ``port``, at
    ``speed`` times real time (0: as fast as they run; a robot runs at its own pace).
    Returns the number of episodes streamed; the server stops on return (Ctrl-C
    included)."""
    if episodes < 0:
        raise ValueError(f"episodes must be 0 (until interrupted) or more, got {episodes}")
    if bag is not None and driver is not None:
        raise ValueError("view: give a bag or a driver, not both")
    kwargs: dict[str, Any] = {
        "render_mode": "foxglove",
        "viewer_port": port,
        "viewer_speed": speed,
        "estimator": estimator,
    }
    if bag is not None or driver is not None:
        kwargs["driver"] = f"bag:{bag}" if bag is not None else driver
    if steps is not None:
        kwargs["max_episode_steps"] = steps
    env = gym.make(env_id, **kwargs, **policy_env_kwargs(policy))
    act, reset_policy = make_policy(policy, env, seed)
    done_episodes = 0
    try:
        while not episodes or done_episodes < episodes:
            obs, _ = env.reset(seed=seed + done_episodes)
            reset_policy()
            done = False
            while not done:
                obs, _, terminated, truncated, _ = env.step(act(obs))
                done = terminated or truncated
            done_episodes += 1
            log.info("episode %d streamed", done_episodes)
    finally:
        env.close()
    return done_episodes
