"""The cross-world benchmark (issue 42): every estimator scored on worlds it was not
tuned in, from runs recorded once per world."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from agents.benchmarks.cross_world import WORLDS, bench_cross_world, nees_per_dof
from agents.benchmarks.estimation import record_face_transition
from agents.recordings.runs import replay
from estimation.ukf import UkfEstimator

pytest.importorskip("mujoco")


def test_every_world_differs_and_each_row_has_its_figures() -> None:
    """One seed, 40 steps, the UKF: a row per world with every figure finite (NEES
    too: the UKF has a covariance); the description-error world is another robot (its
    CoM path differs from the own world's), and the targets are checked off ``own``."""
    result = bench_cross_world(("ukf", "ukf_exact_lengths"), seeds=(0,), steps=40)
    exact = result["rows"]["ukf_exact_lengths"]  # the variant, on the same runs
    assert set(exact) == set(WORLDS) and np.isfinite(exact["own"]["mean"]["nees_per_dof"])
    rows = result["rows"]["ukf"]
    assert set(rows) == set(WORLDS)
    for world, row in rows.items():
        assert row["runs"] == 2 and set(row["by_motion"]) == {"rolling", "turning"}, world
        assert all(np.isfinite(v) for v in row["mean"].values()), (world, row["mean"])
        assert row["mean"]["com_rmse_m"] < 0.05, (world, row["mean"])
    assert set(result["targets"]["ukf"]) == set(WORLDS) - {"own"}
    check = result["targets"]["ukf"]["other_engine"]["com_rmse_m"]
    assert check["met"] == (check["value"] <= check["target"])


def test_the_command_line_chooses_worlds_and_estimators() -> None:
    """``bench --cross-world [WORLD ...] [--cross-world-estimators E ...]``: every world
    with no name, else the own world and those named; unknown names refused."""
    from agents.cli import build_parser
    from agents.cli.bench import _cross_world

    parser = build_parser()
    assert _cross_world(parser.parse_args(["bench"])) is False
    assert _cross_world(parser.parse_args(["bench", "--cross-world"])) == {"worlds": tuple(WORLDS)}
    chosen = _cross_world(parser.parse_args(
        ["bench", "--cross-world", "stiff_contacts", "--cross-world-estimators", "inekf", "icp"]
    ))  # fmt: skip
    assert chosen == {"worlds": ("own", "stiff_contacts"), "estimators": ("inekf", "icp")}
    with pytest.raises(ValueError, match=r"--cross-world-estimators: unknown 'ekf'; choose from"):
        _cross_world(parser.parse_args(
            ["bench", "--cross-world", "--cross-world-estimators", "ekf"]
        ))  # fmt: skip
    with pytest.raises(ValueError, match="needs --cross-world"):
        _cross_world(parser.parse_args(["bench", "--cross-world-estimators", "inekf"]))


def test_nees_is_nan_without_a_covariance_and_near_one_for_the_ukf_at_home() -> None:
    run = record_face_transition("tensegrity_gym/ThreeBarRoll-v0", 0, 30, calibration="true")
    estimates = replay(run, UkfEstimator())
    assert 0.3 < nees_per_dof(run, estimates) < 2.0
    assert np.isnan(nees_per_dof(run, [replace(e, covariance=None) for e in estimates]))


@pytest.mark.slow  # 7 s; the default run is near its 15 minutes
def test_the_invariant_ekf_s_floor_corrections_are_counted_per_run() -> None:
    """The InEKF's row counts the contact heights it used (one a touch-down, so that a
    flickering contact sensor shows); an estimator without them has no such figure."""
    from agents.benchmarks.cross_world import ESTIMATOR_ROBOTS, score_run

    env_id, gait = ESTIMATOR_ROBOTS["inekf"]["rolling"]
    run = record_face_transition(env_id, 0, 20, gait=gait, calibration="true")
    inekf = score_run(run, "inekf", 0)
    seconds = 20 * run.control_period
    assert 1 <= inekf["floor_corrections"] <= 6 * seconds * run.description.n_nodes / 2
    assert "floor_corrections" not in score_run(run, "ukf_large", 0)
