"""The sim-to-real report: every policy under every condition, as a Markdown page with
a table and plots, and the same numbers as JSON."""

from __future__ import annotations

import json
import logging
from pathlib import PurePath
from typing import TYPE_CHECKING, Any

import numpy as np

from agents.evaluation.evaluate import (
    BASELINES,
    CONDITIONS,
    GAIT_BASELINES,
    GAIT_POLICY,
    RANDOM_POLICY,
    STEER_POLICY,
    condition,
    evaluate_policies,
    gait_policy,
    load_policy,
    random_policy,
    summarise,
)
from agents.evaluation.plots import pyplot
from agents.training.cluster import executor
from tensegrity_gym.sim.engines import DEFAULT_ENGINE

if TYPE_CHECKING:
    from collections.abc import Sequence
    from pathlib import Path

    from agents.evaluation.evaluate import EpisodeResult, LoadedPolicy

__all__ = ["check_sentence", "steering_sentence", "write_report"]

log = logging.getLogger(__name__)

TARGET_PROGRESS_RATIO = 3.0
TARGET_ROLLS = 1.0
TARGET_GAIT_SHARE = 0.5
"""A trained policy's progress toward the goal, at least this share of the scripted
gait's on the same episodes (any positive progress where the gait made none). The gait
rolls along a heading fixed to the robot's body, so toward goals drawn at random its
expected progress is nil and a few episodes' mean is mostly noise: the share of the
distance it rolls its own way (``progress_vs_gait_distance``) is the stricter yardstick."""
TARGET_STEERING_SHARE = 1.1
"""The yardstick that counts: a trained policy's progress toward the goal, at least this
share of the steering gait's (the best hand gait: it aims) on the same episodes."""
MIN_GAIT_DISTANCE = 0.01
"""m: a gait that rolled less than this is given no share of its distance."""


def _monitor_curve(run_dir: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """(timesteps, episode return) from the Monitor logs of a training run, episodes in
    the order they ended; None where the run left no log or no finished episode.

    Raises:
        ValueError: a log that SB3's reader cannot parse, in one line naming the folder.
    """
    from stable_baselines3.common.monitor import LoadMonitorResultsError, load_results

    folder = run_dir / "monitor"
    try:
        frame = load_results(str(folder))
        lengths = frame["l"].to_numpy(dtype=np.int64)
        returns = frame["r"].to_numpy(dtype=np.float64)
    except LoadMonitorResultsError:  # no *.monitor.csv there
        return None
    except AssertionError:  # SB3 asserts the first line is Monitor's '#{...}' header
        raise ValueError(f"{folder}: a Monitor log lacks its '#{{...}}' header line") from None
    except (ValueError, KeyError) as e:  # pandas' and json's errors are ValueErrors
        why = " ".join(str(e).split()) or type(e).__name__
        raise ValueError(f"{folder}: unreadable Monitor log ({why})") from None
    if not len(lengths):
        return None
    return np.cumsum(lengths), returns


def _plot_paths(results: dict[str, dict[str, list[EpisodeResult]]], file: Path, title: str) -> None:
    plt = pyplot()
    names = list(results)
    conditions = list(next(iter(results.values())))
    fig, axes = plt.subplots(
        1, len(conditions), figsize=(3.2 * len(conditions), 3.4), squeeze=False
    )
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, cond in zip(axes[0], conditions, strict=True):
        for k, name in enumerate(names):
            for e, ep in enumerate(results[name][cond][:3]):
                c = colours[k % len(colours)]
                label = name if e == 0 else None
                ax.plot(ep.true_path[:, 0], ep.true_path[:, 1], "-", color=c, label=label)
                ax.plot(ep.est_path[:, 0], ep.est_path[:, 1], ":", color=c, alpha=0.8)
        ax.plot(0, 0, "k+")
        ax.set_title(cond, fontsize=9)
        ax.set_xlabel("x (m)")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True, alpha=0.3)
    axes[0][0].set_ylabel("y (m)")
    axes[0][0].legend(fontsize=7, loc="best")
    fig.suptitle(f"{title}: CoM from above, true (solid) and estimated (dotted); goal +x")
    fig.tight_layout()
    fig.savefig(file, dpi=110)
    plt.close(fig)


def _plot_errors(results: dict[str, dict[str, list[EpisodeResult]]], file: Path) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 3.5))
    name = next(n for n in results if n not in BASELINES)
    for cond, episodes in results[name].items():
        if cond == "oracle":
            continue
        length = min(len(ep.errors) for ep in episodes)
        mean = np.mean([ep.errors[:length] for ep in episodes], axis=0)
        ax.plot(0.1 * np.arange(length), 100 * mean, label=cond)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("CoM error (cm)")
    ax.set_title(f"estimation error along the way ({name}, mean over episodes)")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(file, dpi=110)
    plt.close(fig)


def _plot_training(curves: dict[str, tuple[np.ndarray, np.ndarray]], file: Path) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 3.5))
    for name, (steps, returns) in curves.items():
        window = max(1, len(returns) // 20)
        smooth = np.convolve(returns, np.ones(window) / window, mode="valid")
        ax.plot(steps[window - 1 :], smooth, label=name)
    ax.set_xlabel("training steps")
    ax.set_ylabel("episode return")
    ax.set_title("training reward (Monitor, moving average)")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(file, dpi=110)
    plt.close(fig)


def write_report(
    run_dirs: Sequence[Path],
    out: Path,
    *,
    episodes: int = 5,
    conditions: Sequence[str] = tuple(CONDITIONS),
    seed: int = 1000,
    include_random: bool = True,
    ray_address: str | None = None,
    engine: str | None = None,
) -> dict[str, Any]:
    """Evaluate the trained policies of ``run_dirs`` (and a random policy) under
    ``conditions``; write ``report.md``, ``report.json`` and the plots into ``out``.
    ``ray_address``: the episodes run as tasks on that Ray cluster (the same numbers);
    ``engine``: the physics engine they run on (None: the default; a policy trained on
    one engine can be evaluated on the other)."""
    chosen = {c: condition(c) for c in conditions}  # an unknown name is refused here
    if not run_dirs:
        raise ValueError("no trained model to evaluate")
    policies: list[LoadedPolicy] = [load_policy(d) for d in run_dirs]
    env_ids = {p.env_id for p in policies}
    if len(env_ids) > 1:
        raise ValueError(f"the models are of different envs: {sorted(env_ids)}")
    env_id = env_ids.pop()
    names = [p.name for p in policies]
    if len(set(names)) < len(names):  # two runs trained on the same estimator
        for p, label in zip(policies, _distinct_labels(run_dirs), strict=True):
            p.name = f"{p.name} ({label})"
    trained = list(policies)
    # The training curves first: an unreadable log fails before the long evaluation.
    curves = {
        p.name: c
        for p, d in zip(trained, run_dirs, strict=True)
        if (c := _monitor_curve(d)) is not None
    }
    if include_random:
        policies.append(random_policy(env_id, seed))
        gaits = (gait_policy(env_id, name) for name in GAIT_BASELINES)
        policies += [g for g in gaits if g is not None]
    out.mkdir(parents=True, exist_ok=True)
    log.info("evaluating %s under %s", [p.name for p in policies], list(conditions))
    with executor(ray_address) as jobs:
        results = evaluate_policies(policies, list(chosen.values()), episodes, seed, jobs, engine)
    table = {p: {c: summarise(r) for c, r in by_cond.items()} for p, by_cond in results.items()}
    checks = _checks(table, [p.name for p in trained], conditions) if include_random else {}

    _plot_paths(results, out / "com_paths.png", env_id.split("/")[-1])
    _plot_errors(results, out / "estimation_error.png")
    if curves:
        _plot_training(curves, out / "training.png")

    report = {
        "env": env_id,
        "episodes": episodes,
        "seed": seed,
        "engine": engine or DEFAULT_ENGINE,
        "conditions": {c: chosen[c].about for c in conditions},
        "results": table,
        "checks": checks,
        "runs": [str(d) for d in run_dirs],
    }
    (out / "report.json").write_text(json.dumps(report, indent=2) + "\n")
    (out / "report.md").write_text(_markdown(report, bool(curves)))
    return report


def _distinct_labels(run_dirs: Sequence[Path]) -> list[str]:
    """The shortest trailing parts of the run folders' paths, as given, that tell them
    apart (``seed_0/ppo_ukf`` and ``seed_1/ppo_ukf``, not ``ppo_ukf`` twice); ValueError
    for one run given twice."""
    real = [d.resolve() for d in run_dirs]
    for k, d in enumerate(run_dirs):
        if real.index(real[k]) != k:
            raise ValueError(f"evaluate: the run {d} is given twice")
    parts = [d.absolute().parts for d in run_dirs]
    labels = []
    for k, mine in enumerate(parts):
        others = parts[:k] + parts[k + 1 :]
        depth = next((n for n in range(1, len(mine))
                      if all(p[-n:] != mine[-n:] for p in others)), len(mine))  # fmt: skip
        labels.append(str(PurePath(*mine[-depth:])))
    return labels


def _checks(
    table: dict[str, dict[str, dict[str, Any]]], trained: list[str], conditions: Sequence[str]
) -> dict[str, Any]:
    """Each trained policy against the baselines, under the UKF (else the first
    condition): its progress over the random policy's and the scripted gait's (where the
    robot has one), its rolls, and whether the targets are met."""
    cond = "ukf" if "ukf" in conditions else conditions[0]
    random_progress = table[RANDOM_POLICY][cond]["progress_mean_m"]
    gait = table.get(GAIT_POLICY, {}).get(cond)
    steering = table.get(STEER_POLICY, {}).get(cond)
    checks: dict[str, Any] = {}
    for name in trained:
        row = table[name][cond]
        ratio = row["progress_mean_m"] / max(abs(random_progress), 1e-3)
        checks[name] = {
            "condition": cond,
            "progress_m": row["progress_mean_m"],
            "speed_rod_lengths_per_s": row.get("speed_rod_lengths_per_s"),
            "success_rate": row.get("success_rate"),
            "progress_vs_random": round(ratio, 1),
            "rolls_per_episode": row["rolls_per_episode"],
            "rolls_target_met": row["rolls_per_episode"] >= TARGET_ROLLS,
            "progress_target_met": ratio >= TARGET_PROGRESS_RATIO,
        }
        if gait is not None:
            checks[name].update(_against_gait(row["progress_mean_m"], gait))
        if steering is not None:
            checks[name].update(_against_steering(row["progress_mean_m"], steering))
    return checks


def _against_steering(mine: float, steering: dict[str, Any]) -> dict[str, Any]:
    """A policy's progress toward the goal (m) against the steering gait's row: the
    share of its progress, whether that meets :data:`TARGET_STEERING_SHARE` (on the
    share as printed; where the gait went nowhere, any progress of the policy's own),
    and the gait's speed and success beside."""
    g = steering["progress_mean_m"]
    share = _share(mine, g)
    return {
        "steering_progress_m": g,
        "progress_vs_steering": share,
        "steering_target_met": mine > 0 and (share is None or share >= TARGET_STEERING_SHARE),
        "steering_speed_rod_lengths_per_s": steering.get("speed_rod_lengths_per_s"),
        "steering_success_rate": steering.get("success_rate"),
    }


def _share(mine: float, theirs: float) -> float | None:
    """``mine`` as a share of a baseline's progress ``theirs`` (m), rounded; None where
    the baseline went nowhere or backwards (a share of that would read as a small one)."""
    return round(mine / theirs, 2) if theirs > 0 else None


def _against_gait(mine: float, gait: dict[str, Any]) -> dict[str, Any]:
    """A policy's progress toward the goal (m) against the scripted gait's row: the share
    of the gait's progress (None where the gait went backwards: a share of that would
    read as a small one), whether it meets :data:`TARGET_GAIT_SHARE` (judged on the
    share as printed), and the share of the distance the gait rolled its own way."""
    g, distance = gait["progress_mean_m"], gait["distance_mean_m"]
    share = _share(mine, g)
    return {
        "gait_progress_m": g,
        "progress_vs_gait": share,
        "gait_target_met": mine > 0 and (share is None or share >= TARGET_GAIT_SHARE),
        "gait_distance_m": distance,
        "progress_vs_gait_distance": (
            round(mine / distance, 2) if np.isfinite(distance) and distance >= MIN_GAIT_DISTANCE
            else None
        ),
    }  # fmt: skip


def _met(flag: bool) -> str:
    return "met" if flag else "NOT met"


def check_sentence(check: dict[str, Any]) -> str:
    """A trained policy's check (:func:`_checks`) as a sentence: its progress against a
    random policy's, its rolls and, where the robot has a gait, against the gait's, each
    with its target; where it has a steering gait, the share of that gait's progress."""
    return (
        f"{check['progress_vs_random']}x the progress of a random policy (target "
        f"{TARGET_PROGRESS_RATIO:g}x: {_met(check['progress_target_met'])}), "
        f"{check['rolls_per_episode']} rolls per episode (target {TARGET_ROLLS:g}: "
        f"{_met(check['rolls_target_met'])})" + _gait_share(check) + _steering_share(check)
    )


def _steering_share(check: dict[str, Any]) -> str:
    """The sentence's end on the steering gait (which aims), where the robot has one."""
    share = check.get("progress_vs_steering")
    if "steering_progress_m" not in check:
        return ""
    g = check["steering_progress_m"]
    return f" The steering gait made {g:.2f} m toward the goal" + (
        f"; the policy made {share:.0%} of that (target {TARGET_STEERING_SHARE:.0%}: "
        f"{_met(check['steering_target_met'])})."
        if share is not None
        else f" (target, progress of its own: {_met(check['steering_target_met'])})."
    )


def _speed(value: float | None) -> str:
    return "-" if value is None or not np.isfinite(value) else f"{value:.3f}"


def _percent(share: float | None) -> str:
    return "-" if share is None else f"{100 * share:.0f} %"


def steering_sentence(name: str, check: dict[str, Any]) -> str:
    """The headline's sentence for one trained policy against the steering gait: the
    progress toward the goal, its share, the speed in rod lengths per second and the
    success, each beside the gait's."""
    share = check["progress_vs_steering"]
    of = f"{share:.0%} of" if share is not None else "against"
    return (
        f"**{name}**, under `{check['condition']}`: {check['progress_m']:.2f} m toward the "
        f"goal, {of} the steering gait's {check['steering_progress_m']:.2f} m (target "
        f"{TARGET_STEERING_SHARE:.0%}: {_met(check['steering_target_met'])}); "
        f"{_speed(check['speed_rod_lengths_per_s'])} rod lengths/s against "
        f"{_speed(check['steering_speed_rod_lengths_per_s'])}; success "
        f"{_percent(check['success_rate'])} against {_percent(check['steering_success_rate'])}."
    )


def _gait_share(check: dict[str, Any]) -> str:
    """The check's sentence end on the scripted gait, where there is a gait: the share of
    its progress toward the same goals, and of the distance it rolls its own way (what
    its progress would be had every goal lain that way)."""
    if "gait_progress_m" not in check:
        return "."
    met = _met(check["gait_target_met"])
    toward = (
        f"{check['progress_vs_gait']:.0%} of the scripted gait's progress "
        f"(target {TARGET_GAIT_SHARE:.0%}: {met})"
        if check["progress_vs_gait"] is not None
        else "the scripted gait made no progress toward the goal "
        f"({check['gait_progress_m']:.2f} m; target, progress of its own: {met})"
    )
    own_way = check["progress_vs_gait_distance"]
    if own_way is None:  # the gait stayed put, or its distance is not a number
        rolled = check["gait_distance_m"]
        return f"; {toward}" + (
            f"; the gait rolled {rolled:.2f} m its own way." if np.isfinite(rolled) else "."
        )
    return (
        f"; {toward}, and {own_way:.0%} of the distance the gait rolls its own way "
        f"({check['gait_distance_m']:.2f} m)."
    )


def _headline(checks: dict[str, Any], results: dict[str, Any]) -> list[str]:
    """Markdown lines: the policy trained on truth against the one trained on UKF
    estimates, under the UKF, then each trained policy's targets."""
    both = "trained on oracle" in results and "trained on ukf" in results
    if not (checks or both):
        return []
    lines = ["## Headline", ""]
    # The yardstick first: the best hand gait the robot has.
    against = [f"- {steering_sentence(name, c)}" for name, c in checks.items()
               if "steering_progress_m" in c]  # fmt: skip
    if against:
        lines += [*against, ""]
    if both:
        o = results["trained on oracle"].get("ukf")
        u = results["trained on ukf"].get("ukf")
        o_truth = results["trained on oracle"].get("oracle")
        if o and u and o_truth:
            lines.append(
                f"On UKF estimates, the policy trained on ground truth moves the CoM "
                f"{o['progress_mean_m']:.2f} m toward the goal ("
                f"{o_truth['progress_mean_m']:.2f} m on ground truth); the policy trained on "
                f"UKF estimates, {u['progress_mean_m']:.2f} m. Success "
                f"{100 * o['success_rate']:.0f} % against {100 * u['success_rate']:.0f} %."
            )
            lines.append("")
    lines += [f"- **{name}**, under `{c['condition']}`: {check_sentence(c)}"
              for name, c in checks.items()]  # fmt: skip
    return [*lines, ""]


def _markdown(report: dict[str, Any], training_plot: bool) -> str:
    env = report["env"]
    lines = [
        f"# {env.split('/')[-1]}: what estimation costs a rolling policy",
        "",
        f"{report['episodes']} episodes per policy and condition (seeds {report['seed']}..."
        f"{report['seed'] + report['episodes'] - 1}, the same for every row). Progress is the "
        "true CoM's displacement along the goal heading over the episode (a Roll id), or "
        "its approach to the goal points, each up to the step that reached it (a GoTo id); "
        "speed is progress per second, in rod lengths; success is the true CoM within the "
        "task's radius of a goal (a GoTo id) or a progress of at least one rod length (a "
        "Roll id); distance is its straight-line displacement in whatever direction; a "
        "roll is a tip onto a new base triangle.",
        "",
    ]
    lines += _headline(report["checks"], report["results"])
    lines += [
        "## Every policy under every condition",
        "",
        "| policy | condition | progress (m) | speed (rod lengths/s) | distance (m) "
        "| success | rolls / ep. | CoM error (cm) | re-inits | divergences | return |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for policy, by_cond in report["results"].items():
        for cond, r in by_cond.items():
            lines.append(
                f"| {policy} | {cond} | {r['progress_mean_m']:.3f} ± {r['progress_std_m']:.3f} "
                f"| {_speed(r.get('speed_rod_lengths_per_s'))} | {r['distance_mean_m']:.2f} "
                f"| {100 * r['success_rate']:.0f} % "
                f"| {r['rolls_per_episode']:.1f} "
                f"| {100 * r['com_error_mean_m']:.2f} | {r['reinitialisations']} "
                f"| {r['divergences']} | {r['return_mean']:.1f} |"
            )
    lines += ["", "Conditions:", ""]
    lines += [f"- `{c}`: {about}" for c, about in report["conditions"].items()]
    lines += [
        "",
        "## Plots",
        "",
        "![CoM paths](com_paths.png)",
        "",
        "![Estimation error](estimation_error.png)",
        "",
    ]
    if training_plot:
        lines += ["![Training reward](training.png)", ""]
    lines += ["Numbers: `report.json`. Training runs: " + ", ".join(report["runs"]), ""]
    return "\n".join(lines)
