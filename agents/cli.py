"""The ``tensegrity-gym`` command line."""

from __future__ import annotations

import argparse
import ast
import json
import logging
import math
import signal
import sys
from pathlib import Path
from typing import Any

__all__ = ["main"]

log = logging.getLogger("tensegrity_gym")


def _count(text: str) -> int:
    """An argparse type: a whole number >= 0."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must not be negative, got {value}")
    return value


def _positive_int(text: str) -> int:
    """An argparse type: a whole number >= 1."""
    value = _count(text)
    if value == 0:
        raise argparse.ArgumentTypeError("must be at least 1, got 0")
    return value


def _env_kwargs(args: argparse.Namespace, *names: str) -> dict[str, Any]:
    """The ``gym.make`` arguments among ``names`` that the command line gave."""
    return {n: getattr(args, n) for n in names if getattr(args, n) is not None}


def _key_value(text: str) -> tuple[str, str]:
    """``KEY:VALUE`` split at its first colon; ArgumentTypeError for another form."""
    key, sep, value = text.partition(":")
    if not sep or not key.isidentifier():
        raise argparse.ArgumentTypeError(f"expected KEY:VALUE, got {text!r}")
    return key, value


def _env_kwarg(text: str) -> tuple[str, Any]:
    """An argparse type: ``KEY:VALUE``, a ``gym.make`` argument as rl-zoo3's
    ``--env-kwargs`` writes it (the value a Python literal: ``ctrl_cost:0.0``,
    ``goal_heading:None``, ``terrain:"'valley'"``)."""
    key, value = _key_value(text)
    try:
        return key, ast.literal_eval(value)
    except (ValueError, SyntaxError):
        raise argparse.ArgumentTypeError(
            f"{key}: {value!r} is not a Python literal (quote a string: {key}:\"'{value}'\")"
        ) from None


_TEXT_HYPERPARAMS = ("policy", "normalize", "policy_kwargs")
"""The hyperparameters whose value may be text as it stands (rl-zoo3 writes them so)."""


def _hyperparam(text: str) -> tuple[str, Any]:
    """An argparse type: ``KEY:VALUE``, a hyperparameter as rl-zoo3's ``--hyperparams``
    writes it (``learning_rate:1e-4``, ``policy_kwargs:"dict(log_std_init=-2.0)"``): a
    Python literal, or for :data:`_TEXT_HYPERPARAMS` the text as it stands (a
    ``dict(...)`` the config reader parses)."""
    key, value = _key_value(text)
    try:
        return key, ast.literal_eval(value)
    except (ValueError, SyntaxError):
        if key in _TEXT_HYPERPARAMS:
            return key, value
        raise argparse.ArgumentTypeError(
            f"--hyperparams {key}: {value!r} is not a Python literal"
        ) from None


def _pairs(pairs: list[tuple[str, Any]] | None, option: str) -> dict[str, Any]:
    """``KEY:VALUE`` options as a dict; ValueError for a key given twice."""
    out: dict[str, Any] = {}
    for key, value in pairs or ():
        if key in out:
            raise ValueError(f"{option} {key} is given twice")
        out[key] = value
    return out


def _finite_float(text: str) -> float:
    """``text`` as a finite float, or ArgumentTypeError."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
    return value


def _positive_float(text: str) -> float:
    """An argparse type: a finite number > 0."""
    value = _finite_float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return value


def _non_negative_float(text: str) -> float:
    """An argparse type: a finite number >= 0."""
    value = _finite_float(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {text}")
    return value


def _calibration_seconds(text: str) -> float:
    """An argparse type: a calibration run's length (s), in the range
    :func:`agents.calibration_run.check_seconds` takes (its message, after the flag)."""
    from agents.calibration_run import check_seconds

    try:
        seconds = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number of seconds, got {text!r}") from None
    try:
        return check_seconds(seconds)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err).partition(": ")[2]) from None


def _port(text: str) -> int:
    """An argparse type: a TCP port, 0 (a free one) to 65535."""
    value = _count(text)
    if value > 65535:
        raise argparse.ArgumentTypeError(f"must be a TCP port in [0, 65535], got {value}")
    return value


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Each option's default after its help, where it has one (not None, not a flag's
    False: those help texts say what their absence means)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        if action.default is None or action.default is False:
            return action.help
        return super()._get_help_string(action)


class _SubcommandParser(argparse.ArgumentParser):
    """A subcommand's parser, whose ``--help`` shows defaults (and choices, as ever)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("formatter_class", _HelpFormatter)
        super().__init__(*args, **kwargs)


def _env_help(what: str) -> str:
    """Help for ``--env``: ``what``, and the ids registered now (the robot presets' and
    the labs' own), which any other id is refused with."""
    import gymnasium as gym

    import tensegrity_gym  # noqa: F401  (registers the ids)

    ids = sorted(i for i in gym.registry if i.startswith("tensegrity_gym/"))
    return f"{what}; registered: {', '.join(ids)}"


def _one_line(err: BaseException) -> str:
    """An error's message on one line (whitespace runs, newlines among them, made one
    space), or its type's name where it has none."""
    return " ".join(str(err).split()) or type(err).__name__


def _user_errors() -> tuple[type[BaseException], ...]:
    """What a user can cause (a bad id, path, bag, robot YAML or config; a robot that does
    not answer; an estimator that cannot start from the data; a missing optional
    package): one line on stderr and exit status 2, a traceback only with --verbose."""
    import gymnasium.error

    from estimation.ukf.initialise import InitialisationError
    from hardware.link.wire import LinkError
    from hardware.viewer import ViewerError

    return (ValueError, OSError, ImportError, LinkError, InitialisationError, ViewerError,
            gymnasium.error.Error)  # fmt: skip


def _demo(args: argparse.Namespace) -> int:
    from agents.main_job import RESIDUAL_GAIT, run_main_job, run_main_job_seeds
    from agents.report import check_sentence

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
    for key, given in (("ukf_timesteps", args.timesteps),
                       ("oracle_timesteps", args.oracle_timesteps)):  # fmt: skip
        if given is not None:  # else run_main_job's own: the demo's budget
            budget[key] = given
    if args.seeds:
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
    report = run_main_job(Path(args.out), seed=args.seed, **budget)
    sys.stdout.write(f"report: {Path(args.out) / 'report' / 'report.md'}\n")
    for name, check in report["checks"].items():
        sys.stdout.write(f"  {name} under {check['condition']}: {check_sentence(check)}\n")
    sys.stdout.write(f"  wall time per stage (s): {report['timing_s']}\n")
    return 0


_OWN_OPTIONS = {"estimator": "--estimator", "randomization": "--randomization",
                "residual_gait": "--residual-gait", "robot": "--env", "task": "--env"}  # fmt: skip
"""``gym.make`` arguments that ``train`` has an option of its own for (the env id names
the robot and the task)."""


def _training_env_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """``--env-kwargs`` and the options that are ``gym.make`` arguments, as one dict;
    raises ValueError for a key given twice or one that has its own option."""
    given = _pairs(args.env_kwargs, "--env-kwargs")
    for key in given:
        if key in _OWN_OPTIONS:
            raise ValueError(f"--env-kwargs {key}: use {_OWN_OPTIONS[key]} instead")
    return {**given, **_env_kwargs(args, "randomization", "residual_gait")}


def _train(args: argparse.Namespace) -> int:
    from agents.train import train

    try:
        path = train(
            args.env,
            args.algo,
            args.estimator,
            Path(args.out),
            timesteps=args.timesteps,
            seed=args.seed,
            n_envs=args.n_envs,
            config_file=Path(args.config) if args.config else None,
            hyperparams=_pairs(args.hyperparams, "--hyperparams"),
            progress_bar=not args.no_progress,
            env_kwargs=_training_env_kwargs(args),
            ray_address=args.ray,
            workers=args.workers,
        )
    except KeyboardInterrupt:
        log.warning("interrupted: the model reached so far is in %s", args.out)
        return 130
    except ValueError as err:
        log.error("%s", _one_line(err))
        return 2
    sys.stdout.write(f"{path}\n")
    return 0


def _evaluate(args: argparse.Namespace) -> int:
    from agents.report import write_report

    try:
        report = write_report(
            [Path(m) for m in args.models],
            Path(args.out),
            episodes=args.episodes,
            conditions=args.conditions,
            seed=args.seed,
            ray_address=args.ray,
        )
    except ValueError as err:
        log.error("%s", _one_line(err))
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


def _gait(args: argparse.Namespace) -> int:
    from agents.demo import run_gait

    summary = run_gait(
        args.env,
        steps=args.steps,
        seed=args.seed,
        estimator=args.estimator,
        gait=args.gait,
        out=Path(args.out),
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


def _bench(args: argparse.Namespace) -> int:
    from agents.bench import run_benchmarks

    results = run_benchmarks(
        speed_steps=args.steps,
        memory_steps=args.memory_steps,
        estimation=args.estimation,
        bag_minutes=args.bag_minutes,
        link_steps=args.link_steps,
        soak_minutes=args.soak_minutes,
        sim2real=args.sim2real,
        ray_address=args.ray,
    )
    text = json.dumps(results, indent=2)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(text + "\n")
    sys.stdout.write(text + "\n")
    return 0


def _terminate(signum: int, frame: object) -> None:
    raise SystemExit(128 + signum)  # unwinds like Ctrl-C does, so open bags get closed


def _record(args: argparse.Namespace) -> int:
    from agents.offline import record

    signal.signal(signal.SIGTERM, _terminate)
    try:
        paths = record(
            args.env,
            args.policy,
            args.episodes,
            Path(args.out),
            steps=args.steps,
            seed=args.seed,
            estimator=args.estimator,
            driver=args.driver,
            markers=args.markers,
        )
    except KeyboardInterrupt:
        log.warning("interrupted: the bag being written was closed and is complete so far")
        return 130
    for path in paths:
        sys.stdout.write(f"{path}\n")
    return 0


def _estimate(args: argparse.Namespace) -> int:
    from agents.offline import BAG_FAILURES, BagsFailedError, estimate_bag
    from tensegrity_gym.model.description import load_robot

    failed = None
    try:
        description = load_robot(args.robot) if args.robot else None
        results = estimate_bag(
            args.bag,
            args.estimator,
            Path(args.out),
            seed=args.seed,
            description=description,
            strict=args.strict,
            progress=not args.no_progress,
            calibration=args.calibration,
            ray_address=args.ray,
        )
    except BagsFailedError as err:  # each failure is logged; the other bags were estimated
        results, failed = err.results, err
    except BAG_FAILURES as err:
        log.error("%s", _one_line(err))
        return 2
    for r in results:
        line = f"{r['bag']}: {r['steps']} steps, {r['duration_s']:.1f} s in {r['wall_s']:.1f} s"
        if "com_rmse_m" in r:
            line += (
                f"; CoM error {100 * r['com_rmse_m']:.2f} cm RMS, "
                f"ATE {100 * r.get('ate_rmse_m', float('nan')):.2f} cm"
            )
        rejected = r.get("estimator_rejected") or {}
        if rejected:
            kinds = ", ".join(f"{k} {v}" for k, v in rejected.items())
            line += f"; {sum(rejected.values())} implausible measurements rejected ({kinds})"
        sys.stdout.write(line + "\n")
    sys.stdout.write(f"written to {args.out}\n")
    if failed is not None:
        log.error("%s", failed)
        return 2
    return 0


def _calibrate(args: argparse.Namespace) -> int:
    from agents.calibration_run import calibrate_command

    result = calibrate_command(
        bag=args.bag, env_id=args.env, seconds=args.seconds, world_seed=args.world_seed,
        robot=args.robot, out=Path(args.out),
    )  # fmt: skip
    sys.stdout.write(result + "\n")
    return 0


def _identify(args: argparse.Namespace) -> int:
    from agents.identify_report import identify_command

    result = identify_command(
        args.bag, Path(args.out), params=[p for p in args.params.split(",") if p],
        robot=args.robot, model=args.model, segment_seconds=args.segment_seconds,
        max_evaluations=args.max_evaluations, workers=args.workers, seed=args.seed,
        imu_windows=args.imu_windows,
    )  # fmt: skip
    sys.stdout.write(result + "\n")
    return 0


def _view(args: argparse.Namespace) -> int:
    from agents.view import view

    bag = Path(args.bag) if args.bag else None
    view(args.env, args.policy, bag=bag, driver=args.driver, port=args.port, speed=args.speed,
         episodes=args.episodes, steps=args.steps, seed=args.seed,
         estimator=args.estimator)  # fmt: skip
    return 0


def _add_view(sub: Any, env_help: str) -> None:
    """view: the live Foxglove view of a simulation or a replayed bag."""
    from hardware.viewer import DEFAULT_PORT
    from tensegrity_gym.model.registry import ESTIMATORS

    v = sub.add_parser(
        "view", help="stream a simulation or a replayed bag to Foxglove (ws://localhost:PORT)"
    )
    v.add_argument("--env", default="tensegrity_gym/ThreeBarRoll-v0", help=env_help)
    v.add_argument("--policy", default="scripted",
                   help="scripted (the robot's face gait), random, or a training run "
                   "folder")  # fmt: skip
    v.add_argument("--bag", default=None, help="replay this bag instead (its commands drive it)")
    v.add_argument("--driver", default=None, help="a robot on the network: zenoh/tcp/HOST:PORT")
    v.add_argument("--port", type=_port, default=DEFAULT_PORT,
                   help="WebSocket port (0: any free one)")  # fmt: skip
    v.add_argument("--speed", type=_non_negative_float, default=1.0,
                   help="run time per wall-clock time; 0: as fast as it runs")  # fmt: skip
    v.add_argument("--episodes", type=_count, default=0, help="episodes; 0: until Ctrl-C")
    v.add_argument("--steps", type=_positive_int, default=None, help="control steps per episode")
    v.add_argument("--seed", type=_count, default=0, help="episode k uses seed + k")
    v.add_argument("--estimator", default="ukf", choices=list(ESTIMATORS.names()),
                   help="the estimator run in the loop")  # fmt: skip
    v.set_defaults(func=_view)


def _emulate(args: argparse.Namespace) -> int:
    from hardware.link.emulator import run_from_args

    return run_from_args(args)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="tensegrity-gym", description="Tensegrity robots with estimated-state observations."
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log at debug level")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_SubcommandParser)
    env_help = _env_help("env id")
    _add_training(sub, env_help)
    _add_bench(sub)
    _add_recordings(sub, env_help)
    _add_view(sub, env_help)
    _add_identify(sub)

    from hardware.link.emulator import add_arguments

    emu = sub.add_parser(
        "emulate", help="serve the simulated robot over the robot wire (Zenoh), in real time"
    )
    add_arguments(emu)
    emu.set_defaults(func=_emulate)
    return parser


def _add_ray(parser: argparse.ArgumentParser, what: str) -> None:
    """``--ray ADDRESS``: run ``what`` on a Ray cluster."""
    parser.add_argument(
        "--ray",
        default=None,
        metavar="ADDRESS",
        help=f"{what}, on the Ray cluster at ADDRESS (HOST:PORT of `ray start --head`, "
        "auto, or local: a Ray instance started here); needs pip install tensegrity-gym[ray]",
    )


def _add_training(sub: Any, env_help: str) -> None:
    """demo, train, evaluate and gait."""
    _add_demo(sub)
    _add_train(sub, env_help)
    _add_evaluate(sub)
    _add_gait(sub, env_help)


def _add_demo(sub: Any) -> None:
    demo = sub.add_parser(
        "demo",
        help="the main job: train PPO with the UKF in the loop (and on ground truth), "
        "evaluate, write the report",
    )
    demo.add_argument(
        "--timesteps", type=_positive_int, help="UKF training steps (default: the demo's budget)"
    )
    demo.add_argument(
        "--oracle-timesteps", type=_count,
        help="ground-truth training steps (0: skip; default: the demo's budget)",
    )  # fmt: skip
    demo.add_argument(
        "--episodes", type=_positive_int, default=5, help="evaluation episodes per row"
    )
    seeding = demo.add_mutually_exclusive_group()
    seeding.add_argument(
        "--seed", type=_count, default=0,
        help="seeds the training (the evaluation's episodes are the same for every seed)",
    )  # fmt: skip
    seeding.add_argument(
        "--seeds",
        type=_count,
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
    demo.set_defaults(func=_demo)


def _add_train(sub: Any, env_help: str) -> None:
    from agents.train import ALGORITHMS
    from tensegrity_gym.model.randomization import RANDOMIZATIONS
    from tensegrity_gym.model.registry import ESTIMATORS

    tr = sub.add_parser("train", help="train a policy with stable-baselines3")
    tr.add_argument("--env", default="tensegrity_gym/ThreeBarRoll-v0", help=env_help)
    tr.add_argument("--algo", default="ppo", choices=list(ALGORITHMS), help="algorithm")
    tr.add_argument("--estimator", default="ukf", choices=list(ESTIMATORS.names()),
                    help="what the policy's observations are estimated with")  # fmt: skip
    tr.add_argument("--timesteps", type=_positive_int, default=None, help="default: the config's")
    tr.add_argument("--seed", type=_count, default=0, help="seeds the envs and the algorithm")
    tr.add_argument(
        "--n-envs", type=_positive_int, default=None, help="workers; default: the config's"
    )
    tr.add_argument("--config", default=None, help="hyperparameter YAML (rl-zoo3 layout)")
    tr.add_argument(
        "--randomization", default=None, choices=sorted(RANDOMIZATIONS),
        help="train in worlds drawn from these ranges at each reset (default: none)",
    )  # fmt: skip
    tr.add_argument(
        "--residual-gait", type=_positive_float, default=None, metavar="SCALE",
        help="actions correct the robot's scripted gait, scaled by SCALE "
        "(gym.make(residual_gait=)); default: actions are the rest-length targets",
    )  # fmt: skip
    tr.add_argument(
        "--env-kwargs", type=_env_kwarg, nargs="+", action="extend", default=None,
        metavar="KEY:VALUE",
        help="more gym.make arguments for training, as rl-zoo3 takes them (e.g. the "
        "task's ctrl_cost:0.0); the run's config keeps them",
    )  # fmt: skip
    tr.add_argument(
        "--hyperparams", type=_hyperparam, nargs="+", action="extend", default=None,
        metavar="KEY:VALUE",
        help="hyperparameters put over the config's, as rl-zoo3 takes them (e.g. "
        "learning_rate:1e-4 policy_kwargs:\"dict(log_std_init=-2.0)\"); the run's config "
        "keeps them",
    )  # fmt: skip
    tr.add_argument("--out", required=True, help="folder for the run")
    tr.add_argument("--no-progress", action="store_true", help="no progress bar")
    _add_ray(tr, "step the envs on --workers Ray actors")
    tr.add_argument("--workers", type=_positive_int, default=None,
                    help="Ray actors sharing the --n-envs envs (default: one per CPU of the "
                    "cluster, at most --n-envs); with --ray only")  # fmt: skip
    tr.set_defaults(func=_train)


def _add_evaluate(sub: Any) -> None:
    from agents.evaluate import CONDITIONS, condition_names

    ev = sub.add_parser(
        "evaluate", help="evaluate trained policies under each estimator; write the report"
    )
    ev.add_argument("models", nargs="+", help="training run folders (from train)")
    ev.add_argument("--episodes", type=_positive_int, default=10, help="episodes per row")
    ev.add_argument(
        "--conditions",
        nargs="+",
        default=list(CONDITIONS),
        choices=condition_names(),
        help="estimators and worlds to evaluate under",
    )
    ev.add_argument("--seed", type=_count, default=1000, help="episode k uses seed + k")
    ev.add_argument("--out", required=True, help="folder for the report")
    _add_ray(ev, "run each episode as a Ray task")
    ev.set_defaults(func=_evaluate)


def _add_gait(sub: Any, env_help: str) -> None:
    from tensegrity_gym.model.registry import ESTIMATORS

    gait = sub.add_parser("gait", help="roll a robot with its scripted gait; plot the CoM")
    gait.add_argument("--env", default="tensegrity_gym/ThreeBarRoll-v0", help=env_help)
    gait.add_argument("--steps", type=_positive_int, default=300, help="control steps (10 Hz)")
    gait.add_argument("--seed", type=_count, default=0, help="the episode's seed")
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
    gait.set_defaults(func=_gait)


def _add_bench(sub: Any) -> None:
    bench = sub.add_parser("bench", help="measure env speed and memory; print JSON")
    bench.add_argument("--steps", type=_positive_int, default=2000, help="env steps timed per env")
    bench.add_argument(
        "--memory-steps",
        type=_count,
        default=100_000,
        help="env steps of the memory test (0: skip)",
    )
    bench.add_argument(
        "--estimation",
        action="store_true",
        help="also run the estimation study (papers/000 on SUPERball), the UKF's "
        "speed against filterpy's, the ICP tracker's figures and papers/002's table "
        "(the invariant EKF on the 1.45 m robot, beside the UKF)",
    )
    bench.add_argument(
        "--sim2real",
        action="store_true",
        help="also run the UKF in randomised worlds (none, mild, strong) and the "
        "identification of a 3-bar robot recorded 30 %% off its description",
    )
    bench.add_argument(
        "--bag-minutes",
        type=_non_negative_float,
        default=10.0,
        help="minutes of 3-bar recording whose reading and replay are timed (0: skip)",
    )
    bench.add_argument(
        "--link-steps",
        type=_count,
        default=300,
        help="10 Hz steps of the robot-link latency test against the emulator (0: skip)",
    )
    bench.add_argument(
        "--soak-minutes",
        type=_non_negative_float,
        default=0.0,
        help="minutes of emulated operation watched for memory and latency growth",
    )
    _add_ray(bench, "measure the Ray vec env (the JSON's ray) and run --estimation's jobs as tasks")
    bench.add_argument("--out", default=None, help="also write the JSON to this file")
    bench.set_defaults(func=_bench)


def _add_recordings(sub: Any, env_help: str) -> None:
    """record, estimate and calibrate."""
    from tensegrity_gym.model.registry import ESTIMATORS

    rec = sub.add_parser("record", help="run a policy and write each episode to a ROS 2 bag")
    rec.add_argument("--env", default="tensegrity_gym/ThreeBarRoll-v0", help=env_help)
    rec.add_argument(
        "--policy",
        default="scripted",
        help="scripted (the robot's face gait), random, or a training run folder (from train)",
    )
    rec.add_argument("--episodes", type=_positive_int, default=1, help="episodes (bags)")
    rec.add_argument("--steps", type=_positive_int, default=None, help="control steps per episode")
    rec.add_argument("--seed", type=_count, default=0, help="episode k uses seed + k")
    rec.add_argument("--estimator", default="ukf", choices=list(ESTIMATORS.names()),
                     help="the estimator run (and recorded) in the loop")  # fmt: skip
    rec.add_argument("--driver", default=None, help="a robot on the network: zenoh/tcp/HOST:PORT")
    rec.add_argument("--out", required=True, help="folder for the bags (episode_000, ...)")
    rec.add_argument("--markers", action=argparse.BooleanOptionalAction, default=True,
                     help="write /tf and /tensegrity/markers (what ROS viewers draw) at the "
                     "control rate")  # fmt: skip
    rec.set_defaults(func=_record)

    est = sub.add_parser(
        "estimate", help="run an estimator over a bag; write its trajectory, metrics, plots"
    )
    est.add_argument("bag", help="a bag, or a folder of bags (one per episode)")
    est.add_argument("--estimator", default="ukf", choices=list(ESTIMATORS.names()),
                     help="the estimator to run over the bag")  # fmt: skip
    est.add_argument("--out", required=True, help="folder for the results")
    est.add_argument(
        "--seed",
        type=_count,
        default=0,
        help="seed of the generator handed to the estimator (the ICP tracker's RANSAC draws "
        "from it; the UKF and the oracle are deterministic and draw nothing)",
    )
    est.add_argument(
        "--robot", default=None, help="robot preset or YAML, for a bag without a description"
    )
    est.add_argument(
        "--strict", action="store_true", help="stop at the first bad message instead of skipping"
    )
    est.add_argument("--no-progress", action="store_true", help="no progress bar")
    est.add_argument(
        "--calibration",
        default=None,
        help="a UWB calibration file (tensegrity-gym calibrate) to use instead of the bag's",
    )
    _add_ray(est, "run each bag as a Ray task (the bags on a path every node reads)")
    est.set_defaults(func=_estimate)

    cal = sub.add_parser(
        "calibrate",
        help="calibrate the UWB anchors and offsets from a recorded run of the robot moving",
    )
    cal.add_argument("bag", nargs="?", default=None, help="a bag of the robot moving")
    cal.add_argument(
        "--env", default=None, help=_env_help("or record a calibration run of this env id")
    )
    cal.add_argument("--seconds", type=_calibration_seconds, default=120.0,
                     help="length of that run (s)")  # fmt: skip
    cal.add_argument("--world-seed", type=_count, default=0, help="the simulated lab's seed")
    cal.add_argument("--robot", default=None, help="robot preset or YAML, for a bare bag")
    cal.add_argument("--out", required=True, help="the calibration file to write (YAML)")
    cal.set_defaults(func=_calibrate)


def _add_identify(sub: Any) -> None:
    from agents.identify import MAX_EVALUATIONS, MODELS, PARAMETERS

    ide = sub.add_parser(
        "identify",
        help="fit a robot's physical parameters to a recorded run (multiple shooting, CMA-ES)",
    )
    ide.add_argument("bag", help="a bag with commands, encoders and a trajectory")
    ide.add_argument("--out", required=True, help="the fitted robot description to write (YAML)")
    ide.add_argument(
        "--params", default="stiffness,damping,rest,friction,motor",
        help=f"comma-separated parameter groups, of {', '.join(sorted(PARAMETERS))} (mass "
        "only without stiffness and damping: the motion cannot tell them apart)",
    )  # fmt: skip
    ide.add_argument("--robot", default=None, help="start from this preset or YAML, not the bag's")
    ide.add_argument("--model", choices=sorted(MODELS), default="sim",
                     help="the simulator's physics, or the UKF's spring-mass model")  # fmt: skip
    ide.add_argument("--segment-seconds", type=_positive_float, default=2.0,
                     help="length of a segment (at least one control period)")  # fmt: skip
    ide.add_argument("--max-evaluations", type=_positive_int, default=MAX_EVALUATIONS,
                     help="the search's budget, in candidates scored on every IMU window "
                     "(half of it is spent first on a quarter of the windows, four "
                     "candidates to one)")  # fmt: skip
    ide.add_argument("--workers", type=_positive_int, default=None,
                     help="processes (default: one per core)")  # fmt: skip
    ide.add_argument("--seed", type=_count, default=0, help="seeds CMA-ES")
    ide.add_argument(
        "--imu-windows", type=_count, default=300,
        help="periods at most (spread over the bag) whose IMU readings the fit compares "
        "with the replay's, each replayed from its recorded start; 0: fit the node "
        "positions over the segments instead (damping then weakly determined)",
    )  # fmt: skip
    ide.set_defaults(func=_identify)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
    )
    try:
        return int(args.func(args))
    except KeyboardInterrupt:
        log.warning("interrupted")
        return 130
    except _user_errors() as err:
        if args.verbose:
            log.exception("%s failed", args.command)
        else:
            log.error("%s", _one_line(err))
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
