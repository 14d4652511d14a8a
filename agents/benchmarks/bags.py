"""Benchmark of the bag layer: recording overhead, bag size, and how much faster than real
time a bag reads and replays (issue target: a 10-minute 3-bar bag without images at
least 50 times faster than real time)."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any, cast

import gymnasium as gym
import numpy as np

import tensegrity_gym  # noqa: F401  (registers the envs)
from agents.recordings.offline import estimate_bag, make_policy
from hardware.bag.reader import BagReader
from hardware.bag.replay import ReplayBackend

__all__ = ["bench_bags"]


def _run(env_id: str, steps: int, record_dir: Path | None, seed: int = 0) -> float:
    """Seconds to run ``steps`` env steps of the scripted gait (oracle estimator)."""
    env = gym.make(env_id, estimator="oracle", max_episode_steps=steps, record_dir=record_dir)
    policy, reset = make_policy("scripted", env, seed)
    obs, _ = env.reset(seed=seed)
    reset()
    start = time.perf_counter()
    for _ in range(steps):
        obs, _, terminated, truncated, _ = env.step(policy(obs))
        if terminated or truncated:
            break
    env.close()  # closing the bag is part of recording
    return time.perf_counter() - start


def bench_bags(
    env_id: str = "tensegrity_gym/ThreeBarRoll-v0",
    minutes: float = 10.0,
    overhead_steps: int = 1000,
) -> dict[str, Any]:
    """Record ``minutes`` of the scripted gait without images, then time reading it."""
    steps = round(minutes * 60.0 / 0.1)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        # Recording overhead, side by side on the same steps.
        plain = _run(env_id, overhead_steps, None)
        recorded = _run(env_id, overhead_steps, folder / "overhead")
        record_s = _run(env_id, steps, folder / "long")
        bag = folder / "long" / "episode_000"
        size_mb = sum(f.stat().st_size for f in bag.iterdir()) / 1e6

        with BagReader(bag) as reader:
            start = time.perf_counter()
            samples = 0
            duration = 0.0
            for period in reader.periods():
                samples += len(period.samples)
                duration = period.t_end
            read_s = time.perf_counter() - start
            messages = reader.message_count

        backend = ReplayBackend(bag)
        start = time.perf_counter()
        result = backend.reset(np.random.default_rng(0))
        while not result.ended:
            result = backend.step(cast("np.ndarray", backend.next_command))
        replay_s = time.perf_counter() - start
        backend.close()

        estimate = estimate_bag(bag, "ukf", folder / "estimate", progress=False)[0]
    return {
        "env": env_id,
        "recorded_minutes": round(duration / 60.0, 2),
        "messages": messages,
        "samples": samples,
        "bag_mb": round(size_mb, 1),
        "bag_mb_per_minute": round(size_mb / (duration / 60.0), 2),
        "record_env_steps_per_s": round(steps / record_s, 1),
        "recording_overhead_ms_per_step": round(1e3 * (recorded - plain) / overhead_steps, 3),
        "env_steps_per_s_without_recording": round(overhead_steps / plain, 1),
        "env_steps_per_s_with_recording": round(overhead_steps / recorded, 1),
        "read_s": round(read_s, 2),
        "read_realtime_factor": round(duration / read_s, 1),
        "replay_backend_s": round(replay_s, 2),
        "replay_realtime_factor": round(duration / replay_s, 1),
        "ukf_offline_realtime_factor": estimate["realtime_factor"],
        "read_share_of_offline_ukf": round(replay_s / estimate["wall_s"], 3),
        "target_replay_realtime_factor": 50,
    }
