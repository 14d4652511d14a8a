"""The main job (the demo, docs/results/demo.md): train a rolling policy with the UKF in
the loop (correcting the robot's steering gait), train one on ground truth beside it,
evaluate both (and a random policy and the scripted gaits) under the oracle, the UKF and
the invariant EKF, and write the report. Sized to finish in
under 15 minutes on two cores (40,960 + 20,480 training steps)."""

from __future__ import annotations

import json
import logging
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from agents.evaluation.report import check_sentence, write_report
from agents.training.train import CONFIG_DIR, train
from tensegrity_gym.model.description import STEER_GAIT

if TYPE_CHECKING:
    from collections.abc import Sequence
    from pathlib import Path

__all__ = ["across_seeds", "demo_settings", "run_main_job", "run_main_job_seeds"]

log = logging.getLogger(__name__)

ENV_ID = "tensegrity_gym/ThreeBarRoll-v0"
DEMO_CONDITIONS = ("oracle", "ukf", "inekf")
"""The demo evaluates every policy on ground truth, the UKF's estimates (UWB, IMU,
cable lengths) and the proprioceptive invariant EKF's (no UWB)."""
RESIDUAL_GAIT = 0.5
"""The demo's policies correct the scripted gait at this scale; docs/results/training.md has
it against absolute actions and against 2.0 (where a correction can reach every
command), over seeds."""
BASE_GAIT = STEER_GAIT
"""The gait the demo's policies correct: the steering gait, which rolls toward the goal
(the forward gait rolls its own way, and a policy on it learned to aim only a little:
docs/results/demo.md)."""
CONFIG_BY_GAIT = {STEER_GAIT: CONFIG_DIR / "steer.yml"}
"""The hyperparameters for residual actions on a gait (others: ``agents/training/configs/ppo.yml``):
the steering gait's flips are marginal, and exploration on it starts small."""


def run_main_job(
    out: Path,
    *,
    ukf_timesteps: int = 40_960,
    oracle_timesteps: int = 20_480,
    episodes: int = 5,
    seed: int = 0,
    progress_bar: bool = True,
    residual_gait: float | None = RESIDUAL_GAIT,
    base_gait: str = BASE_GAIT,
) -> dict[str, Any]:
    """Train (UKF, then oracle; ``oracle_timesteps=0`` skips it), evaluate, report.
    Both policies act by correcting the robot's gait ``base_gait`` (``gym.make``'s
    ``residual_gait`` and ``base_gait``; ``residual_gait`` None: absolute rest-length
    targets). Returns the report, with the wall time of each stage under
    ``"timing_s"``."""
    env_kwargs = None
    if residual_gait is not None:
        env_kwargs = {"residual_gait": residual_gait, "base_gait": base_gait}
    config = CONFIG_BY_GAIT.get(base_gait) if env_kwargs else None
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
            env_kwargs=env_kwargs,
            config_file=config,
        )
        timing[f"train_{estimator}"] = round(time.perf_counter() - start, 1)
        runs.append(out / f"ppo_{estimator}")
    start = time.perf_counter()
    report = write_report(runs, out / "report", episodes=episodes, conditions=DEMO_CONDITIONS)
    timing["evaluate_and_report"] = round(time.perf_counter() - start, 1)
    report["timing_s"] = timing
    settings = demo_settings(ukf_timesteps, oracle_timesteps, episodes, residual_gait, base_gait)
    lines = against_reference(report, settings, load_reference())
    report["settings"] = settings
    report["against_seeds"] = lines
    with (out / "report" / "report.md").open("a") as md:
        md.write("\n## Against the multi-seed run\n\n" + "\n".join(lines) + "\n")
    (out / "report" / "report.json").write_text(json.dumps(report, indent=2) + "\n")
    return report


def demo_settings(
    ukf_timesteps: int,
    oracle_timesteps: int,
    episodes: int,
    residual_gait: float | None,
    base_gait: str,
) -> dict[str, Any]:
    """What a demo ran with (:func:`run_main_job`'s arguments that change its figures),
    as its report and the stored multi-seed run keep it."""
    return {
        "ukf_timesteps": ukf_timesteps,
        "oracle_timesteps": oracle_timesteps,
        "episodes": episodes,
        "residual_gait": residual_gait,
        "base_gait": base_gait if residual_gait is not None else None,
    }


REFERENCE = CONFIG_DIR / "demo_seeds.json"
"""The multi-seed run docs/results/demo.md quotes (``demo --seeds 0 1 2``'s ``seeds.json`` with the
settings it ran with): what a one-seed demo states its result against."""


def load_reference(path: Path = REFERENCE) -> dict[str, Any] | None:
    """The stored multi-seed figures, None where there are none."""
    return json.loads(path.read_text()) if path.exists() else None


def against_reference(
    report: dict[str, Any], settings: dict[str, Any], reference: dict[str, Any] | None
) -> list[str]:
    """Markdown lines setting each trained policy's progress and rolls under the UKF
    beside the multi-seed run's mean ± std [least, greatest], where it ran with these
    ``settings``."""
    if reference is None:
        return ["No multi-seed run is stored (`agents/training/configs/demo_seeds.json`)."]
    if reference.get("settings") != settings:
        return [
            f"The multi-seed run used other settings ({reference.get('settings')}), "
            f"so this run ({settings}) is not compared with it."
        ]
    command = reference.get("command", "tensegrity-gym demo --seeds ...")
    lines = [f"The multi-seed run (seeds {reference['seeds']}, `{command}`):", ""]
    for policy, by_condition in reference["results"].items():
        mine = report["results"].get(policy, {}).get("ukf")
        ref = by_condition.get("ukf")
        if mine is None or ref is None or not policy.startswith("trained"):
            continue
        parts = []
        for key, label in (("progress_mean_m", "progress (m)"), ("rolls_per_episode", "rolls")):
            f, x = ref[key], mine[key]
            within = "within" if f["min"] <= x <= f["max"] else "outside"
            parts.append(
                f"{label} {x:.2f} against {f['mean']:.2f} ± {f['std']:.2f} "
                f"[{f['min']:.2f}, {f['max']:.2f}] ({within} the seeds' range)"
            )
        lines.append(f"- **{policy}** under `ukf`: " + "; ".join(parts) + ".")
    return lines


SEED_FIGURES = (
    "progress_mean_m",
    "distance_mean_m",
    "rolls_per_episode",
    "success_rate",
    "com_error_mean_m",
)
"""The per-policy, per-condition figures :func:`across_seeds` gathers."""


def across_seeds(reports: dict[int, dict[str, Any]]) -> dict[str, Any]:
    """The figures of several seeds' reports (seed -> :func:`run_main_job`'s report):
    per policy and condition, each of :data:`SEED_FIGURES` as its mean, standard
    deviation, least and greatest over the seeds, and the seeds' own values."""
    seeds = sorted(reports)
    first = reports[seeds[0]]["results"]
    table: dict[str, Any] = {}
    for policy, by_condition in first.items():
        table[policy] = {}
        for cond in by_condition:
            table[policy][cond] = {}
            for key in SEED_FIGURES:
                values = np.array([reports[s]["results"][policy][cond][key] for s in seeds])
                table[policy][cond][key] = {
                    "mean": round(float(values.mean()), 4),
                    "std": round(float(values.std()), 4),
                    "min": round(float(values.min()), 4),
                    "max": round(float(values.max()), 4),
                    "per_seed": values.round(4).tolist(),
                }
    return {"seeds": seeds, "results": table}


def run_main_job_seeds(out: Path, seeds: Sequence[int], **kwargs: Any) -> dict[str, Any]:
    """:func:`run_main_job` once per seed (into ``out/seed_<s>``), then the figures
    across them (:func:`across_seeds`), written to ``out/seeds.json`` and ``out/seeds.md``."""
    if len(set(seeds)) != len(seeds) or not seeds:
        raise ValueError(f"demo --seeds: give distinct seeds, got {list(seeds)}")
    reports = {s: run_main_job(out / f"seed_{s}", seed=s, **kwargs) for s in seeds}
    summary = across_seeds(reports)
    summary["settings"] = reports[seeds[0]]["settings"]
    summary["timing_s"] = {s: r["timing_s"] for s, r in reports.items()}
    summary["checks"] = {s: r["checks"] for s, r in reports.items()}
    out.mkdir(parents=True, exist_ok=True)
    (out / "seeds.json").write_text(json.dumps(summary, indent=2) + "\n")
    (out / "seeds.md").write_text(_seeds_markdown(summary))
    return summary


def _seeds_markdown(summary: dict[str, Any]) -> str:
    """The table of :func:`across_seeds`: mean ± standard deviation [least, greatest]."""
    lines = [
        f"# The demo over seeds {', '.join(map(str, summary['seeds']))}",
        "",
        "Mean ± standard deviation over the seeds [least, greatest]; each seed's report "
        "is in its `seed_<s>/report` folder.",
        "",
        "| policy | condition | progress (m) | distance (m) | rolls / ep. | success "
        "| CoM error (cm) |",
        "|---|---|---|---|---|---|---|",
    ]

    def cell(f: dict[str, float], scale: float = 1.0) -> str:
        return (
            f"{scale * f['mean']:.2f} ± {scale * f['std']:.2f} "
            f"[{scale * f['min']:.2f}, {scale * f['max']:.2f}]"
        )

    for policy, by_condition in summary["results"].items():
        for cond, f in by_condition.items():
            lines.append(
                f"| {policy} | {cond} | {cell(f['progress_mean_m'])} "
                f"| {cell(f['distance_mean_m'])} "
                f"| {cell(f['rolls_per_episode'])} | {cell(f['success_rate'])} "
                f"| {cell(f['com_error_mean_m'], 100.0)} |"
            )
    return "\n".join(lines + _seed_checks(summary.get("checks", {}))) + "\n"


def _seed_checks(checks: dict[int, dict[str, Any]]) -> list[str]:
    """Markdown lines: each seed's trained policies against the targets (the reports'
    checks, in the words of their headlines)."""
    if not checks:
        return []
    lines = ["", "## The targets, seed by seed", ""]
    for seed, by_policy in checks.items():
        for name, c in by_policy.items():
            lines.append(f"- seed {seed}, **{name}** under `{c['condition']}`: {check_sentence(c)}")
    return lines
