"""Evaluating policies under each estimator and under harder sensing: the sim-to-real gap
that estimation alone opens.

A condition is an estimator and a sensor suite. Every policy runs the same seeded
episodes under every condition; what is measured comes from the simulator's truth:
how far the CoM rolled toward the goal, whether it got one rod length there (success),
how many times the robot tipped onto a new base triangle (rolls), the estimator's CoM
error along the way, re-initialisations and simulator divergences.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from functools import partial
from typing import TYPE_CHECKING, Any, cast

import gymnasium as gym
import numpy as np
import yaml

import tensegrity_gym  # noqa: F401  (registers the ids)
from tensegrity_gym.envs.moves import MoveChoice, MovePolicy
from tensegrity_gym.model.description import (
    DEFAULT_GAIT,
    STEER_GAIT,
    RobotDescription,
    load_robot,
)
from tensegrity_gym.model.registry import ESTIMATORS, estimator_spec
from tensegrity_gym.tasks.gaits import FaceGait

if TYPE_CHECKING:
    from collections.abc import Callable, Mapping, Sequence
    from pathlib import Path

    from numpy.typing import NDArray

    from agents.training.cluster import Executor
    from tensegrity_gym.envs.tensegrity_env import TensegrityEnv

__all__ = [
    "BASELINES",
    "CONDITIONS",
    "GAIT_BASELINES",
    "GAIT_POLICY",
    "RANDOM_POLICY",
    "STEER_POLICY",
    "Condition",
    "EpisodeResult",
    "LoadedPolicy",
    "action_kwargs",
    "condition",
    "condition_names",
    "count_rolls",
    "evaluate_policies",
    "evaluate_policy",
    "gait_policy",
    "goal_reached",
    "load_policy",
    "random_policy",
]

log = logging.getLogger(__name__)

ACTION_KWARGS = ("residual_gait", "base_gait", "observe_base", "residual_deadband")
"""The ``gym.make`` arguments of a training run that say what its actions and
observations mean: its policy is evaluated with them. Its others (``train
--env-kwargs``: its task's reward, its terrain) shaped its training only: every policy
and baseline of an evaluation runs on the env id's own task and worlds, so that the
rows compare."""

RANDOM_POLICY = "random"
GAIT_POLICY = "scripted gait"
STEER_POLICY = "steering gait"
GAIT_BASELINES = {GAIT_POLICY: DEFAULT_GAIT, STEER_POLICY: STEER_GAIT}
"""The baselines' rows of the robot's scripted gaits, by the gait they run (a robot
without one has no such row)."""
BASELINES = (RANDOM_POLICY, *GAIT_BASELINES)
"""The names of the policies an evaluation sets beside the trained ones."""


def _more_dropout(d: RobotDescription) -> RobotDescription:
    uwb = replace(d.sensors.uwb, reject_fraction=(0.75, 0.9))
    return replace(d, sensors=replace(d.sensors, uwb=uwb))


def _half_the_anchors(d: RobotDescription) -> RobotDescription:
    uwb = replace(d.sensors.uwb, anchors=d.sensors.uwb.anchors[::2])
    return replace(d, sensors=replace(d.sensors, uwb=uwb))


def _noisier_imu(d: RobotDescription) -> RobotDescription:
    c = d.sensors.imu
    imu = replace(
        c,
        accel_noise=5 * c.accel_noise,
        gyro_noise=5 * c.gyro_noise,
        accel_bias=5 * c.accel_bias,
        gyro_bias=5 * c.gyro_bias,
        mag_noise=5 * c.mag_noise,
    )
    return replace(d, sensors=replace(d.sensors, imu=imu))


@dataclass(frozen=True)
class Condition:
    """An estimator and the sensors it works with."""

    name: str
    estimator: str
    sensing: Callable[[RobotDescription], RobotDescription] | None = None
    """Turns the robot's nominal sensor suite into this condition's; None: nominal."""
    about: str = ""
    calibration: str = "estimated"
    """The UWB calibration the estimator gets (``gym.make(..., calibration=)``)."""
    randomization: str | None = None
    """The simulated world departs from the description by these ranges
    (``gym.make(..., randomization=)``); the estimator keeps the description."""


CONDITIONS: dict[str, Condition] = {
    c.name: c
    for c in (
        Condition("oracle", "oracle", None, "ground truth"),
        Condition("ukf", "ukf", None, "the UKF on the nominal sensors, self-calibrated UWB"),
        Condition(
            "ukf_true_calibration",
            "ukf",
            None,
            "the UKF given the simulator's own UWB anchors and offsets",
            "true",
        ),
        Condition("ukf_dropout", "ukf", _more_dropout, "75-90 % of UWB packets lost"),
        Condition("ukf_4_anchors", "ukf", _half_the_anchors, "4 UWB anchors instead of 8"),
        Condition("ukf_imu_noise", "ukf", _noisier_imu, "IMU noise and biases x5"),
        Condition(
            "ukf_mild",
            "ukf",
            None,
            "the UKF in worlds drawn from the mild "
            "randomisation (the model and the robot part ways)",
            randomization="mild",
        ),
        Condition(
            "ukf_strong",
            "ukf",
            None,
            "the UKF in worlds drawn from the strong randomisation",
            randomization="strong",
        ),
        Condition(
            "oracle_strong",
            "oracle",
            None,
            "ground truth in the strong randomisation's "
            "worlds: what the policy loses to the dynamics alone",
            randomization="strong",
        ),
    )
}


def condition_names() -> list[str]:
    """Every condition :func:`condition` knows: :data:`CONDITIONS`, then the other
    registered estimators."""
    return [*CONDITIONS, *(n for n in ESTIMATORS.names() if n not in CONDITIONS)]


def condition(name: str) -> Condition:
    """A condition of :data:`CONDITIONS` by name, or any registered estimator on the
    nominal sensors (a lab's own estimator is evaluated as ``--conditions NAME``)."""
    if name in CONDITIONS:
        return CONDITIONS[name]
    if name in ESTIMATORS:
        return Condition(name, name, None, estimator_spec(name).summary or name)
    raise ValueError(f"unknown condition {name!r}; valid choices: {condition_names()}")


def count_rolls(node_z: NDArray[np.float64], hold: int = 3) -> int:
    """Net rolls: tips onto a new base triangle, rocking back not counted.

    The base is the set of the three lowest nodes, taken once it has held for ``hold``
    steps; a tip back onto the base before the current one undoes the last roll, so a
    robot rocking between two faces rolls at most once. Node heights (T, n).
    """
    faces = [frozenset(np.argsort(z, kind="stable")[:3].tolist()) for z in node_z]
    if not faces:
        return 0
    visited = [faces[0]]  # the bases rolled through, with back-and-forth removed
    candidate, run = None, 0
    for face in faces[1:]:
        if face == visited[-1]:
            candidate, run = None, 0
            continue
        run = run + 1 if face == candidate else 1
        candidate = face
        if run >= hold:
            if len(visited) > 1 and face == visited[-2]:
                visited.pop()  # rocked back
            else:
                visited.append(face)
            candidate, run = None, 0
    return len(visited) - 1


@dataclass
class EpisodeResult:
    progress: float
    """True CoM progress (m): along the goal heading (roll), or the approach to the goal
    points, each counted up to the step that reached it (goto); see
    :func:`true_progress`."""
    rolls: int
    success: bool
    """A go-to id: the true CoM came within the task's success radius of a goal in force
    (a goal reached in truth, whatever the estimate said); a rolling id: a progress of
    at least one rod length."""
    com_error_mean: float
    """Mean distance between estimated and true CoM (m)."""
    reinitialisations: int
    diverged: bool
    episode_return: float
    true_path: NDArray[np.float64] = field(repr=False)
    est_path: NDArray[np.float64] = field(repr=False)
    errors: NDArray[np.float64] = field(repr=False)
    seconds: float = float("nan")
    """Simulated seconds the episode lasted (steps times the control period)."""
    rod_length: float = float("nan")
    """The robot's mean rod length (m): its body length, the unit of its speed."""

    @property
    def speed(self) -> float:
        """Progress per second (m/s)."""
        return self.progress / self.seconds if self.seconds > 0 else float("nan")


def _no_reset(episode_seed: int) -> None:
    """A policy without state of its own across episodes."""


@dataclass
class LoadedPolicy:
    """A trained model with the observation normalisation it was trained with."""

    name: str
    env_id: str
    trained_on: str
    act: Callable[[NDArray[np.float32]], NDArray[np.float32]]
    new_episode: Callable[[int], None] = _no_reset
    """Called with the episode's seed before it starts: a policy that draws reseeds, so
    that an episode's actions depend on its seed alone, wherever and in whatever order
    the episodes run."""
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    """What its actions mean, as ``gym.make`` takes it (:data:`ACTION_KWARGS` of its
    training run's env): every condition's env is made with these."""
    saved: dict[str, bytes] | None = field(default=None, repr=False)
    """A trained policy's files (``model.zip``, ``config.yaml``, ``vecnormalize.pkl``):
    it is pickled (sent to a Ray worker) as these and loaded again there."""

    def __reduce_ex__(self, protocol: Any) -> Any:
        if self.saved is None:
            return super().__reduce_ex__(protocol)
        return _policy_from_files, (self.saved, self.name)


def action_kwargs(config: Mapping[str, Any]) -> dict[str, Any]:
    """The ``gym.make`` arguments of a training run's ``config.yaml`` (loaded) that its
    policy must run with (:data:`ACTION_KWARGS`)."""
    env_kwargs = config.get("env_kwargs") or {}
    return {k: env_kwargs[k] for k in ACTION_KWARGS if env_kwargs.get(k) is not None}


def _policy_from_files(saved: dict[str, bytes], name: str) -> LoadedPolicy:
    """:func:`load_policy` of a run folder's files (a pickled :class:`LoadedPolicy`)."""
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory(prefix="tensegrity-policy-") as folder:
        for file, content in saved.items():
            (Path(folder) / file).write_bytes(content)
        return load_policy(Path(folder), name)


def load_policy(run_dir: Path, name: str | None = None) -> LoadedPolicy:
    """A policy saved by :func:`agents.training.train.train` (``model.zip``, ``config.yaml`` and
    ``vecnormalize.pkl`` when it normalised); clear errors for a missing or foreign file."""
    import pickle

    from stable_baselines3 import PPO, SAC

    config_file = run_dir / "config.yaml"
    model_file = run_dir / "model.zip"
    if not model_file.exists() or not config_file.exists():
        raise ValueError(f"{run_dir}: not a training run (needs model.zip and config.yaml)")
    try:
        config = yaml.safe_load(config_file.read_text())
        env_id, algo, trained_on = config["env_id"], config["algo"], config["estimator"]
    except (yaml.YAMLError, KeyError, TypeError) as err:
        raise ValueError(f"{config_file}: not a training config: {err}") from None
    classes: dict[str, Any] = {"ppo": PPO, "sac": SAC}
    if algo not in classes:
        raise ValueError(f"{config_file}: unknown algorithm {algo!r}")
    try:
        model = classes[algo].load(model_file, device="cpu")
    except Exception as err:  # a corrupted zip fails in many ways inside SB3
        raise ValueError(f"{model_file}: cannot load a {algo} model: {err}") from None
    env_kwargs = config.get("env_kwargs") or {}
    actions = action_kwargs(config)
    normalise: Callable[[Any], Any] = lambda obs: obs  # noqa: E731
    stats_file = run_dir / "vecnormalize.pkl"
    if stats_file.exists():
        with stats_file.open("rb") as f:
            stats = pickle.load(f)
        stats.training = False
        normalise = stats.normalize_obs

    def predict(obs: NDArray[np.float32]) -> Any:
        return model.predict(normalise(obs), deterministic=True)[0]

    moves = (config.get("moves"), config.get("move_tempos"), config.get("move_ranks"))
    act, new_episode, shape = _acting(env_id, actions, moves, predict)
    if model.observation_space.shape != shape:
        raise ValueError(
            f"{model_file}: the model observes {model.observation_space.shape}, "
            f"but {env_id} gives {shape}: a model of another env"
        )
    files = [f for f in (model_file, config_file, stats_file) if f.exists()]
    saved = {f.name: f.read_bytes() for f in files}
    # The report says which worlds a policy trained in (gym.make's randomization).
    worlds = env_kwargs.get("randomization")
    default = f"trained on {trained_on}" + (f" in {worlds} worlds" if worlds else "")
    return LoadedPolicy(name or default, env_id, trained_on, act, new_episode,
                        env_kwargs=actions, saved=saved)  # fmt: skip


def _acting(
    env_id: str,
    actions: dict[str, Any],
    moves: tuple[str | None, list[list[int]] | None, int | None],
    predict: Callable[[NDArray[np.float32]], Any],
) -> tuple[Callable[[NDArray[np.float32]], NDArray[np.float32]], Callable[[int], None],
           tuple[int, ...] | None]:  # fmt: skip
    """A trained model's ``predict`` as the env's policy: the act, what it does before
    an episode, and the observation shape the model must have. With ``moves`` (a run of
    ``train --moves``: the gait's name, the tempos and the ranks), the model picks among the
    steering gait's moves (and tempos) as each period begins
    (:class:`~tensegrity_gym.envs.moves.MovePolicy`) and the gait commands the steps."""
    env = gym.make(env_id, estimator="oracle", **actions)
    try:
        gait, tempos, ranks = moves
        if gait is None:
            shape = env.observation_space.shape

            def act(obs: NDArray[np.float32]) -> NDArray[np.float32]:
                return np.asarray(predict(obs), dtype=np.float32)

            return act, _no_reset, shape
        chosen = MoveChoice(env, gait, tempos, ranks)
        policy = MovePolicy(chosen.gait, lambda seen: int(predict(seen)), tempos, ranks)
        return policy, policy.reset, chosen.observation_space.shape
    finally:
        env.close()


class _RandomActions:
    """Uniform actions in [low, high], from a generator drawn anew for each episode from
    (the policy's seed, the episode's seed)."""

    def __init__(self, low: NDArray[np.float32], high: NDArray[np.float32], seed: int) -> None:
        self.low, self.high, self.seed = low, high, seed
        self.rng = np.random.default_rng(seed)

    def new_episode(self, episode_seed: int) -> None:
        self.rng = np.random.default_rng([self.seed, episode_seed])

    def __call__(self, obs: NDArray[np.float32]) -> NDArray[np.float32]:
        return self.rng.uniform(self.low, self.high).astype(np.float32)


def random_policy(env_id: str, seed: int) -> LoadedPolicy:
    """Uniform random actions, each episode's from a generator seeded with ``seed`` and
    the episode's seed."""
    env = gym.make(env_id, estimator="oracle")
    low, high = env.action_space.low, env.action_space.high  # type: ignore[attr-defined]
    env.close()
    actions = _RandomActions(low, high, seed)
    return LoadedPolicy(RANDOM_POLICY, env_id, "-", actions, actions.new_episode)


def gait_policy(env_id: str, name: str = GAIT_POLICY) -> LoadedPolicy | None:
    """A scripted face gait of the robot (:class:`FaceGait`; ``name`` is a key of
    :data:`GAIT_BASELINES`: the ``"forward"`` gait, or the ``"steer"`` gait that rolls
    toward the goal) acting on the estimates as a policy would; None for a robot
    without that gait."""
    env = gym.make(env_id, estimator="oracle")
    inner = cast("TensegrityEnv", env.unwrapped)
    try:
        gait = FaceGait(inner.backend.description, inner.task, gait=GAIT_BASELINES[name])
    except ValueError:
        return None
    finally:
        env.close()
    return LoadedPolicy(name, env_id, "-", gait, lambda _seed: gait.reset())


MEASURED_TASKS = ("roll", "goto")
"""The tasks whose progress :func:`true_progress` measures."""


def true_progress(
    true: NDArray[np.float64],
    heading: NDArray[np.float64] | None,
    goals: NDArray[np.float64] | None = None,
) -> float:
    """The true CoM's progress (m) over an episode, ``true`` (T + 1, 3) its positions:
    toward goal points where ``goals`` (T, 2) gives the one in force at each step (the
    step that reaches a goal counts toward it, the next toward the next: a go-to task's
    goals one after another), else its displacement along ``heading`` (2,)."""
    if goals is not None:
        before = np.linalg.norm(goals - true[:-1, :2], axis=1)
        after = np.linalg.norm(goals - true[1:, :2], axis=1)
        return float(np.sum(before - after))
    if heading is None:
        raise ValueError("true_progress: give the goal heading or the goals")
    return float((true[-1, :2] - true[0, :2]) @ heading)


def goal_reached(true: NDArray[np.float64], goals: NDArray[np.float64], radius: float) -> bool:
    """Whether the true CoM, ``true`` (T + 1, 3), came within ``radius`` (m) of the goal
    in force, ``goals`` (T, 2) (the one before each step), after some step."""
    if len(goals) == 0:
        return False
    return bool(np.min(np.linalg.norm(goals - true[1:, :2], axis=1)) <= radius)


def run_episode(env: gym.Env[Any, Any], act: Callable[..., Any], seed: int) -> EpisodeResult:
    inner = cast("TensegrityEnv", env.unwrapped)
    d = inner.backend.description
    obs, info = env.reset(seed=seed)
    # A rolling id's task: the goal heading drawn (or fixed) at reset; a go-to id's: the
    # goal point in force before each step (info["goal"]).
    heading = getattr(inner.task, "direction", None)
    goals: list[Any] | None = [] if "goal" in info else None
    true_path, est_path, node_z = [info["com_true"]], [info["com_estimate"]], []
    truth = inner.backend.ground_truth()
    assert truth is not None
    node_z.append(truth.node_positions[:, 2])
    total, reinit, diverged = 0.0, 0, False
    done = False
    while not done:
        goal_before = info.get("goal")
        obs, reward, terminated, truncated, info = env.step(act(obs))
        total += float(reward)
        reinit += int(info["estimator_reinitialised"])
        if info["sim_diverged"]:
            diverged = True
            break
        if goals is not None:
            goals.append(goal_before)
        true_path.append(info["com_true"])
        est_path.append(info["com_estimate"])
        truth = inner.backend.ground_truth()
        assert truth is not None
        node_z.append(truth.node_positions[:, 2])
        done = terminated or truncated
    true = np.array(true_path)
    est = np.array(est_path)
    goal_points = None if goals is None else np.array(goals)
    progress = true_progress(true, heading, goal_points)
    errors = np.linalg.norm(est - true, axis=-1)
    radius = getattr(inner.task, "success_radius", None)
    if goal_points is not None and radius is not None:
        success = goal_reached(true, goal_points, radius)
    else:
        success = progress >= d.characteristic_length
    return EpisodeResult(
        progress=progress,
        rolls=count_rolls(np.array(node_z)),
        success=success,
        com_error_mean=float(errors.mean()),
        reinitialisations=reinit,
        diverged=diverged,
        episode_return=total,
        true_path=true,
        est_path=est,
        errors=errors,
        seconds=(len(true) - 1) * inner.backend.control_period,
        rod_length=d.characteristic_length,
    )


def evaluate_policy(
    policy: LoadedPolicy,
    condition: Condition,
    episodes: int,
    seed: int = 1000,
    executor: Executor | None = None,
) -> list[EpisodeResult]:
    """``episodes`` episodes of ``policy`` under ``condition``, seeds ``seed``, ``seed+1``...
    (:func:`evaluate_policies` of the one policy and condition)."""
    results = evaluate_policies([policy], [condition], episodes, seed, executor)
    return results[policy.name][condition.name]


def evaluate_policies(
    policies: Sequence[LoadedPolicy],
    conditions: Sequence[Condition],
    episodes: int,
    seed: int = 1000,
    executor: Executor | None = None,
    engine: str | None = None,
) -> dict[str, dict[str, list[EpisodeResult]]]:
    """Every policy under every condition, ``episodes`` episodes each with seeds ``seed``,
    ``seed+1``...: ``results[policy name][condition name]``, simulated by ``engine``
    (None: the default physics engine). Each episode is a job of
    ``executor`` (default: here, one after the other; an
    :class:`agents.training.cluster.RayExecutor`
    runs them as Ray tasks, with the same results: an episode depends on its seed alone)."""
    for policy in policies:
        made = gym.spec(policy.env_id).kwargs
        task = made.get("task", "roll")
        if task not in MEASURED_TASKS:
            raise ValueError(
                f"{policy.env_id}: evaluate measures progress along a goal heading (the "
                f"'roll' task) or toward goal points ('goto'); it does not evaluate the "
                f"{task!r} task"
            )
        _check_robot(policy.env_id, made.get("robot", "three_bar"), conditions)
    from agents.training.cluster import LocalExecutor

    jobs = [
        (p, c, seed + k)
        for p in range(len(policies))
        for c in range(len(conditions))
        for k in range(episodes)
    ]
    run = partial(_episode, tuple(policies), tuple(conditions), engine)
    try:
        done = (executor or LocalExecutor()).map(run, jobs)
    finally:
        _release_env()
    results: dict[str, dict[str, list[EpisodeResult]]] = {
        p.name: {c.name: [] for c in conditions} for p in policies
    }
    for (p, c, _), result in zip(jobs, done, strict=True):
        results[policies[p].name][conditions[c].name].append(result)
    return results


def _check_robot(env_id: str, robot: Any, conditions: Sequence[Condition]) -> None:
    """Refuse, before any episode runs, a condition whose estimator cannot run on the
    robot of ``env_id`` (``robot``: its preset name, YAML path or description)."""
    description = robot if isinstance(robot, RobotDescription) else load_robot(robot)
    for c in conditions:
        missing = estimator_spec(c.estimator).missing(None, description)
        if missing is not None:
            raise ValueError(f"{env_id}: condition {c.name!r}: {missing}")


_ENV: dict[tuple[Any, ...], gym.Env[Any, Any]] = {}
"""The env of the last (env id, condition, action arguments) this process ran an episode
under: the next episodes under the same reuse it (an episode depends on its seed alone)."""


def _condition_env(
    env_id: str, condition: Condition, env_kwargs: dict[str, Any], engine: str | None = None
) -> gym.Env[Any, Any]:
    """The env of ``env_id`` under ``condition`` whose actions mean what ``env_kwargs``
    (:attr:`LoadedPolicy.env_kwargs`) says, on ``engine`` (None: the default), made once
    per process and condition."""
    key = (env_id, condition, tuple(sorted(env_kwargs.items())), engine)
    if key not in _ENV:
        _release_env()
        robot = gym.spec(env_id).kwargs.get("robot", "three_bar")
        description = load_robot(robot)
        if condition.sensing is not None:
            description = condition.sensing(description)
        world: dict[str, Any] = {} if engine is None else {"engine": engine}
        _ENV[key] = gym.make(
            env_id,
            robot=description,
            estimator=condition.estimator,
            calibration=condition.calibration,
            randomization=condition.randomization,
            **env_kwargs,
            **world,
        )
    return _ENV[key]


def _release_env() -> None:
    """Close this process's cached env (:func:`_condition_env`)."""
    for env in _ENV.values():
        env.close()
    _ENV.clear()


def _episode(
    policies: Sequence[LoadedPolicy],
    conditions: Sequence[Condition],
    engine: str | None,
    job: tuple[int, int, int],
) -> EpisodeResult:
    """One episode, ``job`` = (policy index, condition index, seed): the job that
    :func:`evaluate_policies` maps, here or on a Ray worker."""
    policy, condition = policies[job[0]], conditions[job[1]]
    env = _condition_env(policy.env_id, condition, policy.env_kwargs, engine)
    policy.new_episode(job[2])
    try:
        return run_episode(env, policy.act, job[2])
    except BaseException:
        _release_env()
        raise


def _distance(path: NDArray[np.float64]) -> float:
    """Straight-line distance (m) from a CoM path's start to its end on the ground,
    path (T, 3)."""
    return float(np.linalg.norm(path[-1, :2] - path[0, :2]))


def summarise(results: Sequence[EpisodeResult]) -> dict[str, Any]:
    progress = np.array([r.progress for r in results])
    return {
        "episodes": len(results),
        "progress_mean_m": round(float(progress.mean()), 3),
        "progress_std_m": round(float(progress.std()), 3),
        # How far the robot rolled in whatever direction: the scripted gait cannot aim,
        # so this is its progress had the goal lain its way.
        "distance_mean_m": round(float(np.mean([_distance(r.true_path) for r in results])), 3),
        "success_rate": round(float(np.mean([r.success for r in results])), 3),
        "speed_m_per_s": round(float(np.mean([r.speed for r in results])), 4),
        # Rod lengths per second: speeds of robots of any size side by side.
        "speed_rod_lengths_per_s": round(
            float(np.mean([r.speed / r.rod_length for r in results])), 4
        ),
        "rolls_per_episode": round(float(np.mean([r.rolls for r in results])), 2),
        "com_error_mean_m": round(float(np.mean([r.com_error_mean for r in results])), 4),
        "reinitialisations": int(sum(r.reinitialisations for r in results)),
        "divergences": int(sum(r.diverged for r in results)),
        "return_mean": round(float(np.mean([r.episode_return for r in results])), 2),
    }
