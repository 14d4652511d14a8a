"""The README's main job: train a rolling policy with the UKF in the loop, train one on
ground truth beside it, evaluate both (and a random policy) under the oracle and the
UKF, and write the report. Sized to finish in under 15 minutes on two cores."""

from __future__ import annotations

import json
import logging
import time
from typing import TYPE_CHECKING, Any

from agents.report import write_report
from agents.train import train

if TYPE_CHECKING:
    from pathlib import Path

__all__ = ["run_main_job"]

log = logging.getLogger(__name__)

ENV_ID = "tensegrity_gym/ThreeBarRoll-v0"


def run_main_job(
    out: Path,
    *,
    ukf_timesteps: int = 120_000,
    oracle_timesteps: int = 80_000,
    episodes: int = 5,
    seed: int = 0,
    progress_bar: bool = True,
) -> dict[str, Any]:
    """Train (UKF, then oracle; ``oracle_timesteps=0`` skips it), evaluate, report.
    Returns the report, with the wall time of each stage under ``"timing_s"``."""
    timing: dict[str, float] = {}
    runs = []
    for estimator, steps in (("ukf", ukf_timesteps), ("oracle", oracle_timesteps)):
        if steps <= 0:
            continue
        start = time.perf_counter()
        log.info("training PPO on %s states for %d steps", estimator, steps)
        train(
            ENV_ID,
            "ppo",
            estimator,
            out / f"ppo_{estimator}",
            timesteps=steps,
            seed=seed,
            progress_bar=progress_bar,
        )
        timing[f"train_{estimator}"] = round(time.perf_counter() - start, 1)
        runs.append(out / f"ppo_{estimator}")
    start = time.perf_counter()
    report = write_report(runs, out / "report", episodes=episodes, conditions=("oracle", "ukf"))
    timing["evaluate_and_report"] = round(time.perf_counter() - start, 1)
    report["timing_s"] = timing
    (out / "report" / "report.json").write_text(json.dumps(report, indent=2) + "\n")
    return report
