"""``demo``, ``train``, ``evaluate`` and ``gait``: policies trained, evaluated and rolled."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from agents.cli.arguments import (
    Command,
    add_engine,
    add_randomization,
    add_ray,
    count,
    env_help,
    env_kwarg,
    given,
    hyperparam,
    pairs,
    positive_float,
    positive_int,
    tempo,
)
from agents.cli.errors import log, one_line

__all__ = ["COMMANDS"]


def add_demo(demo: argparse.ArgumentParser) -> None:
    """``demo``'s options: the training budget, the evaluation, the seeds, the gait."""
    demo.add_argument(
        "--timesteps", type=positive_int, help="UKF training steps (default: the demo's budget)"
    )
    demo.add_argument(
        "--oracle-timesteps", type=count,
        help="ground-truth training steps (0: skip; default: the demo's budget)",
    )  # fmt: skip
    demo.add_argument(
        "--episodes", type=positive_int, default=5, help="evaluation episodes per row"
    )
    seeding = demo.add_mutually_exclusive_group()
    seeding.add_argument(
        "--seed", type=count, default=0,
        help="seeds the training (the evaluation's episodes are the same for every seed)",
    )  # fmt: skip
    seeding.add_argument(
        "--seeds",
        type=count,
        nargs="+",
        help="run the demo once per seed (into OUT/seed_<s>) and report mean ± spread "
        "across them in OUT/seeds.md",
    )
    demo.add_argument(
        "--absolute-actions", action="store_true",
        help="the policies command rest-length targets themselves, not corrections of the "
        "scripted gait (gym.make's residual_gait)",
    )  # fmt: skip
    demo.add_argument(
        "--base-gait", metavar="GAIT",
        help="the robot's gait the policies correct (gym.make's base_gait; default 'steer', "
        "the steering gait; 'forward': the gait that rolls its own way)",
    )  # fmt: skip
    demo.add_argument("--out", default="demo_out", help="folder for the runs and the report")
    demo.add_argument("--no-progress", action="store_true", help="no progress bars")


def _demo_budget(args: argparse.Namespace) -> dict[str, Any]:
    """The arguments of the demo's run from ``demo``'s options; ValueError for a
    ``--base-gait`` with ``--absolute-actions``."""
    from agents.demo import RESIDUAL_GAIT

    budget: dict[str, Any] = {
        "episodes": args.episodes,
        "progress_bar": not args.no_progress,
        "residual_gait": None if args.absolute_actions else RESIDUAL_GAIT,
    }
    if args.base_gait is not None:  # else the demo's own
        if args.absolute_actions:
            raise ValueError("demo: --base-gait names the gait the policies correct; "
                             "--absolute-actions policies correct none")  # fmt: skip
        budget["base_gait"] = args.base_gait
    for key, value in (("ukf_timesteps", args.timesteps),
                       ("oracle_timesteps", args.oracle_timesteps)):  # fmt: skip
        if value is not None:  # else run_main_job's own: the demo's budget
            budget[key] = value
    return budget


def _demo_seeds(args: argparse.Namespace, budget: dict[str, Any]) -> int:
    """``demo --seeds``: the demo once per seed; print each policy's progress under the
    UKF across them."""
    from agents.demo import run_main_job_seeds

    summary = run_main_job_seeds(Path(args.out), args.seeds, **budget)
    sys.stdout.write(f"over seeds {summary['seeds']}: {Path(args.out) / 'seeds.md'}\n")
    for policy, by_condition in summary["results"].items():
        progress = by_condition.get("ukf", {}).get("progress_mean_m")
        if progress is not None:
            sys.stdout.write(
                f"  {policy} under ukf: progress {progress['mean']:.2f} ± "
                f"{progress['std']:.2f} m [{progress['min']:.2f}, {progress['max']:.2f}]\n"
            )
    return 0


def run_demo(args: argparse.Namespace) -> int:
    """``demo``: the main job (or one per seed); print the report's path and checks."""
    from agents.demo import run_main_job
    from agents.evaluation.report import check_sentence

    budget = _demo_budget(args)
    if args.seeds:
        return _demo_seeds(args, budget)
    report = run_main_job(Path(args.out), seed=args.seed, **budget)
    sys.stdout.write(f"report: {Path(args.out) / 'report' / 'report.md'}\n")
    for name, check in report["checks"].items():
        sys.stdout.write(f"  {name} under {check['condition']}: {check_sentence(check)}\n")
    sys.stdout.write(f"  wall time per stage (s): {report['timing_s']}\n")
    return 0


def _add_moves(tr: argparse.ArgumentParser) -> None:
    """``train``'s options of a policy that makes the steering gait's choices."""
    tr.add_argument(
        "--moves", default=None, metavar="GAIT",
        help="the policy picks among the support face's moves of the robot's steering "
        "gait GAIT (e.g. steer), a step a gait period (PPO; --timesteps then counts those "
        "choices); default: actions are the rest-length targets",
    )  # fmt: skip
    tr.add_argument(
        "--move-tempos", nargs="+", type=tempo, default=None, metavar="HOLD/SETTLE",
        help="with --moves: a choice also sets its period's tempo, the gait's own or one "
        "of these (hold and settle control steps, e.g. 15/0)",
    )  # fmt: skip
    tr.add_argument(
        "--move-ranks", type=positive_int, default=None, metavar="K",
        help="with --moves: a choice picks among the gait's first K ranks (1: the gait's "
        "own move, the policy setting the tempo); default: every entry of a face",
    )  # fmt: skip


def add_train(tr: argparse.ArgumentParser) -> None:
    """``train``'s options: the env, the algorithm and its hyperparameters, the run."""
    from agents.training.presets import PRESETS
    from agents.training.train import ALGORITHMS
    from tensegrity_gym.model.registry import ESTIMATORS

    tr.add_argument("--env", default="tensegrity_gym/ThreeBarRoll-v0", help=env_help())
    tr.add_argument("--algo", default="ppo", choices=list(ALGORITHMS), help="algorithm")
    tr.add_argument("--estimator", default="ukf", choices=list(ESTIMATORS.names()),
                    help="what the policy's observations are estimated with")  # fmt: skip
    tr.add_argument("--timesteps", type=positive_int, default=None, help="default: the config's")
    tr.add_argument("--seed", type=count, default=0, help="seeds the envs and the algorithm")
    tr.add_argument(
        "--n-envs", type=positive_int, default=None, help="workers; default: the config's"
    )
    tr.add_argument("--config", default=None, help="hyperparameter YAML (rl-zoo3 layout)")
    add_randomization(tr, "train in worlds drawn from these ranges at each reset")
    tr.add_argument(
        "--residual-gait", type=positive_float, default=None, metavar="SCALE",
        help="actions correct the robot's scripted gait, scaled by SCALE "
        "(gym.make(residual_gait=)); default: actions are the rest-length targets",
    )  # fmt: skip
    _add_moves(tr)
    tr.add_argument(
        "--env-kwargs", type=env_kwarg, nargs="+", action="extend", default=None,
        metavar="KEY:VALUE",
        help="more gym.make arguments for training, as rl-zoo3 takes them (e.g. the "
        "task's ctrl_cost:0.0); the run's config keeps them",
    )  # fmt: skip
    tr.add_argument(
        "--hyperparams", type=hyperparam, nargs="+", action="extend", default=None,
        metavar="KEY:VALUE",
        help="hyperparameters put over the config's, as rl-zoo3 takes them (e.g. "
        "learning_rate:1e-4 policy_kwargs:\"dict(log_std_init=-2.0)\"); the run's config "
        "keeps them",
    )  # fmt: skip
    tr.add_argument("--out", required=True, help="folder for the run")
    tr.add_argument(
        "--preset", choices=sorted(PRESETS), default=None,
        help="named settings that fill in the options not given: "
        + "; ".join(f"{k}: {p.about}" for k, p in PRESETS.items()),
    )  # fmt: skip
    tr.add_argument(
        "--resume", action="store_true",
        help="go on with the run in --out from its newest checkpoint, with its own "
        "settings (--timesteps: a new total)",
    )  # fmt: skip
    tr.add_argument(
        "--checkpoint-every", type=positive_int, default=50_000,
        help="steps between the run's checkpoints",
    )  # fmt: skip
    tr.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_engine(tr)
    add_ray(tr, "step the envs on --workers Ray actors")
    tr.add_argument("--workers", type=positive_int, default=None,
                    help="Ray actors sharing the --n-envs envs (default: one per CPU of the "
                    "cluster, at most --n-envs); with --ray only")  # fmt: skip


_OWN_OPTIONS = {"estimator": "--estimator", "randomization": "--randomization",
                "residual_gait": "--residual-gait", "robot": "--env", "task": "--env",
                "engine": "--engine"}  # fmt: skip
"""``gym.make`` arguments that ``train`` has an option of its own for (the env id names
the robot and the task)."""


def training_env_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """``--env-kwargs`` and the options that are ``gym.make`` arguments, as one dict;
    raises ValueError for a key given twice or one that has its own option."""
    kwargs = pairs(args.env_kwargs, "--env-kwargs")
    for key in kwargs:
        if key in _OWN_OPTIONS:
            raise ValueError(f"--env-kwargs {key}: use {_OWN_OPTIONS[key]} instead")
    return {**kwargs, **given(args, "randomization", "residual_gait", "engine")}


_SETTINGS = ("config", "hyperparams", "env_kwargs", "residual_gait", "randomization",
             "n_envs", "engine", "preset", "moves", "move_tempos",
             "move_ranks")  # fmt: skip
"""``train``'s options that a resumed run takes from its own config instead."""


def _with_preset(args: argparse.Namespace) -> argparse.Namespace:
    """``args`` with ``--preset``'s settings where the command line gave none."""
    from agents.training.presets import preset

    if args.preset is None:
        return args
    p = preset(args.preset)
    kwargs = dict(args.env_kwargs or [])
    extra = [(k, v) for k, v in p.env_kwargs.items() if k not in kwargs]
    return argparse.Namespace(**(vars(args) | {
        "config": args.config or str(p.config),
        "timesteps": args.timesteps or p.timesteps,
        "residual_gait": args.residual_gait if args.residual_gait is not None
        else p.residual_gait,
        "env_kwargs": [*(args.env_kwargs or []), *extra],
        "moves": args.moves or p.moves,
        "move_tempos": args.move_tempos or (
            None if p.move_tempos is None else [list(t) for t in p.move_tempos]),
        "move_ranks": args.move_ranks or p.move_ranks,
    }))  # fmt: skip


def _train_or_resume(args: argparse.Namespace) -> Path:
    """The run ``args`` ask for: a new one, or (``--resume``) the one in ``--out`` going
    on; ValueError for a setting given to a resumed run."""
    from agents.training.resume import resume
    from agents.training.train import train

    if args.resume:
        named = [f"--{n.replace('_', '-')}" for n in _SETTINGS if getattr(args, n) is not None]
        if named:
            raise ValueError(
                f"train --resume goes on with the run's own settings: leave out {named}"
            )
        return resume(Path(args.out), timesteps=args.timesteps,
                      checkpoint_every=args.checkpoint_every,
                      progress_bar=not args.no_progress, ray_address=args.ray,
                      workers=args.workers)  # fmt: skip
    args = _with_preset(args)
    return train(
        args.env,
        args.algo,
        args.estimator,
        Path(args.out),
        timesteps=args.timesteps,
        seed=args.seed,
        n_envs=args.n_envs,
        config_file=Path(args.config) if args.config else None,
        hyperparams=pairs(args.hyperparams, "--hyperparams"),
        checkpoint_every=args.checkpoint_every,
        progress_bar=not args.no_progress,
        env_kwargs=training_env_kwargs(args),
        ray_address=args.ray,
        workers=args.workers,
        moves=args.moves,
        move_tempos=args.move_tempos,
        move_ranks=args.move_ranks,
    )


def run_train(args: argparse.Namespace) -> int:
    """``train``: train a policy, or go on with one; print the run's path (130 when
    interrupted)."""
    try:
        path = _train_or_resume(args)
    except KeyboardInterrupt:
        log.warning("interrupted: the model reached so far is in %s", args.out)
        return 130
    except ValueError as err:
        log.error("%s", one_line(err))
        return 2
    sys.stdout.write(f"{path}\n")
    return 0


def add_evaluate(ev: argparse.ArgumentParser) -> None:
    """``evaluate``'s options: the runs, the conditions, the episodes."""
    from agents.evaluation.evaluate import CONDITIONS, condition_names

    ev.add_argument("models", nargs="+", help="training run folders (from train)")
    ev.add_argument("--episodes", type=positive_int, default=10, help="episodes per row")
    ev.add_argument(
        "--conditions",
        nargs="+",
        default=list(CONDITIONS),
        choices=condition_names(),
        help="estimators and worlds to evaluate under",
    )
    ev.add_argument("--seed", type=count, default=1000, help="episode k uses seed + k")
    ev.add_argument("--out", required=True, help="folder for the report")
    add_engine(ev)
    add_ray(ev, "run each episode as a Ray task")


def run_evaluate(args: argparse.Namespace) -> int:
    """``evaluate``: write the report; print its path and a row per policy and condition."""
    from agents.evaluation.report import write_report

    try:
        report = write_report(
            [Path(m) for m in args.models],
            Path(args.out),
            episodes=args.episodes,
            conditions=args.conditions,
            seed=args.seed,
            ray_address=args.ray,
            engine=args.engine,
        )
    except ValueError as err:
        log.error("%s", one_line(err))
        return 2
    sys.stdout.write(f"report: {Path(args.out) / 'report.md'}\n")
    for policy, by_cond in report["results"].items():
        for cond, r in by_cond.items():
            sys.stdout.write(
                f"  {policy:>20} | {cond:>13} | progress {r['progress_mean_m']:+.3f} m | "
                f"rolls {r['rolls_per_episode']:.1f} | "
                f"CoM error {100 * r['com_error_mean_m']:.2f} cm\n"
            )
    return 0


def add_gait(gait: argparse.ArgumentParser) -> None:
    """``gait``'s options: the env, the gait, the estimator plotted."""
    from tensegrity_gym.model.registry import ESTIMATORS

    gait.add_argument("--env", default="tensegrity_gym/ThreeBarRoll-v0", help=env_help())
    gait.add_argument("--steps", type=positive_int, default=300, help="control steps (10 Hz)")
    gait.add_argument("--seed", type=count, default=0, help="the episode's seed")
    gait.add_argument("--estimator", default="ukf", choices=list(ESTIMATORS.names()),
                      help="the estimator whose CoM is plotted against the truth")  # fmt: skip
    gait.add_argument(
        "--gait",
        default="forward",
        help="which of the robot's gaits, by name: forward (its YAML's gait) or one of its "
        "YAML's gaits (three_bar_large: backward, left, right); another is refused with "
        "the list",
    )
    gait.add_argument("--out", default="gait_out", help="folder for the plot and summary")
    add_engine(gait)


def run_gait(args: argparse.Namespace) -> int:
    """``gait``: roll the robot; print where its CoM went and the estimate's error (1 when
    the estimate diverged)."""
    from agents.gait import run_gait as roll

    summary = roll(
        args.env,
        steps=args.steps,
        seed=args.seed,
        estimator=args.estimator,
        gait=args.gait,
        out=Path(args.out),
        **given(args, "engine"),
    )
    s, e = summary["com_start"], summary["com_end"]
    sys.stdout.write(
        f"{summary['env']}: scripted gait {summary['gait']!r}, {summary['seconds']:.1f} s "
        f"simulated, {summary['face_changes']} support-face changes\n"
        f"  true CoM went from ({s[0]:+.3f}, {s[1]:+.3f}) to ({e[0]:+.3f}, {e[1]:+.3f}) m: "
        f"{summary['distance']:.3f} m in a straight line, {summary['path_length']:.3f} m of path "
        f"({summary['rest_path_length']:.3f} m from rest to rest), turning "
        f"{summary['heading_change_deg']:+.0f} deg (left > 0)\n"
        f"  {summary['estimator']} estimate of the CoM: "
        f"{100 * summary['estimation_error_rms']:.1f} cm RMS error, "
        f"{100 * summary['estimation_error_max']:.1f} cm at worst\n"
        f"  plot: {summary['plot']}\n"
    )
    return 1 if summary["diverged"] else 0


COMMANDS = (
    Command(
        "demo",
        "the main job: train PPO with the UKF in the loop (and on ground truth), evaluate, "
        "write the report",
        add_demo,
        run_demo,
    ),
    Command("train", "train a policy with stable-baselines3", add_train, run_train),
    Command(
        "evaluate",
        "evaluate trained policies under each estimator; write the report",
        add_evaluate,
        run_evaluate,
    ),
    Command("gait", "roll a robot with its scripted gait; plot the CoM", add_gait, run_gait),
)
"""The subcommands of this module, in ``--help``'s order."""
