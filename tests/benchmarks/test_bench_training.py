"""bench --training: where a training run's time goes."""

from __future__ import annotations

import pytest

from agents.benchmarks.training import PARTS, bench_training


@pytest.mark.parametrize("algo", ["ppo", pytest.param("sac", marks=pytest.mark.slow)])
def test_the_training_bench_splits_the_run_into_its_parts(algo: str) -> None:
    """Each part timed inside the run takes some of it, and the shares with the rest
    add up to the whole; a SAC run past its learning start updates its policy."""
    result = bench_training(algos=(algo,), steps=300, estimator="oracle")
    row = result["rows"][algo]
    shares = row["shares"]
    assert set(shares) == {*PARTS, "rest"}
    assert all(shares[p] > 0.0 for p in PARTS), shares
    assert abs(sum(shares.values()) - 1.0) < 0.01 and shares["rest"] > -0.01
    assert row["env_steps_per_s"] > 0.0 and row["wall_s"] > 0.0
    assert row["over_target"] == pytest.approx(row["env_steps_per_s"] / 1000.0, abs=1e-3)
