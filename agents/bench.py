"""Benchmarks: env throughput against the bare physics ceiling, and memory growth.

Every figure is measured in one run of one process, so ratios compare like with like
on a shared, noisy machine.
"""

from __future__ import annotations

import os
import platform
import time
from typing import TYPE_CHECKING, Any, cast

import gymnasium as gym
import numpy as np

import tensegrity_gym  # noqa: F401  (registers the envs)

if TYPE_CHECKING:
    from tensegrity_gym.envs.roll_env import TensegrityEnv
    from tensegrity_gym.sim.backend import SimBackend

__all__ = ["bench_env_speed", "bench_memory", "run_benchmarks"]


def _rss_mb() -> float:
    """Resident set size of this process (MB)."""
    with open("/proc/self/statm") as f:
        pages = int(f.read().split()[1])
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20


def _bare_physics_rate(env: Any, steps: int) -> float:
    """Physics steps per second of the same bodies with no cables, sensors or env."""
    world = env.unwrapped.backend.world
    t = time.perf_counter()
    world.step_bare(steps)
    return steps / (time.perf_counter() - t)


def bench_env_speed(
    env_id: str, steps: int, estimator: str = "oracle", seed: int = 0
) -> dict[str, Any]:
    """Env steps per second under uniformly random actions, resets included."""
    env = gym.make(env_id, estimator=estimator)
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    shape = env.action_space.shape or ()
    actions = rng.uniform(-1.0, 1.0, (steps, *shape)).astype(np.float32)
    for a in actions[:20]:  # warm-up: caches, first allocations
        env.step(a)
    t = time.perf_counter()
    for a in actions:
        _, _, terminated, truncated, _ = env.step(a)
        if terminated or truncated:
            env.reset()
    rate = steps / (time.perf_counter() - t)
    backend = cast("SimBackend", cast("TensegrityEnv", env.unwrapped).backend)
    physics_per_env_step = round(backend.control_period / backend.time_step)
    env.reset(seed=seed)
    bare = _bare_physics_rate(env, 20000) / physics_per_env_step
    env.close()
    return {
        "env": env_id,
        "estimator": estimator,
        "steps": steps,
        "env_steps_per_s": round(rate, 1),
        "bare_physics_env_steps_per_s": round(bare, 1),
        "fraction_of_ceiling": round(rate / bare, 3),
    }


def bench_memory(env_id: str, steps: int, seed: int = 0) -> dict[str, Any]:
    """Growth of the process (MB) over ``steps`` env steps with episodes resetting."""
    env = gym.make(env_id, estimator="ukf")
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
    before = _rss_mb()
    t = time.perf_counter()
    run(steps)
    elapsed = time.perf_counter() - t
    after = _rss_mb()
    env.close()
    return {
        "env": env_id,
        "steps": steps,
        "rss_before_mb": round(before, 1),
        "rss_after_mb": round(after, 1),
        "growth_mb": round(after - before, 2),
        "env_steps_per_s": round(steps / elapsed, 1),
    }


def run_benchmarks(
    speed_steps: int = 2000,
    memory_steps: int = 100_000,
    estimation: bool = False,
    bag_minutes: float = 10.0,
    link_steps: int = 300,
    soak_minutes: float = 0.0,
) -> dict[str, Any]:
    """Env speed (oracle and UKF), memory, the bag layer (:mod:`agents.bench_bags`) and
    the robot link against the emulator (:mod:`agents.bench_link`, ``link_steps`` 10 Hz
    steps, and a soak of ``soak_minutes``); with ``estimation``, also the estimation
    study and the UKF's speed against filterpy's (:mod:`agents.bench_estimation`)."""
    results: dict[str, Any] = {
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
        },
        "speed": [
            bench_env_speed("tensegrity_gym/ThreeBarRoll-v0", speed_steps),
            bench_env_speed("tensegrity_gym/SuperBallRoll-v0", max(speed_steps // 2, 100)),
            bench_env_speed("tensegrity_gym/ThreeBarRoll-v0", speed_steps, estimator="ukf"),
            bench_env_speed(
                "tensegrity_gym/SuperBallRoll-v0", max(speed_steps // 2, 100), estimator="ukf"
            ),
        ],
        "targets": {
            "tensegrity_gym/ThreeBarRoll-v0 oracle env_steps_per_s": 400,
            "tensegrity_gym/SuperBallRoll-v0 oracle env_steps_per_s": 150,
            "tensegrity_gym/ThreeBarRoll-v0 ukf env_steps_per_s": 250,
            "tensegrity_gym/SuperBallRoll-v0 ukf env_steps_per_s": 80,
            "memory growth_mb per 100k steps (ukf in the loop)": 50,
        },
    }
    if estimation:
        from agents.bench_estimation import bench_estimation, bench_filter_speed

        results["filter_speed"] = [
            bench_filter_speed("tensegrity_gym/ThreeBarRoll-v0"),
            bench_filter_speed("tensegrity_gym/SuperBallRoll-v0"),
        ]
        results["filter_speed_targets"] = {
            "three_bar fast_filter_step_ms_median": 2.0,
            "superball fast_filter_step_ms_median": 5.0,
            "speedup_vs_filterpy_numpy_model": 50,
        }
        results["estimation"] = bench_estimation()
        from agents.bench_icp import bench_icp

        results["icp"] = bench_icp()
    if bag_minutes > 0:
        from agents.bench_bags import bench_bags

        results["bags"] = bench_bags(minutes=bag_minutes)
    if link_steps > 0 or soak_minutes > 0:
        from agents.bench_link import bench_latency, bench_soak, bench_throughput

        link: dict[str, Any] = {}
        if link_steps > 0:
            link["latency"] = bench_latency(link_steps)
            link["throughput"] = bench_throughput(max(link_steps * 2 // 3, 50))
        if soak_minutes > 0:
            link["soak"] = bench_soak(soak_minutes)
        link["targets"] = {
            "driver_added_latency_ms median and p99": 5.0,
            "throughput dropped_on_driver_side": 0,
            "soak growth": "none in memory or latency",
        }
        results["link"] = link
    if memory_steps > 0:
        results["memory"] = bench_memory("tensegrity_gym/ThreeBarRoll-v0", memory_steps)
    return results
