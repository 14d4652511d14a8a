"""UWB self-calibration in simulation (issue 15, papers/000 section III-C).

For each robot, a calibration run: the robot rolls under its scripted gait for two
minutes from one reset (driven by the truth, so that no estimator is involved), with
the description's packet loss; and beside it the run ``gym.make`` makes for
``calibration="estimated"`` in the same world (legs from resets spread over the
floor, :mod:`agents.calibration_run`); the calibrator gets the run's uncorrected ranges and the
robot description, no anchor position. Figures: the anchors' RMS error after the best
rigid motion onto the truth (proper: a mirror image does not align), the robot-anchor
and robot-robot offsets' RMS errors, the calibration's wall time, its verdict. And the
robustness rows: 10 % of the ranges replaced by multipath outliers (0.5 to 3 m too
long), and one anchor moved 30 cm between calibration and use (later ranges in the
same world checked against the calibration, each anchor moved in turn: is it flagged,
and only it?). A move across the anchor's line of sight to the robot barely changes
its ranges (nor what an estimator makes of them): such a move can go unflagged.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any, cast

import gymnasium as gym
import numpy as np

from estimation.uwb_calibration import (
    CalibrationResult,
    calibrate_samples,
    check_samples,
    rigid_alignment_rms,
)
from tensegrity_gym.model.description import load_robot
from tensegrity_gym.model.samples import UwbRangeSample
from tensegrity_gym.tasks.gaits import FaceGait

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from tensegrity_gym.envs.roll_env import TensegrityEnv
    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.protocols import StepResult
    from tensegrity_gym.sim.sensors import UwbModel

__all__ = ["ROBOTS", "TARGETS", "SimulatedRun", "bench_calibration", "calibration_run"]

ROBOTS = ("superball", "three_bar", "three_bar_large")
TARGETS = {
    "anchor_rms_m": 0.02,
    "robot_anchor_offset_rms_m": 0.015,
    "robot_robot_offset_rms_m": 0.015,
    "superball_seconds": 60.0,
}
"""Issue 15's figures to reach."""


@dataclass
class SimulatedRun:
    """A calibration run's UWB rounds and the truth they were made from."""

    description: RobotDescription
    samples: list[UwbRangeSample]
    anchors: NDArray[np.float64]
    """(A, 3) the simulator's anchors (m)."""
    offsets: NDArray[np.float64]
    """(n + A, n + A) the simulator's o_ij (m)."""
    packet_loss: float
    model: UwbModel
    """The run's sensor model, its world as drawn (to range again in that world)."""
    rounds: list[tuple[float, NDArray[np.float64]]]
    """(time s, node positions (n, 3)) of every UWB round: the truth it ranged."""
    sim_seconds: float
    """Wall time the simulation took."""


def _env_id(description: RobotDescription) -> str:
    return f"tensegrity_gym/{description.display_name}Roll-v0"


def calibration_run(robot: str, seconds: float = 120.0, seed: int = 0) -> SimulatedRun:
    """``seconds`` of the simulated ``robot`` rolling under its gait from one reset, in
    the world (anchors, offsets) ``seed`` draws and from a reset with ``seed``: every
    UWB round it ranged, and the truth."""
    d = load_robot(robot)
    steps = round(seconds / 0.1)
    env = gym.make(_env_id(d), estimator="oracle", calibration="true", world_seed=seed,
                   max_episode_steps=steps + 1)  # fmt: skip
    inner = cast("TensegrityEnv", env.unwrapped)
    backend: Any = inner.backend
    model: UwbModel = backend.uwb
    gait = FaceGait(d, inner.task)
    rounds: list[tuple[float, NDArray[np.float64]]] = []
    sample = model.sample

    def recording(snaps: Any, rng: np.random.Generator) -> list[UwbRangeSample]:
        rounds.extend((s.t, np.array(s.node_positions, dtype=np.float64)) for s in snaps)
        return sample(snaps, rng)

    model.sample = recording  # type: ignore[method-assign]
    samples: list[UwbRangeSample] = []
    clock = time.perf_counter()
    step = backend.step

    def tapped(targets: NDArray[np.float64]) -> StepResult:
        result: StepResult = step(targets)
        samples.extend(s for s in result.samples if isinstance(s, UwbRangeSample))
        return result

    reset = backend.reset

    def tapped_reset(*args: Any, **kwargs: Any) -> StepResult:
        result: StepResult = reset(*args, **kwargs)
        samples.extend(s for s in result.samples if isinstance(s, UwbRangeSample))
        return result

    backend.step, backend.reset = tapped, tapped_reset
    obs, _ = env.reset(seed=seed)
    for _ in range(steps):
        obs, _, terminated, truncated, _ = env.step(gait(obs))
        if terminated or truncated:
            break
    elapsed = time.perf_counter() - clock
    env.close()
    model.sample = sample  # type: ignore[method-assign]
    return SimulatedRun(d, samples, model.anchors.copy(), model.offsets.copy(),
                        float(model.reject_fraction), model, rounds, elapsed)  # fmt: skip


def _errors(result: CalibrationResult, run: SimulatedRun) -> dict[str, float]:
    n = run.description.n_nodes
    ra = result.offsets[n:, :n] - run.offsets[n:, :n]
    iu = np.triu_indices(n, 1)
    rr = result.offsets[:n, :n][iu] - run.offsets[:n, :n][iu]
    return {
        "anchor_rms_m": round(rigid_alignment_rms(result.anchors, run.anchors), 4),
        "robot_anchor_offset_rms_m": round(float(np.sqrt(np.mean(ra**2))), 4),
        "robot_robot_offset_rms_m": round(float(np.sqrt(np.mean(rr**2))), 4),
        "calibration_seconds": round(result.wall_time, 1),
        "predicted_anchor_sigma_m": round(float(np.sqrt(np.mean(result.anchor_sigma**2))), 4),
        "verdict": result.verdict,  # type: ignore[dict-item]
    }


def _with_outliers(
    samples: list[UwbRangeSample], share: float, rng: np.random.Generator
) -> list[UwbRangeSample]:
    """``samples`` with ``share`` of the ranges 0.5 to 3 m too long (multipath)."""
    out = []
    for s in samples:
        ranges = s.ranges.copy()
        hit = rng.random(len(ranges)) < share
        ranges[hit] += rng.uniform(0.5, 3.0, int(np.count_nonzero(hit)))
        out.append(UwbRangeSample(s.t, s.times, s.pairs, ranges))
    return out


def _moved_anchors(
    run: SimulatedRun, result: CalibrationResult, rng: np.random.Generator, n_samples: int
) -> dict[str, Any]:
    """The run's last minute ranged again in its world, as calibrated and then with
    each anchor in turn moved 30 cm (horizontally, a random way), checked against the
    calibration: how many moves are flagged (only the moved anchor), how many
    unmoved anchors are flagged with them, and whether the unmoved world fits."""
    model = run.model
    kept = model.anchors.copy()
    later = run.rounds[len(run.rounds) // 2 :]
    snaps = [SimpleNamespace(t=t, node_positions=nodes) for t, nodes in later]
    d = run.description
    same = check_samples(result, model.sample(snaps, rng), d, n_samples=n_samples)  # type: ignore[arg-type]
    detected, false_flags, shifts = 0, 0, []
    for anchor in range(len(kept)):
        heading = rng.uniform(0.0, 2.0 * np.pi)
        model.anchors = kept.copy()
        model.anchors[anchor] += 0.3 * np.array([np.cos(heading), np.sin(heading), 0.0])
        samples = model.sample(snaps, rng)  # type: ignore[arg-type]
        check = check_samples(result, samples, d, n_samples=n_samples)
        detected += anchor in check.flagged_anchors
        false_flags += len(set(check.flagged_anchors) - {anchor})
        shifts.append(round(abs(check.anchor_stats[anchor].median), 3))
    model.anchors = kept
    return {
        "anchors_moved": len(kept),
        "detected": detected,
        "other_anchors_flagged": false_flags,
        "unmoved_fits": same.verdict == "fits",
        "moved_residual_shift_m": shifts,
    }


def _env_run(robot: str, seconds: float, seed: int) -> dict[str, Any]:
    """The calibration run ``gym.make(..., calibration="estimated")`` makes in the
    world ``seed`` (:func:`agents.calibration_run.calibration_samples`: legs from
    resets spread over the floor), calibrated and scored against that world."""
    from agents.calibration_run import calibration_samples

    d = load_robot(robot)
    env = gym.make(_env_id(d), estimator="oracle", calibration="true", world_seed=seed)
    truth = cast("Any", env.unwrapped).backend.true_uwb
    env.close()
    clock = time.perf_counter()
    samples = calibration_samples(d, world_seed=seed, seconds=seconds)
    elapsed = time.perf_counter() - clock
    result = calibrate_samples(samples, d, rng=np.random.default_rng(seed))
    run = SimulatedRun(
        d, samples, truth.anchors, truth.uwb_offsets, float("nan"), cast("Any", None), [], elapsed
    )
    return {"simulation_seconds": round(elapsed, 1), **_errors(result, run)}


def _robot_rows(robot: str, seconds: float, seed: int, robustness: bool) -> dict[str, Any]:
    run = calibration_run(robot, seconds, seed)
    rng = np.random.default_rng(seed)
    result = calibrate_samples(run.samples, run.description, rng=np.random.default_rng(seed))
    row: dict[str, Any] = {
        "robot": robot,
        "seconds": seconds,
        "packet_loss": round(run.packet_loss, 3),
        "rounds": len(run.samples),
        "samples_used": result.n_samples,
        "simulation_seconds": round(run.sim_seconds, 1),
        **_errors(result, run),
    }
    row["env_calibration_run"] = _env_run(robot, seconds, seed)
    if robustness:
        spoiled = _with_outliers(run.samples, 0.1, rng)
        noisy = calibrate_samples(spoiled, run.description, rng=np.random.default_rng(seed))
        row["multipath_10_percent"] = _errors(noisy, run)
        row["moved_30_cm"] = _moved_anchors(run, result, rng, n_samples=100)
    return row


def bench_calibration(
    robots: tuple[str, ...] = ROBOTS, seconds: float = 120.0, seed: int = 0, robustness: bool = True
) -> dict[str, Any]:
    """The figures per robot (JSON-able), with the issue's targets beside them."""
    rows = [_robot_rows(robot, seconds, seed, robustness) for robot in robots]
    return {"runs": rows, "targets": TARGETS}
