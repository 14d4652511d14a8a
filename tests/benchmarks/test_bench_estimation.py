"""The estimation benchmark's parts on short runs: they measure, and what they measure holds."""

from __future__ import annotations

import numpy as np
import pytest

from agents.benchmarks.estimation import (
    VARIANTS,
    bench_filter_speed,
    propagate_numpy,
    record_face_transition,
    record_stationary_actuation,
)
from agents.recordings.runs import replay, trajectory_errors
from estimation.ukf import SpringMassModel, UkfEstimator
from tensegrity_gym.model.description import load_robot
from tests.reference_spring_mass import awkward_states, propagate_reference


def test_filter_speed_compares_like_with_like() -> None:
    out = bench_filter_speed("tensegrity_gym/ThreeBarRoll-v0", steps=3, numpy_steps=1)
    # 36 node states, the AHRS frame's alignment (3), the 6 actuated cables' and the 3
    # rods' length errors: 2 x 48 + 1 sigma points.
    assert out["steps_timed"] == 3 and out["state_dim"] == 48 and out["sigma_points"] == 97
    # Both filters ran the same steps from the same start: the same answer.
    assert out["max_state_difference_vs_filterpy_m"] < 1e-6
    assert out["fast_filter_step_ms_median"] > 0
    assert out["speedup_vs_filterpy_numpy_model"] > out["speedup_vs_filterpy_compiled_model"] > 1


@pytest.mark.parametrize("robot", ["three_bar", "superball"])
def test_numpy_model_of_the_benchmark_matches_the_reference(robot: str) -> None:
    """The "plain numpy" model filterpy is timed with computes what the filter's does."""
    d = load_robot(robot)
    model = SpringMassModel(d)
    states = awkward_states(d, np.random.default_rng(3))
    rest = d.rest_lengths[d.actuated]
    out = model.propagate(states, 0.05, rest, 0.95 * rest, kernel=propagate_numpy)
    for state, got in zip(states, out, strict=True):
        ref = propagate_reference(model, state, 0.05, rest, 0.95 * rest)
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9)
    single = model.propagate(states[2], 0.05, rest, kernel=propagate_numpy)
    np.testing.assert_allclose(single, model.propagate(states[2], 0.05, rest), rtol=0, atol=1e-9)


def test_recorded_runs_replay_through_every_variant() -> None:
    # The filter's own figures: the simulator's calibration (with the self-calibrated one
    # of world 0 the variant without IMU re-initialises once in these 3 s: 6.5 cm).
    run = record_face_transition(
        "tensegrity_gym/ThreeBarRoll-v0", seed=0, steps=30, calibration="true"
    )
    assert len(run.steps) == 30 and run.steps[-1].truth is not None
    for config in VARIANTS.values():
        errors = trajectory_errors(run, replay(run, UkfEstimator(config)))
        assert errors["finite"] and errors["steps_scored"] >= 10  # after 2 s of 3
        assert errors["com_rmse_m"] < 0.05
        assert 0.0 <= errors["rods_within_2cm_5deg"] <= 1.0


@pytest.mark.slow  # SUPERball's env made, calibrated and stepped: over a minute on CI
def test_stationary_actuation_moves_two_cables_and_not_the_robot() -> None:
    run = record_stationary_actuation("tensegrity_gym/SuperBallRoll-v0", seed=0, steps=40)
    commands = np.array([s.command for s in run.steps])
    moving = np.flatnonzero(np.ptp(commands, axis=0) > 1e-9)
    assert moving.tolist() == [0, 1]
    start, end = run.start.truth, run.steps[-1].truth
    assert start is not None and end is not None
    assert np.linalg.norm(end.com[:2] - start.com[:2]) < 0.2  # metres: it stays put


@pytest.mark.slow  # four envs made, each calibrated and started: over a minute here
def test_the_speed_ratio_alternates_and_takes_the_least_of_each() -> None:
    from agents.benchmarks.env import bench_env_speed_ratio

    r = bench_env_speed_ratio("tensegrity_gym/ThreeBarRoll-v0", "inekf", steps=30, repeats=2)
    assert r["repeats"] == 2 and r["steps"] == 30
    for name in ("oracle", "inekf"):
        assert 0.0 < r[f"{name}_ms_per_step"] <= r[f"{name}_ms_per_step_median"]
    assert r["ratio"] == pytest.approx(r["oracle_ms_per_step"] / r["inekf_ms_per_step"], abs=2e-3)
