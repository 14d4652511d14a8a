"""The physics engines side by side: MuJoCo's env against its bare ``mj_step`` and
against PyBullet's env, with the oracle and with the UKF in the loop.

Every figure comes from one run of one process, the envs stepped in turn (alternated
repeats, the least process time of each: other processes only ever add to it), so the
ratios compare like with like on a shared, noisy machine.
"""

from __future__ import annotations

import time
from typing import Any

import gymnasium as gym
import numpy as np

import tensegrity_gym  # noqa: F401  (registers the envs)
from agents.benchmarks.env import ms_per_step

__all__ = ["ENGINE_TARGETS", "bench_engines", "bench_vector", "replayed_ms_per_period"]

ENGINE_TARGETS = {
    "mujoco_oracle_over_bare_mj_step": 0.9,
    "mujoco_over_pybullet_oracle": 2.0,
    "mujoco_over_pybullet_ukf": 1.5,
    "vector_over_single_per_core (N = 16, ukf)": 3.0,
}
"""Issue 41's figures: each ratio at least this."""

_ENGINES = ("pybullet", "mujoco")
_ESTIMATORS = ("oracle", "ukf")


def _bare_ms_per_period(env: Any, periods: int) -> float:
    """Process-time ms per control period of the engine's bare step of the same model
    (MuJoCo: ``mj_step`` with the cables, which are part of its model; PyBullet: the
    bodies without them)."""
    backend = env.unwrapped.backend
    steps = periods * round(backend.control_period / backend.time_step)
    t = time.process_time()
    backend.world.step_bare(steps)
    return 1e3 * (time.process_time() - t) / periods


def replayed_ms_per_period(env: Any, actions: Any, seed: int) -> float:
    """Process-time ms per control period of MuJoCo's bare ``mj_step`` through the
    env's own periods: the env stepped over ``actions`` from ``reset(seed)`` as
    :func:`~agents.benchmarks.env.ms_per_step` steps it (the first 10 periods not
    counted), untimed, to the episode's end at most, with its world's
    :attr:`~tensegrity_gym.sim.mujoco_world.MujocoWorld.trace` on; then the traced calls
    replayed from the state they began at, timed. The env is left where it ended."""
    if len(actions) <= 10:
        raise ValueError(f"replayed_ms_per_period needs more than 10 actions, got {len(actions)}")
    world = env.unwrapped.backend.world
    env.reset(seed=seed)
    for a in actions[:10]:
        env.step(a)
    start, world.trace = world.save_state(), []
    periods = 0
    try:
        for a in actions[10:]:
            periods += 1
            if any(env.step(a)[2:4]):
                break
        trace = world.trace
    finally:
        world.trace = None
    end = world.save_state()
    world.restore_state(start)
    t = time.process_time()
    world.replay(trace)
    seconds = time.process_time() - t
    world.restore_state(end)
    return 1e3 * seconds / periods


def bench_engines(
    env_id: str = "tensegrity_gym/ThreeBarRoll-v0", steps: int = 300, repeats: int = 5,
    seed: int = 0,
) -> dict[str, Any]:  # fmt: skip
    """ms per env step on each engine with the oracle and the UKF, ms per period of the
    bare engine step (at rest; MuJoCo's also through the oracle env's own periods,
    :func:`replayed_ms_per_period`, which its target's ratio is taken against), and the
    ratios of :data:`ENGINE_TARGETS` (speed-ups: > 1 is faster)."""
    envs = {(e, est): gym.make(env_id, engine=e, estimator=est)
            for e in _ENGINES for est in _ESTIMATORS}  # fmt: skip
    shape = envs[_ENGINES[0], "oracle"].action_space.shape or ()
    actions = np.random.default_rng(seed).uniform(-1.0, 1.0, (steps, *shape)).astype(np.float32)
    times: dict[str, list[float]] = {}
    try:
        for _ in range(repeats):
            for (engine, estimator), env in envs.items():
                key = f"{engine}_{estimator}_ms_per_step"
                times.setdefault(key, []).append(ms_per_step(env, actions, seed))
            for engine in _ENGINES:
                env = envs[engine, "oracle"]
                env.reset(seed=seed)
                key = f"{engine}_bare_ms_per_period"
                times.setdefault(key, []).append(_bare_ms_per_period(env, max(steps // 3, 20)))
            replayed = replayed_ms_per_period(envs["mujoco", "oracle"], actions, seed)
            times.setdefault("mujoco_replayed_ms_per_period", []).append(replayed)
    finally:
        for env in envs.values():
            env.close()
    least = {key: min(t) for key, t in times.items()}
    ratios = {
        "mujoco_oracle_over_bare_mj_step": least["mujoco_replayed_ms_per_period"]
        / least["mujoco_oracle_ms_per_step"],
        "mujoco_oracle_over_bare_mj_step_at_rest": least["mujoco_bare_ms_per_period"]
        / least["mujoco_oracle_ms_per_step"],
        "mujoco_over_pybullet_oracle": least["pybullet_oracle_ms_per_step"]
        / least["mujoco_oracle_ms_per_step"],
        "mujoco_over_pybullet_ukf": least["pybullet_ukf_ms_per_step"]
        / least["mujoco_ukf_ms_per_step"],
    }
    return {
        "env": env_id,
        "steps": steps,
        "repeats": repeats,
        **{key: round(value, 3) for key, value in least.items()},
        **{key: round(value, 3) for key, value in ratios.items()},
        "targets": ENGINE_TARGETS,
    }


def bench_vector(
    env_id: str = "tensegrity_gym/ThreeBarRoll-v0", num_envs: int = 16, steps: int = 60,
    engine: str = "mujoco", estimator: str = "ukf", seed: int = 0,
) -> dict[str, Any]:  # fmt: skip
    """Process-time ms per env step of the native vector env of ``num_envs`` robots
    against a single env's, on ``engine`` with ``estimator``; one process, so process
    time is time on one core. ``ratio`` > 1: the vector env steps a robot faster."""
    single = gym.make(env_id, engine=engine, estimator=estimator)
    shape = single.action_space.shape or ()
    actions = np.random.default_rng(seed).uniform(-1.0, 1.0, (steps, *shape)).astype(np.float32)
    single_ms = ms_per_step(single, actions, seed)
    single.close()
    vec = gym.make_vec(env_id, num_envs=num_envs, vectorization_mode="vector_entry_point",
                       engine=engine, estimator=estimator)  # fmt: skip
    batched = np.repeat(actions[:, None], num_envs, axis=1)
    vec.reset(seed=seed)
    for a in batched[:5]:
        vec.step(a)
    t = time.process_time()
    for a in batched[5:]:
        vec.step(a)
    vector_ms = 1e3 * (time.process_time() - t) / ((len(batched) - 5) * num_envs)
    vec.close()
    return {
        "env": env_id,
        "engine": engine,
        "estimator": estimator,
        "num_envs": num_envs,
        "single_ms_per_env_step": round(single_ms, 3),
        "vector_ms_per_env_step": round(vector_ms, 3),
        "vector_over_single_per_core": round(single_ms / vector_ms, 3),
    }
