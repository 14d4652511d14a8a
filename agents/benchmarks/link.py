"""Benchmarks of the robot link, with the emulator in another process on loopback.

- latency: what the driver adds to a 10 Hz control step beyond the period itself (from
  the period's deadline to ``step`` returning: draining, decoding, pairing, sorting),
  and how old the newest sample is when the step hands it over;
- throughput: SUPERball with its IMUs at 400 Hz (six rods: the message rate of 12 IMUs
  at 200 Hz) and ranging at 15 Hz; whether the driver's side drops anything, and
  whether every IMU sample of every rod arrives;
- soak: minutes of operation with the UKF in the loop and episodes resetting, with the
  memory of both processes and the step latency minute by minute.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any, cast

import gymnasium as gym
import numpy as np

from agents.benchmarks.env import rss_mb
from hardware.link import ZenohDriver
from hardware.link.process import EmulatorProcess
from tensegrity_gym.model.description import load_robot
from tensegrity_gym.model.samples import ImuSample

if TYPE_CHECKING:
    from tensegrity_gym.envs.tensegrity_env import TensegrityEnv

__all__ = ["bench_latency", "bench_soak", "bench_throughput"]


def _ms(values: list[float]) -> dict[str, float]:
    a = 1e3 * np.asarray(values)
    return {
        "median": round(float(np.median(a)), 3),
        "p99": round(float(np.percentile(a, 99)), 3),
        "max": round(float(a.max()), 3),
    }


def _timed_steps(driver: ZenohDriver, steps: int, rng: np.random.Generator) -> dict[str, Any]:
    """Random commands for ``steps`` periods; per step, the time past the deadline and
    the age of the newest sample at return."""
    lo, hi, _ = driver.description.motor_limits
    added, ages, imu = [], [], []
    for _ in range(steps):
        result = driver.step(rng.uniform(lo, hi))
        added.append(result.info["link_latency_s"])
        if result.info["link_newest_age_s"] is not None:
            ages.append(result.info["link_newest_age_s"])
        imu += [s for s in result.samples if isinstance(s, ImuSample)]
    return {"added": added, "ages": ages, "imu": imu}


def bench_latency(steps: int = 300, seed: int = 0) -> dict[str, Any]:
    """The driver's added latency per 10 Hz step with the 3-bar emulator."""
    t = time.monotonic()
    with EmulatorProcess("three_bar") as emulator:
        started = time.monotonic() - t
        driver = ZenohDriver(load_robot("three_bar"), emulator.address)
        try:
            driver.reset(np.random.default_rng(seed))
            out = _timed_steps(driver, steps, np.random.default_rng(seed))
            counts = driver.link_counts()
        finally:
            driver.close()
    return {
        "robot": "three_bar",
        "emulator_start_s": round(started, 2),
        "control_hz": 10,
        "steps": steps,
        "driver_added_latency_ms": _ms(out["added"]),
        "newest_sample_age_ms": _ms(out["ages"]),
        "skipped_or_dropped": counts,
        "target_ms": 5.0,
    }


def bench_throughput(steps: int = 200, imu_rate: float = 400.0, seed: int = 0) -> dict[str, Any]:
    """SUPERball at full sensor rates: messages per second, and losses on either side."""
    description = load_robot("superball")
    options = ["--imu-rate", str(imu_rate), "--no-truth"]
    with EmulatorProcess("superball", options=options) as emulator:
        driver = ZenohDriver(description, emulator.address)
        try:
            driver.reset(np.random.default_rng(seed))
            received_before = driver.received
            t = time.monotonic()
            out = _timed_steps(driver, steps, np.random.default_rng(seed))
            elapsed = time.monotonic() - t
            received = driver.received - received_before
            counts = driver.link_counts()
        finally:
            driver.close()
    missing, delivered = 0, 0
    for rod in range(description.n_rods):
        stamps = np.array([s.t for s in out["imu"] if s.rod == rod])
        delivered += stamps.size
        gaps = np.round(np.diff(stamps) * imu_rate).astype(int)
        missing += int(np.clip(gaps - 1, 0, None).sum())
    ranging = description.sensors.uwb.rate
    return {
        "robot": "superball",
        "imus": description.n_rods,
        "imu_rate_hz": imu_rate,
        "equivalent": f"{int(description.n_rods * imu_rate / 200)} IMUs at 200 Hz",
        "uwb_rate_hz": ranging,
        "seconds": round(elapsed, 2),
        "messages_per_s": round(received / elapsed, 1),
        "imu_samples_delivered": delivered,
        "imu_samples_missing": missing,
        "dropped_on_driver_side": driver.dropped,
        "skipped_or_dropped": counts,
        "driver_added_latency_ms": _ms(out["added"]),
    }


def bench_soak(minutes: float = 30.0, seed: int = 0) -> dict[str, Any]:
    """The 3-bar emulator driven through the env (UKF, random actions, episodes of
    300 steps) for ``minutes``; memory and latency minute by minute."""
    rows: list[dict[str, Any]] = []
    with EmulatorProcess("three_bar") as emulator:
        env = gym.make(
            "tensegrity_gym_hardware/ThreeBarRoll-v0", driver=emulator.address, estimator="ukf"
        )
        driver = cast("ZenohDriver", cast("TensegrityEnv", env.unwrapped).backend)
        assert emulator.process is not None
        rng = np.random.default_rng(seed)
        env.reset(seed=seed)
        end = time.monotonic() + 60.0 * minutes
        episodes, stalls = 1, 0
        while time.monotonic() < end:
            minute_end = min(time.monotonic() + 60.0, end)
            added = []
            while time.monotonic() < minute_end:
                _, _, terminated, truncated, info = env.step(env.action_space.sample())
                added.append(info["link_latency_s"])
                stalls += bool(info["link_stalled"])
                if terminated or truncated:
                    env.reset(seed=int(rng.integers(1 << 31)))
                    episodes += 1
            rows.append(
                {
                    "minute": len(rows) + 1,
                    "env_rss_mb": round(rss_mb(), 1),
                    "emulator_rss_mb": round(rss_mb(emulator.process.pid), 1),
                    "driver_added_latency_ms": _ms(added),
                }
            )
        counts = driver.link_counts()
        env.close()
    first, last = rows[min(1, len(rows) - 1)], rows[-1]  # the first minute warms up
    return {
        "minutes": minutes,
        "episodes": episodes,
        "stalled_steps": stalls,
        "per_minute": rows,
        "env_rss_growth_mb": round(last["env_rss_mb"] - first["env_rss_mb"], 1),
        "emulator_rss_growth_mb": round(last["emulator_rss_mb"] - first["emulator_rss_mb"], 1),
        "p99_latency_change_ms": round(
            last["driver_added_latency_ms"]["p99"] - first["driver_added_latency_ms"]["p99"], 3
        ),
        "skipped_or_dropped": counts,
    }
