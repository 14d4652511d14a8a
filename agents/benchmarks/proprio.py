"""Table II of Tong et al. 2024 in simulation: the proprioceptive estimator's drift on the
1.45 m robot's runs, beside the UKF with UWB and the UKF without UWB after the first
second, on the same runs.

Each run rolls ``ThreeBarLargeRoll-v0`` with a scripted gait driven by the true state
(the oracle), so that every estimator sees the same samples: the estimators under test
run beside it on the period's samples and are scored against the truth. Figures per
run, as Tong et al. 2024 computes them with evo: trajectory length (m, the path of the body
frame, the base rod's centre where the IMU sits, in 3-D, one pose a control step),
final drift (m, of the body frame's displacement from the start: the start is aligned
by position, as the paper aligns the initial segment, the initial position being
unobservable; the heading is not aligned), drift % of length, RPE RMSE per metre of
that path (translation m/m, rotation deg/m, of the base rod's pose over 1 m segments of
it, as evo's RPE with its delta in metres) and the shape RMSE (m, of the cable-connected endcap
distances). Beside them a stricter drift, of the CoM over its travel in the ground
plane (``com_ground_*``): a rocking gait's bobbing and the rod centre's swing about the
CoM lengthen the paper's path without moving the robot anywhere.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any, cast

import gymnasium as gym
import numpy as np

from estimation.inekf import InekfEstimator
from estimation.ukf import UkfEstimator
from tensegrity_gym.model.lie import so3_log
from tensegrity_gym.model.protocols import StepResult
from tensegrity_gym.model.samples import UwbRangeSample
from tensegrity_gym.tasks.gaits import FaceGait

if TYPE_CHECKING:
    from collections.abc import Sequence

    from numpy.typing import NDArray

    from tensegrity_gym.envs.tensegrity_env import TensegrityEnv
    from tensegrity_gym.model.estimate import Estimate
    from tensegrity_gym.model.protocols import Estimator
    from tensegrity_gym.model.samples import GroundTruth, Sample

__all__ = ["RUNS", "bench_proprioceptive", "drift_metrics"]

ENV_ID = "tensegrity_gym/ThreeBarLargeRoll-v0"
RUNS: dict[str, dict[str, Any]] = {
    "forward": {},
    "backward": {"gait": "backward"},
    "left turn": {"gait": "left", "steps_scale": 1.7},
    "right turn": {"gait": "right"},
    "valley": {"terrain": "valley"},
}
"""The runs by name: the robot's gait to run (``"gait"``, default forward), its control
steps over the bench's (``"steps_scale"``, default 1: the left turn rocks, about 1 cm a
period with thin rods, and needs 510 steps for Tong et al. 2024's 5 m) and the arguments of
``gym.make`` it adds (the rest)."""
UWB_LOST_AFTER = 1.0
"""s: the UKF without UWB has the ranges of the first second only (Tong et al. 2024's
comparison: what the robot's own sensors keep once it leaves the anchors)."""


def _rpe(
    true: list[tuple[NDArray[np.float64], NDArray[np.float64]]],
    est: list[tuple[NDArray[np.float64], NDArray[np.float64]]],
    distance: NDArray[np.float64],
    delta: float = 1.0,
) -> tuple[float, float]:
    """RMSE of the relative pose error over segments of ``delta`` m of travel:
    translation (m) and rotation (deg), each per metre."""
    trans, rot = [], []
    j = 0
    for i in range(len(true)):
        while j < len(true) and distance[j] - distance[i] < delta:
            j += 1
        if j == len(true):
            break
        (Ri, pi), (Rj, pj) = true[i], true[j]
        (Si, qi), (Sj, qj) = est[i], est[j]
        dR_true, dp_true = Ri.T @ Rj, Ri.T @ (pj - pi)
        dR_est, dp_est = Si.T @ Sj, Si.T @ (qj - qi)
        trans.append(float(np.linalg.norm(dp_est - dp_true)))
        rot.append(float(np.degrees(np.linalg.norm(so3_log(dR_true.T @ dR_est)))))
    if not trans:
        return float("nan"), float("nan")
    per = 1.0 / delta
    return (
        float(np.sqrt(np.mean(np.square(trans)))) * per,
        float(np.sqrt(np.mean(np.square(rot)))) * per,
    )


def drift_metrics(
    truths: list[GroundTruth], estimates: list[Estimate], cable_nodes: NDArray[np.intp]
) -> dict[str, float]:
    """The table's figures for one estimator's ``estimates`` against ``truths`` (one a
    step, from the reset on); the base rod's estimated pose is rod 0's nodes' frame."""
    t_com = np.array([t.com for t in truths])
    e_com = np.array([e.com for e in estimates])
    true_poses = [_node_pose(t.node_positions) for t in truths]
    est_poses = [_node_pose(e.node_positions) for e in estimates]
    t_body = np.array([p for _, p in true_poses])
    e_body = np.array([p for _, p in est_poses])
    body_path = _path(t_body)
    trans, rot = _rpe(true_poses, est_poses, body_path)
    t_nodes = np.array([t.node_positions for t in truths])
    e_nodes = np.array([e.node_positions for e in estimates])
    a, b = cable_nodes[:, 0], cable_nodes[:, 1]
    d_true = np.linalg.norm(t_nodes[:, a] - t_nodes[:, b], axis=-1)
    d_est = np.linalg.norm(e_nodes[:, a] - e_nodes[:, b], axis=-1)
    body_length = float(body_path[-1])
    body_drift = _final_drift(e_body, t_body)
    com_drift, com_length = _final_drift(e_com, t_com), float(_path(t_com[:, :2])[-1])
    return {
        "trajectory_length_m": round(body_length, 3),
        "final_drift_m": round(body_drift, 4),
        "drift_percent": _percent(body_drift, body_length),
        "com_ground_length_m": round(com_length, 3),
        "com_ground_drift_m": round(com_drift, 4),
        "com_ground_drift_percent": _percent(com_drift, com_length),
        "rpe_translation_m_per_m": round(trans, 4),
        "rpe_rotation_deg_per_m": round(rot, 3),
        "shape_rmse_m": round(float(np.sqrt(np.mean((d_est - d_true) ** 2))), 4),
    }


def _path(points: NDArray[np.float64]) -> NDArray[np.float64]:
    """m: the distance along ``points`` (T, d) from the first to each, (T,)."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])


def _final_drift(estimated: NDArray[np.float64], true: NDArray[np.float64]) -> float:
    """m: the last point's error, both paths (T, 3) moved to start at the origin."""
    return float(np.linalg.norm((estimated[-1] - estimated[0]) - (true[-1] - true[0])))


def _percent(drift: float, length: float) -> float:
    return round(100.0 * drift / max(length, 1e-9), 2)


def _node_pose(nodes: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A pose of rod 0 from its two nodes (n, 3): its centre and a frame with z along
    the rod, x from the world y axis (the turn about the axis, which nodes do not
    show, is left out, for the truth and every estimator alike)."""
    a, b = nodes[0], nodes[1]
    z = (b - a) / np.linalg.norm(b - a)
    x = np.cross([0.0, 1.0, 0.0], z)
    if np.linalg.norm(x) < 1e-6:
        x = np.cross([1.0, 0.0, 0.0], z)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z]), 0.5 * (a + b)


def _run(name: str, make_kwargs: dict[str, Any], steps: int, seed: int) -> dict[str, Any]:
    """One run of ``steps`` (scaled by the run's ``steps_scale``): the oracle's gait; the
    InEKF, the UKF and the UKF without UWB beside it on its samples."""
    kwargs = dict(make_kwargs)
    gait_name = kwargs.pop("gait", "forward")
    steps = round(steps * kwargs.pop("steps_scale", 1.0))
    env = gym.make(ENV_ID, estimator="oracle", max_episode_steps=steps, **kwargs)
    inner = cast("TensegrityEnv", env.unwrapped)
    backend, d = inner.backend, inner.backend.description
    gait = FaceGait(d, inner.task, gait=gait_name)
    estimators: dict[str, Estimator] = {
        "inekf": InekfEstimator(),
        "ukf": UkfEstimator(),
        "ukf_without_uwb": _WithoutUwb(UkfEstimator(), after=UWB_LOST_AFTER),
    }
    wrapped = _Tap(backend)
    inner.backend = wrapped
    obs, _ = env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    calibration, hold = backend.calibration, d.rest_lengths[d.actuated]
    out = {
        k: [e.reset(d, calibration, wrapped.last.samples, hold, rng)] for k, e in estimators.items()
    }
    truths = [backend.ground_truth()]
    seconds = dict.fromkeys(estimators, 0.0)
    for _ in range(steps):
        obs, _, terminated, truncated, _ = env.step(gait(obs))
        command = wrapped.last_command
        for k, e in estimators.items():
            t0 = time.perf_counter()
            out[k].append(e.update(wrapped.last.samples, command))
            seconds[k] += time.perf_counter() - t0
        truths.append(backend.ground_truth())
        if terminated or truncated:
            break
    inner.backend = backend
    env.close()
    row: dict[str, Any] = {"run": name, "steps": len(truths) - 1, "seed": seed}
    for k in estimators:
        row[k] = drift_metrics(truths, out[k], d.cable_nodes)  # type: ignore[arg-type]
        row[k]["ms_per_update"] = round(1e3 * seconds[k] / max(len(truths) - 1, 1), 2)
    return row


class _WithoutUwb:
    """An estimator whose UWB ranges stop ``after`` seconds: the robot rolls out of the
    anchors' reach, and what is left is its own sensors (the UKF's spring-mass model,
    the IMU and the cable lengths)."""

    def __init__(self, inner: Estimator, after: float) -> None:
        self._inner, self._after = inner, after

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)

    def update(self, samples: Sequence[Sample], command: NDArray[np.float64]) -> Estimate:
        kept = [s for s in samples if s.t <= self._after or not isinstance(s, UwbRangeSample)]
        return self._inner.update(kept, command)


class _Tap:
    """A backend that keeps the last period's samples and command for the estimators
    beside the env's."""

    def __init__(self, inner: Any) -> None:
        self._inner = inner
        self.last = StepResult(())
        self.last_command = np.zeros(0)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)

    def reset(self, rng: np.random.Generator, **kw: Any) -> StepResult:
        self.last = self._inner.reset(rng, **kw)
        return self.last

    def step(self, targets: NDArray[np.float64]) -> StepResult:
        self.last = self._inner.step(targets)
        self.last_command = np.asarray(
            targets if self.last.command is None else self.last.command, dtype=np.float64
        )
        return self.last


def bench_proprioceptive(
    steps: int = 300,
    seed: int = 0,
    runs: dict[str, dict[str, Any]] | None = None,
    seeds: Sequence[int] | None = None,
) -> dict[str, Any]:
    """The table over ``runs`` (default :data:`RUNS`) from ``reset(seed)``, or from each
    of ``seeds`` in turn (the rows of all, and the means over all); the InEKF's mean
    drift % (Tong et al. 2024's, and of the CoM over the ground), the UKF's without UWB, and on
    how many rows the InEKF drifts less."""
    chosen = [seed] if seeds is None else list(seeds)
    rows = [_run(name, kw, steps, s) for s in chosen for name, kw in (runs or RUNS).items()]

    def mean(key: str, figure: str = "drift_percent") -> float:
        return round(float(np.mean([r[key][figure] for r in rows])), 2)

    return {
        "env": ENV_ID,
        "seeds": chosen,
        "runs": rows,
        "inekf_mean_drift_percent": mean("inekf"),
        "ukf_without_uwb_mean_drift_percent": mean("ukf_without_uwb"),
        "inekf_mean_com_ground_drift_percent": mean("inekf", "com_ground_drift_percent"),
        "ukf_without_uwb_mean_com_ground_drift_percent": mean(
            "ukf_without_uwb", "com_ground_drift_percent"
        ),
        "runs_inekf_drifts_less_than_ukf_without_uwb": sum(
            r["inekf"]["drift_percent"] < r["ukf_without_uwb"]["drift_percent"] for r in rows
        ),
        "targets": {"inekf_mean_drift_percent": 4.2, "inekf_shape_rmse_m": 0.0463},
    }
