"""Error metrics: hand-checked cases, invariances, and agreement with evo."""

from __future__ import annotations

import numpy as np
import pytest
from evo.core import metrics as evo_metrics
from evo.core.trajectory import PoseTrajectory3D
from scipy.spatial.transform import Rotation

from estimation.metrics import (
    absolute_trajectory_error,
    body_poses,
    com_errors,
    relative_pose_error,
    rod_errors,
    shape_errors,
    trajectory_errors,
    umeyama_alignment,
)
from tensegrity_gym.model.description import load_robot

RODS = np.array([[0, 1], [2, 3], [4, 5]])


def _rolling_truth(rng: np.random.Generator, steps: int = 60) -> np.ndarray:
    """Node positions (T, 6, 3) of the 3-bar robot turning and moving along a curve."""
    d = load_robot("three_bar")
    shape = d.initial_positions - d.initial_positions.mean(axis=0)
    out = []
    for k in range(steps):
        R = Rotation.from_rotvec([0.3 * np.sin(0.1 * k), 0.05 * k, 0.02 * k])
        centre = np.array([0.02 * k, 0.1 * np.sin(0.05 * k), 0.1])
        out.append(R.apply(shape) + centre + 0.001 * rng.standard_normal((6, 3)))
    return np.array(out)


def test_rod_errors_by_hand() -> None:
    true = load_robot("three_bar").initial_positions
    est = true.copy()
    est[[0, 1]] += [0.03, 0.0, 0.0]  # rod 0 shifted 3 cm, not turned
    # Rod 1 turned by 10 degrees about its centre, about an axis normal to it.
    c = 0.5 * (true[2] + true[3])
    axis = np.cross(true[3] - true[2], [0.0, 0.0, 1.0])
    R = Rotation.from_rotvec(np.radians(10.0) * axis / np.linalg.norm(axis))
    est[[2, 3]] = R.apply(true[[2, 3]] - c) + c
    errors = rod_errors(est, true, RODS)
    np.testing.assert_allclose(errors.translation[0], [0.03, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(np.degrees(errors.rotation[0]), [0.0, 10.0, 0.0], atol=1e-9)
    assert errors.share_within() == pytest.approx(1 / 3)  # only rod 2 is within 2 cm, 5 deg
    # Turning a rod about its own axis is no error: the 5-DoF rotation ignores it.
    spin = Rotation.from_rotvec(0.7 * (true[1] - true[0]) / np.linalg.norm(true[1] - true[0]))
    est2 = true.copy()
    c0 = 0.5 * (true[0] + true[1])
    est2[[0, 1]] = spin.apply(true[[0, 1]] - c0) + c0
    assert np.max(rod_errors(est2, true, RODS).rotation) < 1e-7


def test_shape_error_ignores_the_frame_and_com_error_does_not() -> None:
    rng = np.random.default_rng(0)
    true = _rolling_truth(rng, 5)
    moved = Rotation.from_rotvec([0.3, -0.2, 1.0]).apply(true.reshape(-1, 3)).reshape(true.shape)
    moved += [1.0, 2.0, 0.0]
    np.testing.assert_allclose(shape_errors(moved, true), 0.0, atol=1e-12)
    masses = np.full(6, 0.08)
    com_true = body_poses(true, RODS, masses)[:, :3, 3]
    com_moved = body_poses(moved, RODS, masses)[:, :3, 3]
    assert np.all(com_errors(com_moved, com_true) > 1.0)
    stretched = true.copy()
    stretched[:, 0] += [0.0, 0.0, 0.01]  # one endcap up by 1 cm
    assert np.all(shape_errors(stretched, true) > 0.0)


def test_umeyama_recovers_a_rigid_motion_and_ate_is_zero_after_it() -> None:
    rng = np.random.default_rng(1)
    p = rng.standard_normal((50, 3))
    R = Rotation.from_rotvec([0.1, 0.4, -0.7]).as_matrix()
    q = p @ R.T + [3.0, -1.0, 0.5]
    R_est, t_est = umeyama_alignment(p, q)
    np.testing.assert_allclose(R_est, R, atol=1e-12)
    np.testing.assert_allclose(t_est, [3.0, -1.0, 0.5], atol=1e-12)
    np.testing.assert_allclose(absolute_trajectory_error(p, q), 0.0, atol=1e-12)
    assert np.all(absolute_trajectory_error(p, q, align=False) > 0.1)


def test_drift_percentage_by_hand() -> None:
    T = 11
    true = np.tile(np.eye(4), (T, 1, 1))
    true[:, 0, 3] = np.linspace(0.0, 10.0, T)  # 10 m straight
    est = true.copy()
    est[:, 1, 3] = np.linspace(0.0, 0.5, T)  # drifting sideways to 0.5 m
    errors = trajectory_errors(est, true)
    assert errors.path_length == pytest.approx(10.0)
    assert errors.final_drift == pytest.approx(0.5)
    assert errors.drift_percentage == pytest.approx(5.0)


def test_bad_input_is_named() -> None:
    with pytest.raises(ValueError, match="shape"):
        com_errors(np.zeros((3, 3)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match="non-finite"):
        com_errors(np.full((3, 3), np.nan), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="delta"):
        relative_pose_error(np.tile(np.eye(4), (3, 1, 1)), np.tile(np.eye(4), (3, 1, 1)), 5)


@pytest.mark.parametrize("delta", [1, 5])
def test_ate_and_rpe_agree_with_evo(delta: int) -> None:
    rng = np.random.default_rng(2)
    true_nodes = _rolling_truth(rng)
    est_nodes = true_nodes + 0.01 * rng.standard_normal(true_nodes.shape)
    est_nodes += np.linspace(0.0, 0.2, len(est_nodes))[:, None, None] * [1.0, 0.5, 0.0]
    masses = np.full(6, 0.08)
    est, true = body_poses(est_nodes, RODS, masses), body_poses(true_nodes, RODS, masses)
    ours = trajectory_errors(est, true, rpe_delta=delta)

    def traj(poses: np.ndarray) -> PoseTrajectory3D:
        return PoseTrajectory3D(poses_se3=list(poses), timestamps=np.arange(len(poses)) * 0.1)

    ref, est_traj = traj(true), traj(est)
    est_traj.align(ref, correct_scale=False)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((ref, est_traj))
    assert ours.ate_rmse == pytest.approx(
        ape.get_statistic(evo_metrics.StatisticsType.rmse), rel=1e-9
    )
    rpe = evo_metrics.RPE(
        evo_metrics.PoseRelation.translation_part,
        delta=delta,
        delta_unit=evo_metrics.Unit.frames,
        all_pairs=False,
    )
    rpe.process_data((traj(true), traj(est)))
    assert ours.rpe_rmse == pytest.approx(
        rpe.get_statistic(evo_metrics.StatisticsType.rmse), rel=1e-9
    )
    assert ours.ate_rmse > 0.005 and ours.rpe_rmse > 0.001  # the comparison is not vacuous
