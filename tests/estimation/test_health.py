"""The health component every estimator reports into (estimation/health.py)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from estimation.health import EstimatorHealth, HealthParams
from tensegrity_gym.model.estimate import Estimate

PERIOD_NS = 100_000_000  # 0.1 s


def _estimate() -> Estimate:
    zeros = np.zeros((2, 3))
    return Estimate(0.0, zeros, zeros, np.zeros(3), np.zeros(1))


class _Screen:
    def __init__(self) -> None:
        self.rejected = {"uwb_range_too_long": 3}
        self.failed = ("uwb",)
        self.mismatches = ("motor 0 (cable 'c0') reads 0.1-0.2 m, ...",)


def test_no_correction_for_longer_than_the_limit_is_unhealthy_to_the_nanosecond() -> None:
    health = EstimatorHealth(HealthParams(max_prediction_time=0.5))
    flags = []
    for _ in range(6):
        health.predicted(PERIOD_NS, corrected=False)
        flags.append(health.fill(_estimate()).healthy)
    assert flags == [True] * 5 + [False]  # 0.5 s exactly is still healthy
    health.predicted(0, corrected=False)  # an update spanning no time counts a period
    health.predicted(PERIOD_NS, corrected=True)
    assert health.fill(_estimate()).healthy


def test_every_update_must_correct_with_a_zero_limit() -> None:
    health = EstimatorHealth(HealthParams(max_prediction_time=0.0))
    health.predicted(0, corrected=False)  # not even a period known yet
    assert not health.fill(_estimate()).healthy
    health.predicted(0, corrected=True)
    assert health.fill(_estimate()).healthy


@pytest.mark.parametrize("healthy_when_reinitialised", [False, True])
def test_divergences_and_reinitialisations_are_counted_by_reason(
    healthy_when_reinitialised: bool,
) -> None:
    health = EstimatorHealth(HealthParams(healthy_when_reinitialised=healthy_when_reinitialised))
    health.diverged("rods stretched")
    assert health.pending == "rods stretched"
    health.reinitialised(placed=True)
    first = health.fill(_estimate())
    assert first.reinitialised and first.healthy == healthy_when_reinitialised
    health.diverged("rods stretched")
    health.request_reinitialisation("fitness")  # a lost track: no divergence
    assert health.divergences == {"rods stretched": 2}
    assert health.reinitialisations_by_reason == {"rods stretched": 2, "fitness": 1}
    assert health.reinitialisations == 3 and health.pending == "fitness"
    later = health.fill(_estimate())
    assert not later.reinitialised and later.healthy  # the flag is one update's


def test_a_failed_reinitialisation_does_not_count_as_a_correction() -> None:
    health = EstimatorHealth(HealthParams(max_prediction_time=0.15))
    health.predicted(PERIOD_NS, corrected=False)
    health.diverged("numerics failed")
    health.reinitialised(placed=False)
    assert not health.fill(_estimate()).healthy
    health.predicted(PERIOD_NS, corrected=False)
    assert not health.fill(_estimate()).healthy  # 0.2 s without a correction


def test_the_screen_counts_reach_the_estimate() -> None:
    with_screen = EstimatorHealth(HealthParams(), _Screen()).fill(_estimate())
    assert with_screen.rejected == {"uwb_range_too_long": 3}
    assert with_screen.failed_streams == ("uwb",)
    assert with_screen.description_mismatch == ("motor 0 (cable 'c0') reads 0.1-0.2 m, ...",)
    without = EstimatorHealth(HealthParams())
    assert without.fill(_estimate()).rejected is None
    assert without.summary() == {
        "divergences": {},
        "reinitialisations": {},
        "implausible": {},
        "failed_streams": [],
        "description_mismatch": [],
    }


def test_params_are_frozen_and_checked() -> None:
    with pytest.raises(dataclasses.FrozenInstanceError):
        HealthParams().max_prediction_time = 1.0  # type: ignore[misc]
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="max_prediction_time"):
            HealthParams(max_prediction_time=bad)


def test_a_reinitialisation_carries_its_reason_for_that_update_alone() -> None:
    health = EstimatorHealth(HealthParams())
    health.diverged("rods stretched")
    health.reinitialised(placed=True)
    first = health.fill(_estimate())
    assert first.reinitialised and first.reinitialised_because == "rods stretched"
    second = health.fill(_estimate())
    assert not second.reinitialised and second.reinitialised_because is None
