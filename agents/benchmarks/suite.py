"""``tensegrity-gym bench``: every benchmark in one run, as one JSON document.

Every figure is measured in one run of one process, so ratios compare like with like
on a shared, noisy machine.
"""

from __future__ import annotations

import os
import platform
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from agents.benchmarks.env import bench_env_speed, bench_env_speed_ratio, bench_memory
from agents.training.cluster import executor
from tensegrity_gym.sim.engines import DEFAULT_ENGINE

if TYPE_CHECKING:
    from agents.training.cluster import Executor

__all__ = ["run_benchmarks"]


def _bench_proprioceptive(speed_steps: int) -> dict[str, Any]:
    """Tong et al. 2024 on the 1.45 m robot: table II (:mod:`agents.benchmarks.proprio`), the
    filter's and the shape solver's speed, and the env with it against the oracle."""
    from agents.benchmarks.inekf import bench_inekf
    from agents.benchmarks.proprio import bench_proprioceptive
    from agents.benchmarks.shape import bench_shape

    large = "tensegrity_gym/ThreeBarLargeRoll-v0"
    speed = bench_env_speed_ratio(large, "inekf", steps=max(speed_steps // 7, 100))
    return {
        "table": bench_proprioceptive(),
        "filter_us": bench_inekf(),
        "shape_us": bench_shape(),
        "speed": speed,
        "inekf_over_oracle_env_speed": speed["ratio"],
        "targets": {
            "propagate_us": 20,
            "correct_us (3 contacts)": 40,
            "shape solve_us": 2000,
            "inekf_over_oracle_env_speed": 0.8,
        },
    }


def _bench_estimators(speed_steps: int, jobs: Executor) -> dict[str, Any]:
    """The filters' speed, the estimation study (its jobs on ``jobs``), the ICP tracker,
    Tong et al. 2024's estimator and UWB calibration."""
    from agents.benchmarks.calibration import bench_calibration
    from agents.benchmarks.calibration_loop import bench_calibration_in_loop
    from agents.benchmarks.estimation import bench_estimation, bench_filter_speed
    from agents.benchmarks.icp import bench_icp

    return {
        "filter_speed": [
            bench_filter_speed("tensegrity_gym/ThreeBarRoll-v0"),
            bench_filter_speed("tensegrity_gym/SuperBallRoll-v0"),
        ],
        "filter_speed_targets": {
            "three_bar fast_filter_step_ms_median": 2.0,
            "superball fast_filter_step_ms_median": 5.0,
            "speedup_vs_filterpy_numpy_model": 50,
        },
        "estimation": bench_estimation(executor=jobs),
        "icp": bench_icp(),
        "proprioceptive": _bench_proprioceptive(speed_steps),
        "uwb_calibration": {
            "calibrator": bench_calibration(),
            "ukf_estimated_against_true": bench_calibration_in_loop(),
        },
    }


def _bench_link(link_steps: int, soak_minutes: float) -> dict[str, Any]:
    """The robot link against the emulator: latency and throughput over ``link_steps``
    periods, and a soak of ``soak_minutes``."""
    from agents.benchmarks.link import bench_latency, bench_soak, bench_throughput

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
    return link


def run_benchmarks(
    speed_steps: int = 2000,
    memory_steps: int = 100_000,
    estimation: bool = False,
    bag_minutes: float = 10.0,
    link_steps: int = 300,
    soak_minutes: float = 0.0,
    sim2real: bool = False,
    ray_address: str | None = None,
    engines: bool = False,
    engine: str | None = None,
    cross_world: bool | Mapping[str, tuple[str, ...]] = False,
    streams: bool = False,
    lab_calibration: bool = False,
    training: bool = False,
) -> dict[str, Any]:
    """Env speed (oracle and UKF), memory, the bag layer (:mod:`agents.benchmarks.bags`) and
    the robot link against the emulator (:mod:`agents.benchmarks.link`, ``link_steps`` 10 Hz
    steps, and a soak of ``soak_minutes``); with ``estimation``, also the estimation
    study and the UKF's speed against filterpy's (:mod:`agents.benchmarks.estimation`); with
    ``sim2real``, the UKF in randomised worlds and system identification
    (:mod:`agents.benchmarks.sim2real`); with ``ray_address``, the Ray vec env against
    ``SubprocVecEnv`` and the sizing model's costs (:mod:`agents.benchmarks.ray_cluster`), and the
    estimation study's replays as Ray tasks on that cluster; with ``engines``, the physics
    engines side by side (:mod:`agents.benchmarks.engines`); with ``cross_world``, every
    estimator on worlds it was not tuned in (:mod:`agents.benchmarks.cross_world`; a
    mapping gives :func:`~agents.benchmarks.cross_world.bench_cross_world` its
    ``worlds`` and ``estimators``); with
    ``streams``, the UKF and the invariant EKF on a lab's imperfect sensor streams
    (:mod:`agents.benchmarks.streams`); with
    ``lab_calibration``, the UWB calibration at a lab's conditions
    (:mod:`agents.benchmarks.lab_calibration`); with ``training``, where PPO's and SAC's
    training time goes with the UKF in the loop (:mod:`agents.benchmarks.training`).
    ``engine`` runs the env speed and memory
    figures on that physics engine (None: the default)."""
    with executor(ray_address) as jobs:
        results = _run(speed_steps, memory_steps, estimation, bag_minutes, link_steps,
                       soak_minutes, sim2real, jobs, engine)  # fmt: skip
        if engines:
            from agents.benchmarks.engines import bench_engines, bench_vector

            results["engines"] = bench_engines(steps=max(speed_steps // 5, 100))
            results["engines"]["vector"] = bench_vector(steps=max(speed_steps // 25, 30))
        if cross_world:
            from agents.benchmarks.cross_world import bench_cross_world

            chosen: dict[str, Any] = dict(cross_world) if isinstance(cross_world, Mapping) else {}
            results["cross_world"] = bench_cross_world(**chosen)
        if streams:
            from agents.benchmarks.streams import bench_streams

            results["streams"] = bench_streams()
        if lab_calibration:
            from agents.benchmarks.lab_calibration import bench_lab_calibration

            results["lab_calibration"] = bench_lab_calibration()
        if training:
            from agents.benchmarks.training import bench_training

            results["training"] = bench_training()
        if not jobs.local:
            from agents.benchmarks.ray_cluster import bench_ray

            results["ray"] = bench_ray(steps=max(speed_steps // 5, 100))
    return results


def _run(
    speed_steps: int,
    memory_steps: int,
    estimation: bool,
    bag_minutes: float,
    link_steps: int,
    soak_minutes: float,
    sim2real: bool,
    jobs: Executor,
    engine: str | None = None,
) -> dict[str, Any]:
    """:func:`run_benchmarks` but the Ray part; the estimation study's jobs on ``jobs``."""
    on = engine or DEFAULT_ENGINE
    results: dict[str, Any] = {
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
        },
        "speed": [
            bench_env_speed("tensegrity_gym/ThreeBarRoll-v0", speed_steps, engine=on),
            bench_env_speed(
                "tensegrity_gym/SuperBallRoll-v0", max(speed_steps // 2, 100), engine=on
            ),
            bench_env_speed("tensegrity_gym/ThreeBarRoll-v0", speed_steps, "ukf", engine=on),
            bench_env_speed(
                "tensegrity_gym/SuperBallRoll-v0", max(speed_steps // 2, 100), "ukf", engine=on
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
        results.update(_bench_estimators(speed_steps, jobs))
    if sim2real:
        from agents.benchmarks.sim2real import bench_identify, bench_randomized_ukf

        results["sim2real"] = {"randomized_ukf": bench_randomized_ukf(),
                               "identify": bench_identify()}  # fmt: skip
    if bag_minutes > 0:
        from agents.benchmarks.bags import bench_bags

        results["bags"] = bench_bags(minutes=bag_minutes)
    if link_steps > 0 or soak_minutes > 0:
        results["link"] = _bench_link(link_steps, soak_minutes)
    if memory_steps > 0:
        results["memory"] = bench_memory("tensegrity_gym/ThreeBarRoll-v0", memory_steps, engine=on)
    return results
