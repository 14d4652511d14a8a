"""Training rolling policies with stable-baselines3, the estimator in the loop.

Hyperparameters come from ``agents/training/configs/<algo>.yml`` (rl-zoo3's layout: one mapping
per env id; an id of another task without an entry of its own, say ``ThreeBarGoTo-v0``,
takes its robot's rolling entry, ``ThreeBarRoll-v0``). Each worker builds its own env,
UKF included, from the env id; nothing with a simulator or filter in it is pickled. The
run folder gets the final model and its normalisation statistics, checkpoints, Monitor
logs, TensorBoard logs, and the exact configuration it ran with (``config.yaml``).
"""

from __future__ import annotations

import ast
import inspect
import logging
import os
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

from agents.training.hyperparams import check_hyperparams, check_rollout
from tensegrity_gym.model.registry import estimator_spec

if TYPE_CHECKING:
    from collections.abc import Collection, Mapping, Sequence

    from stable_baselines3.common.base_class import BaseAlgorithm
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.vec_env import VecEnv

    from agents.training.guards import TrainingDivergedError

__all__ = [
    "ALGORITHMS",
    "CONFIG_DIR",
    "Checkpoint",
    "RunOptions",
    "TrainConfig",
    "config_entry",
    "load_hyperparams",
    "make_training_env",
    "parse_config_value",
    "run_training",
    "train",
]

log = logging.getLogger(__name__)

CONFIG_DIR = Path(__file__).parent / "configs"
ALGORITHMS = ("ppo", "sac")
# Keys of a config entry that are not arguments of the algorithm (rl-zoo3's meaning).
_RUN_KEYS = {"n_envs", "n_timesteps", "policy", "normalize", "policy_kwargs"}
# Arguments the trainer sets itself.
_OWN_ARGS = {
    "self",
    "env",
    "policy",
    "verbose",
    "seed",
    "device",
    "tensorboard_log",
    "_init_setup_model",
    "policy_kwargs",
}


def _algorithm_class(algo: str) -> type[BaseAlgorithm]:
    import stable_baselines3 as sb3

    classes: dict[str, type[BaseAlgorithm]] = {"ppo": sb3.PPO, "sac": sb3.SAC}
    if algo not in classes:
        raise ValueError(f"unknown algorithm {algo!r}; valid choices: {list(ALGORITHMS)}")
    return classes[algo]


def parse_config_value(text: str, where: str) -> Any:
    """An rl-zoo3 string value such as ``"dict(net_arch=[64, 64], log_std_init=-0.5)"``,
    read without ``eval``: ``dict(...)`` calls, lists, tuples and literals only."""

    def convert(node: ast.AST) -> Any:
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name):
            if node.func.id == "dict" and not node.args:
                return {kw.arg: convert(kw.value) for kw in node.keywords if kw.arg}
        if isinstance(node, (ast.List, ast.Tuple)):  # lists: the config is written back as YAML
            return [convert(e) for e in node.elts]
        if isinstance(node, ast.Dict):
            pairs = zip(node.keys, node.values, strict=True)
            return {convert(k): convert(v) for k, v in pairs if k is not None}
        try:
            return ast.literal_eval(node)
        except ValueError:
            raise ValueError(
                f"{where}: {ast.unparse(node)!r} is not a literal or dict(...) call"
            ) from None

    try:
        tree = ast.parse(text, mode="eval")
    except SyntaxError as err:
        raise ValueError(f"{where}: {text!r} is not an expression: {err.msg}") from None
    return convert(tree.body)


def config_entry(entries: Collection[str], env_id: str) -> str | None:
    """The config entry that holds ``env_id``'s hyperparameters: its own, else (for an id
    of another task) that of the same robot's rolling id through the same driver; None
    if neither is written."""
    if env_id in entries:
        return env_id
    import gymnasium as gym

    import tensegrity_gym  # noqa: F401  (registers the ids)

    if env_id not in gym.registry:
        return None
    own = gym.spec(env_id).kwargs
    rolling = {**own, "task": "roll"}
    for entry in sorted(entries):
        if entry in gym.registry and gym.spec(entry).kwargs == rolling:
            log.info("no %s entry in the config: %s's hyperparameters are used", env_id, entry)
            return entry
    return None


def load_hyperparams(
    algo: str,
    env_id: str,
    config_file: Path | None = None,
    overrides: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """The checked hyperparameters of ``env_id`` for ``algo`` (see :func:`config_entry`),
    with ``overrides`` (rl-zoo3's ``--hyperparams``) put over the config's; unknown keys
    fail at once with the list of valid ones."""
    cls = _algorithm_class(algo)
    path = config_file or CONFIG_DIR / f"{algo}.yml"
    try:
        doc = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as err:
        raise ValueError(f"cannot read the config {path}: {err}") from None
    entry = config_entry(doc, env_id) if isinstance(doc, dict) else None
    if entry is None:
        ids = sorted(doc) if isinstance(doc, dict) else []
        raise ValueError(
            f"{path}: no entry for {env_id!r} (nor its robot's Roll id); entries: {ids}"
        )
    valid = _RUN_KEYS | (set(inspect.signature(cls.__init__).parameters) - _OWN_ARGS)
    # the entry that holds the values, which for another task's id is not env_id's own
    given = {f"{path}: {entry}": dict(doc[entry]), "--hyperparams": dict(overrides or {})}
    where: dict[str, str] = {}
    for source, entries in given.items():
        unknown = sorted(set(entries) - valid)
        if unknown:
            raise ValueError(
                f"{source}: unknown keys {unknown} for {algo}; valid keys: {sorted(valid)}"
            )
        for key in ("normalize", "policy_kwargs"):
            if isinstance(entries.get(key), str):
                entries[key] = parse_config_value(entries[key], f"{source}.{key}")
        where |= dict.fromkeys(entries, source)
    # only the values the run uses: a config's, where --hyperparams replaces it, is not
    return check_hyperparams(algo, {**given[f"{path}: {entry}"], **given["--hyperparams"]}, where)


@dataclass(frozen=True)
class TrainConfig:
    """Everything a training run depends on; written to ``config.yaml``."""

    env_id: str
    algo: str
    estimator: str
    timesteps: int
    seed: int
    n_envs: int
    hyperparams: dict[str, Any] = field(default_factory=dict)
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    moves: str | None = None
    """A steering gait's name: the policy picks among its moves, a step a gait period
    (:class:`~tensegrity_gym.envs.moves.MoveChoice`); None: the env's own actions."""
    move_tempos: list[list[int]] | None = None
    """With ``moves``: the (hold, settle) control steps a period may also take, beside
    the gait's own (MoveChoice's ``tempos``); None: the gait's own alone."""
    move_ranks: int | None = None
    """With ``moves``: how many of the gait's ranks a choice picks among (MoveChoice's
    ``ranks``); None: all."""


def qualified_id(env_id: str) -> str:
    """``env_id`` as ``module:id``: a fresh worker interpreter registers the ids by
    importing the module it names."""
    return env_id if ":" in env_id else f"tensegrity_gym:{env_id}"


def check_env_kwargs(env_id: str, env_kwargs: dict[str, Any]) -> None:
    """ValueError naming each of ``env_kwargs`` that ``gym.make(env_id)`` does not take
    (neither gymnasium's, ``make_env``'s nor its task's), before a worker starts; the values are
    checked where the env is made."""
    import gymnasium as gym

    from tensegrity_gym.envs.factory import make_env
    from tensegrity_gym.model.registry import task_spec

    named = sorted({"robot", "task"} & set(env_kwargs))
    if named:  # an evaluation would make the id's own, and never know
        raise ValueError(f"env_kwargs {named}: the env id names the robot and the task")
    own = set(inspect.signature(make_env).parameters) - {"task_arguments"}
    own |= set(inspect.signature(gym.make).parameters) - {"id", "kwargs"}
    task = task_spec(gym.spec(env_id).kwargs.get("task", "roll"))
    task.check(set(env_kwargs) - own)


def make_training_env(
    env_id: str,
    n_envs: int,
    seed: int,
    env_kwargs: dict[str, Any],
    monitor_dir: Path | None,
    workers: int | None = None,
    moves: str | None = None,
    move_tempos: list[list[int]] | None = None,
    move_ranks: int | None = None,
) -> VecEnv:
    """``n_envs`` Monitor-wrapped envs, in subprocesses where there is more than one core;
    with ``workers``, on that many Ray actors of the connected cluster
    (:class:`agents.training.cluster.vec_env.RayVecEnv`), the Monitor log kept here;
    with ``moves``, each under :class:`~tensegrity_gym.envs.moves.MoveChoice` of that
    gait, ``move_tempos`` and ``move_ranks`` (not on Ray)."""
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecMonitor

    from tensegrity_gym.envs.moves import MoveChoice

    qualified = qualified_id(env_id)
    if workers is not None:
        if moves is not None:
            raise ValueError("train: --moves runs on this machine's envs, not on Ray workers")
        from agents.training.cluster.vec_env import RayVecEnv

        venv = RayVecEnv(qualified, n_envs, seed, env_kwargs, workers=workers)
        if monitor_dir is not None:
            monitor_dir.mkdir(parents=True, exist_ok=True)
        log.info("%d envs on %d Ray workers", n_envs, workers)
        return VecMonitor(venv, str(monitor_dir / "ray") if monitor_dir is not None else None)
    use_processes = n_envs > 1 and (os.cpu_count() or 1) > 1
    if use_processes:  # one reset here first: a UWB calibration run is then cached for all
        import gymnasium as gym

        first = gym.make(qualified, **env_kwargs)
        first.reset(seed=seed)
        first.close()
    return make_vec_env(
        qualified,
        n_envs=n_envs,
        seed=seed,
        env_kwargs=env_kwargs,
        monitor_dir=str(monitor_dir) if monitor_dir is not None else None,
        vec_env_cls=SubprocVecEnv if use_processes else DummyVecEnv,
        wrapper_class=None if moves is None else MoveChoice,
        wrapper_kwargs=None
        if moves is None
        else {"gait": moves, "tempos": move_tempos, "ranks": move_ranks},
    )


def train(
    env_id: str,
    algo: str,
    estimator: str,
    out: Path,
    *,
    timesteps: int | None = None,
    seed: int = 0,
    n_envs: int | None = None,
    config_file: Path | None = None,
    hyperparams: Mapping[str, Any] | None = None,
    checkpoint_every: int = 50_000,
    progress_bar: bool = True,
    env_kwargs: dict[str, Any] | None = None,
    callbacks: Sequence[BaseCallback] = (),
    ray_address: str | None = None,
    workers: int | None = None,
    moves: str | None = None,
    move_tempos: Sequence[Sequence[int]] | None = None,
    move_ranks: int | None = None,
) -> Path:
    """Train, and return the path of the saved model (``out/model.zip``).

    ``out`` receives ``model.zip`` and ``vecnormalize.pkl`` (when the config normalises),
    ``config.yaml``, ``checkpoints/``, ``monitor/`` and ``tb/`` (TensorBoard);
    ``callbacks`` run beside the checkpointing; ``hyperparams`` are put over the config's
    (``config.yaml`` keeps the result), and a value out of its range
    (:data:`agents.training.hyperparams.VALID`) is a ValueError before any env is made. Ctrl-C
    saves the model reached so far as ``out/model.zip`` (``config.yaml`` then says
    ``interrupted: true``) and re-raises.

    A checkpoint is saved after the first update past each ``checkpoint_every`` steps,
    where the model is finite. A non-finite loss, weight or statistic stops the run
    with :class:`agents.training.guards.TrainingDivergedError` (a ValueError); ``model.zip`` is
    then the last good checkpoint, or there is none (``config.yaml`` says which in
    ``diverged``). No file is left half-written.

    ``ray_address`` (``HOST:PORT``, ``auto`` or ``local``) steps the ``n_envs`` envs on
    ``workers`` Ray actors of that cluster (default: one per CPU of the cluster, at most
    ``n_envs``); the learner and the run folder stay in this process.

    ``moves`` (a steering gait's name, PPO only): the policy picks among the gait's
    moves of the support face, a step a gait period
    (:class:`~tensegrity_gym.envs.moves.MoveChoice`): ``timesteps`` and the
    hyperparameters' step counts then count those choices. ``move_tempos`` ((hold,
    settle) control steps) lets a choice set its period's tempo too; ``move_ranks``
    limits it to the gait's first ranks (1: the tempo alone).
    """
    if workers is not None and ray_address is None:
        raise ValueError("workers are Ray actors: give the cluster's address (--ray)")
    config = _checked_config(
        env_id, algo, estimator, timesteps, seed, n_envs, config_file, hyperparams, env_kwargs
    )
    if (move_tempos is not None or move_ranks is not None) and moves is None:
        raise ValueError("train: --move-tempos and --move-ranks set the choice of --moves: "
                         "give --moves too")  # fmt: skip
    if moves is not None:
        tempos = None if move_tempos is None else [list(t) for t in move_tempos]
        config = replace(config, moves=moves, move_tempos=tempos, move_ranks=move_ranks)
        check_moves(config)
        if config.hyperparams.get("use_sde"):  # the shipped configs' continuous exploration
            log.info("--moves: gSDE explores continuous actions only; off for this run")
            params = {k: v for k, v in config.hyperparams.items() if k != "sde_sample_freq"}
            config = replace(config, hyperparams=params | {"use_sde": False})
    if workers is not None and workers < 1:
        raise ValueError(f"workers ({workers}) must be positive")
    return run_training(config, out, RunOptions(checkpoint_every, progress_bar, callbacks),
                        ray_address, workers)  # fmt: skip


@dataclass(frozen=True)
class RunOptions:
    """How a run goes, beside what it trains (:class:`TrainConfig`)."""

    checkpoint_every: int = 50_000
    progress_bar: bool = True
    callbacks: Sequence[BaseCallback] = ()
    start: Checkpoint | None = None
    """Go on from this checkpoint (a resumed run); None: a new model."""


@dataclass(frozen=True)
class Checkpoint:
    """A model saved during a run, and what it needs to go on."""

    steps: int
    model: Path
    stats: Path | None
    """The VecNormalize statistics saved with it; None where the run does not normalise."""


def run_training(
    config: TrainConfig,
    out: Path,
    options: RunOptions,
    ray_address: str | None = None,
    workers: int | None = None,
) -> Path:
    """Run ``config`` into ``out``, here or on ``workers`` actors of the Ray cluster at
    ``ray_address``; the path of the saved model."""
    if ray_address is None:
        return _run(config, out, options, None)
    from agents.training.cluster import cluster_session, require_ray

    with cluster_session(ray_address):
        if workers is None:
            cpus = int(require_ray().cluster_resources().get("CPU", 1))
            workers = max(1, min(config.n_envs, cpus))
        return _run(config, out, options, workers)


def _checked_config(
    env_id: str,
    algo: str,
    estimator: str,
    timesteps: int | None,
    seed: int,
    n_envs: int | None,
    config_file: Path | None,
    hyperparams: Mapping[str, Any] | None,
    env_kwargs: dict[str, Any] | None,
) -> TrainConfig:
    """What :func:`train` runs, every part checked before any env is made: the env id,
    the estimator, the env's arguments, the hyperparameters by their ranges."""
    import gymnasium as gym

    import tensegrity_gym  # registers the ids

    estimator_spec(estimator)  # an unknown name is refused before anything starts
    if env_id not in gym.registry:
        ids = tensegrity_gym.env_ids(hardware=None)
        raise ValueError(f"unknown env id {env_id!r}; valid choices: {ids}")
    check_env_kwargs(env_id, env_kwargs or {})
    params = load_hyperparams(algo, env_id, config_file, hyperparams)
    total = int(timesteps if timesteps is not None else params.pop("n_timesteps", 100_000))
    params.pop("n_timesteps", None)
    envs = int(n_envs if n_envs is not None else params.pop("n_envs", 1))
    params.pop("n_envs", None)
    if total < 1 or envs < 1:
        raise ValueError(f"timesteps ({total}) and n_envs ({envs}) must be positive")
    if algo == "ppo":  # its minibatches are drawn from one rollout of n_steps * n_envs
        ppo = _defaults(algo) | params
        check_rollout(ppo["n_steps"], envs, ppo["batch_size"], ppo["normalize_advantage"])
    kwargs = {"estimator": estimator, **(env_kwargs or {})}
    return TrainConfig(env_id, algo, estimator, total, seed, envs, dict(params), kwargs)


def check_moves(config: TrainConfig) -> None:
    """ValueError in one line where ``config``'s ``moves`` (and ``move_tempos``) cannot
    be trained on: PPO, absolute actions, a gait of the id's robot with several moves a
    face, tempos the gait can run."""
    import gymnasium as gym

    from tensegrity_gym.envs.moves import MoveChoice

    if config.algo != "ppo":
        raise ValueError(
            f"train: --moves makes the action a choice among moves, which {config.algo} "
            "cannot take (a discrete action): use --algo ppo"
        )
    if config.env_kwargs.get("residual_gait") is not None:
        raise ValueError("train: --moves picks the gait's own moves; leave out --residual-gait")
    env = gym.make(config.env_id, estimator="oracle")
    try:
        MoveChoice(env, str(config.moves), config.move_tempos, config.move_ranks)
    except (ValueError, KeyError) as err:
        raise ValueError(f"train: --moves {config.moves}: {err}") from None
    finally:
        env.close()


def _defaults(algo: str) -> dict[str, Any]:
    """The algorithm's own values of the hyperparameters a config leaves out."""
    parameters = inspect.signature(_algorithm_class(algo).__init__).parameters.values()
    return {p.name: p.default for p in parameters if p.default is not inspect.Parameter.empty}


def _run(config: TrainConfig, out: Path, options: RunOptions, workers: int | None) -> Path:
    """:func:`train`'s run, its arguments checked; ``workers``: Ray actors, or None."""
    import torch

    from agents.training.guards import FiniteGuard

    params = dict(config.hyperparams)
    out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(1)  # small networks: threads only contend with the env workers
    venv = make_training_env(config.env_id, config.n_envs, config.seed, config.env_kwargs,
                             out / "monitor", workers, config.moves,
                             config.move_tempos, config.move_ranks)  # fmt: skip
    venv = _normalized(venv, params, options.start)
    start = options.start
    model = _make_model(config, params, venv, out) if start is None else _load_model(
        config, start, venv, out)  # fmt: skip
    kept = None if start is None else (start.steps, start.model, start.stats)
    guard = FiniteGuard(out, options.checkpoint_every, kept)  # saves the finite checkpoints
    extra = [] if workers is None else [_restart_logger(venv)]
    interrupted = False
    failure: TrainingDivergedError | None = None
    # Written first, so that a run killed outright (no finally) can be resumed.
    _write_record(out, config, start, {"completed_timesteps": int(model.num_timesteps),
                                       "finished": False})  # fmt: skip
    try:
        model.learn(
            config.timesteps - (0 if start is None else start.steps),
            callback=[guard, *extra, *options.callbacks],
            progress_bar=options.progress_bar,
            tb_log_name=config.algo,
            reset_num_timesteps=start is None,
        )
    except KeyboardInterrupt:
        interrupted = True
        log.warning("interrupted after %d steps: saving the model reached", model.num_timesteps)
    except ValueError as err:  # the guard's TrainingDivergedError, or torch refusing a NaN
        failure = guard.divergence(model, err)
        if failure is None:
            raise
    finally:
        failure = guard.finish(model, failure)  # model.zip: never one with a NaN in it
        record = {
            "completed_timesteps": int(model.num_timesteps),
            "finished": True,
            "interrupted": interrupted,
            "diverged": None if failure is None else str(failure),
        }
        if workers is not None:
            record |= {"ray_workers": workers, "worker_restarts": _restarts(venv)}
        _write_record(out, config, start, record)
        venv.close()
    if failure is not None:
        raise failure
    if interrupted:
        raise KeyboardInterrupt
    return out / "model.zip"


def _write_record(
    out: Path, config: TrainConfig, start: Checkpoint | None, state: dict[str, Any]
) -> None:
    """``out/config.yaml``: ``config``, the checkpoint the run went on from, ``state``."""
    from agents.training.guards import replace_atomically

    record = asdict(config) | state
    if start is not None:
        record["resumed_from"] = str(start.model)
    text = yaml.safe_dump(record, sort_keys=False)
    replace_atomically(out / "config.yaml", lambda path: path.write_text(text))


def _normalized(venv: VecEnv, params: dict[str, Any], start: Checkpoint | None) -> VecEnv:
    """``venv`` under VecNormalize where the config normalises (``params``' ``normalize``,
    taken out of them), with ``start``'s statistics where a run goes on."""
    from stable_baselines3.common.vec_env import VecNormalize

    normalize = params.pop("normalize", False)
    if not normalize:
        return venv
    if start is not None and start.stats is not None:
        return VecNormalize.load(str(start.stats), venv)
    norm_kwargs = normalize if isinstance(normalize, dict) else {}
    return VecNormalize(venv, gamma=params.get("gamma", 0.99), **norm_kwargs)


def _tensorboard(out: Path) -> str | None:
    """``out/tb``, where TensorBoard is installed."""
    try:
        import tensorboard  # noqa: F401
    except ImportError:
        log.warning("tensorboard is not installed: no TensorBoard logs (pip install tensorboard)")
        return None
    return str(out / "tb")


def _load_model(config: TrainConfig, start: Checkpoint, venv: VecEnv, out: Path) -> BaseAlgorithm:
    """``start``'s model on ``venv``, to go on learning. Its random generators are seeded
    anew from the run's seed and the step, so that a resumed run is the same each time
    it is resumed from that checkpoint (not the same as a run never stopped)."""
    model = _algorithm_class(config.algo).load(
        start.model, env=venv, device="cpu", tensorboard_log=_tensorboard(out)
    )
    model.set_random_seed(config.seed + start.steps)
    return model


def _make_model(
    config: TrainConfig, params: dict[str, Any], venv: VecEnv, out: Path
) -> BaseAlgorithm:
    """The algorithm on ``venv``, with the config's policy and TensorBoard in ``out/tb``."""
    policy = params.pop("policy", "MlpPolicy")
    policy_kwargs = params.pop("policy_kwargs", None)
    tb = _tensorboard(out)
    if isinstance(params.get("train_freq"), list):  # [n, unit]: SB3 takes a tuple only
        params["train_freq"] = tuple(params["train_freq"])
    return _algorithm_class(config.algo)(
        policy,
        venv,
        policy_kwargs=policy_kwargs,
        seed=config.seed,
        device="cpu",
        verbose=0,
        tensorboard_log=tb,
        **params,
    )


def _restarts(venv: VecEnv) -> int:
    """Worker restarts of the Ray vec env under ``venv``'s wrappers."""
    return int(getattr(venv.unwrapped, "restarts", 0))


def _restart_logger(venv: VecEnv) -> BaseCallback:
    """A callback that puts the Ray workers' restart count in SB3's log
    (``ray/worker_restarts``, in TensorBoard beside the rollout figures)."""
    from stable_baselines3.common.callbacks import BaseCallback

    class WorkerRestarts(BaseCallback):
        def _on_step(self) -> bool:
            self.logger.record("ray/worker_restarts", _restarts(venv))
            return True

    return WorkerRestarts()
