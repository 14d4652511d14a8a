"""Env benchmarks: throughput against the bare physics ceiling, and memory growth.

Every figure is measured in one run of one process, so ratios compare like with like
on a shared, noisy machine.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any, cast

import gymnasium as gym
import numpy as np

import tensegrity_gym  # noqa: F401  (registers the envs)

if TYPE_CHECKING:
    from collections.abc import Callable

    from numpy.typing import NDArray

    from tensegrity_gym.envs.tensegrity_env import TensegrityEnv
    from tensegrity_gym.sim.backend import SimBackend

__all__ = ["bench_env_speed", "bench_env_speed_ratio", "bench_memory", "ms_per_step", "rss_mb"]


def rss_mb(pid: int | str = "self") -> float:
    """Resident set size (MB) of a process on this machine (this one by default)."""
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def _bare_physics_rate(env: Any, steps: int) -> float:
    """Physics steps per second of the engine alone: PyBullet's bodies with no cables,
    MuJoCo's model (its cables included), no sensors or env."""
    world = env.unwrapped.backend.world
    t = time.perf_counter()
    world.step_bare(steps)
    return steps / (time.perf_counter() - t)


def _timed_steps(env: Any, actions: NDArray[np.float32], clock: Callable[[], float]) -> float:
    """Seconds by ``clock`` to step ``env`` through ``actions``, resetting where an
    episode ends."""
    t = clock()
    for a in actions:
        _, _, terminated, truncated, _ = env.step(a)
        if terminated or truncated:
            env.reset()
    return clock() - t


def ms_per_step(env: Any, actions: NDArray[np.float32], seed: int) -> float:
    """Process-time ms per env step over ``actions`` from ``reset(seed)``, the first 10
    not timed (warm-up: caches, first allocations), resetting where an episode ends."""
    env.reset(seed=seed)
    for a in actions[:10]:
        env.step(a)
    seconds = _timed_steps(env, actions[10:], time.process_time)
    return 1e3 * seconds / max(len(actions) - 10, 1)


def bench_env_speed(
    env_id: str, steps: int, estimator: str = "oracle", seed: int = 0, engine: str = "pybullet"
) -> dict[str, Any]:
    """Env steps per second under uniformly random actions, resets included, on the
    physics ``engine``."""
    env = gym.make(env_id, estimator=estimator, engine=engine)
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    shape = env.action_space.shape or ()
    actions = rng.uniform(-1.0, 1.0, (steps, *shape)).astype(np.float32)
    for a in actions[:20]:  # warm-up: caches, first allocations
        env.step(a)
    rate = steps / _timed_steps(env, actions, time.perf_counter)
    backend = cast("SimBackend", cast("TensegrityEnv", env.unwrapped).backend)
    physics_per_env_step = round(backend.control_period / backend.time_step)
    env.reset(seed=seed)
    bare = _bare_physics_rate(env, 20000) / physics_per_env_step
    env.close()
    return {
        "env": env_id,
        "engine": engine,
        "estimator": estimator,
        "steps": steps,
        "env_steps_per_s": round(rate, 1),
        "bare_physics_env_steps_per_s": round(bare, 1),
        "fraction_of_ceiling": round(rate / bare, 3),
    }


def bench_env_speed_ratio(
    env_id: str,
    estimator: str,
    steps: int = 300,
    repeats: int = 6,
    seed: int = 0,
) -> dict[str, Any]:
    """The env's speed with ``estimator`` over its speed with the oracle, on a shared
    machine: ``repeats`` runs of each, alternated, over the same ``steps`` uniformly
    random actions from ``reset(seed)`` (the first 10 not timed), in process time; the
    least time of each is its cost (other processes only ever add to it).

    Returns ms per step (least and median) for both and ``ratio`` = oracle's least over
    ``estimator``'s least (1: as fast as the oracle)."""
    envs = {name: gym.make(env_id, estimator=name) for name in ("oracle", estimator)}
    shape = envs["oracle"].action_space.shape or ()
    actions = np.random.default_rng(seed).uniform(-1.0, 1.0, (steps, *shape)).astype(np.float32)
    times: dict[str, list[float]] = {name: [] for name in envs}
    for _ in range(repeats):
        for name, env in envs.items():
            times[name].append(ms_per_step(env, actions, seed))
    for env in envs.values():
        env.close()
    least = {name: min(t) for name, t in times.items()}
    return {
        "env": env_id,
        "steps": steps,
        "repeats": repeats,
        **{f"{name}_ms_per_step": round(least[name], 3) for name in envs},
        **{
            f"{name}_ms_per_step_median": round(float(np.median(t)), 3) for name, t in times.items()
        },
        "ratio": round(least["oracle"] / least[estimator], 3),
    }


def bench_memory(
    env_id: str, steps: int, seed: int = 0, engine: str = "pybullet"
) -> dict[str, Any]:
    """Growth of the process (MB) over ``steps`` env steps with episodes resetting, on the
    physics ``engine``."""
    env = gym.make(env_id, estimator="ukf", engine=engine)
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    shape = env.action_space.shape

    def run(n: int) -> None:
        for _ in range(n):
            _, _, terminated, truncated, _ = env.step(
                rng.uniform(-1.0, 1.0, shape).astype(np.float32)
            )
            if terminated or truncated:
                env.reset()

    run(1000)  # warm-up
    before = rss_mb()
    t = time.perf_counter()
    run(steps)
    elapsed = time.perf_counter() - t
    after = rss_mb()
    env.close()
    return {
        "env": env_id,
        "steps": steps,
        "rss_before_mb": round(before, 1),
        "rss_after_mb": round(after, 1),
        "growth_mb": round(after - before, 2),
        "env_steps_per_s": round(steps / elapsed, 1),
    }
