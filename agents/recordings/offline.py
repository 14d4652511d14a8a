"""Recording runs to bags, and running estimators over bags offline.

``record`` drives an env with a policy and writes one bag per episode; ``estimate``
replays a bag through an estimator and writes its trajectory (TUM, which evo reads),
metrics against the ground truth where the bag has it, and plots.
"""

from __future__ import annotations

import json
import logging
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import gymnasium as gym
import numpy as np
import yaml
from scipy.spatial.transform import Rotation

import tensegrity_gym  # noqa: F401  (registers the envs)
from agents.evaluation.plots import plot_com_paths, plot_errors
from agents.recordings.runs import estimation_errors
from agents.training.cluster import executor
from estimation.metrics import body_poses, trajectory_errors
from estimation.ukf.initialise import InitialisationError
from hardware.bag.reader import find_bags
from hardware.bag.replay import ReplayBackend
from hardware.recording import hold_command
from tensegrity_gym.envs.calibration import load_uwb_calibration
from tensegrity_gym.envs.factory import make_estimator
from tensegrity_gym.model.checks import output_path_error
from tensegrity_gym.model.registry import estimator_spec
from tensegrity_gym.tasks.gaits import FaceGait

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from tensegrity_gym.envs.tensegrity_env import TensegrityEnv
    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.estimate import Estimate
    from tensegrity_gym.model.protocols import UwbCalibration
    from tensegrity_gym.model.samples import GroundTruth

__all__ = [
    "BAG_FAILURES",
    "POLICIES",
    "BagsFailedError",
    "estimate_bag",
    "make_policy",
    "policy_env_kwargs",
    "record",
    "write_tum",
]

log = logging.getLogger(__name__)

POLICIES = ("scripted", "random")
"""Built-in policies; a training run's folder (from ``train``) is the third kind."""

Policy = Callable[[np.ndarray], np.ndarray]

BAG_FAILURES: tuple[type[Exception], ...] = (ValueError, InitialisationError)
"""What a bag that cannot be estimated raises: :class:`hardware.bag.BagError` and other
ValueErrors (bad content, a robot that does not fit), or an estimator that cannot start
from the bag's first samples. A user's data, not a bug: one line, no traceback."""


class BagsFailedError(ValueError):
    """Some bags of a folder could not be estimated; the others were, and their
    results are in :attr:`results`."""

    def __init__(
        self, results: list[dict[str, Any]], failures: list[tuple[Path, str]], total: int
    ) -> None:
        self.results = results
        self.failures = failures
        """(bag, why) of each bag that failed."""
        names = ", ".join(path.name for path, _ in failures)
        super().__init__(f"{len(failures)} of {total} bags failed: {names}")


def make_policy(name: str, env: gym.Env[Any, Any], seed: int) -> tuple[Policy, Callable[[], None]]:
    """(policy, reset) for ``scripted`` (the robot's face gait), ``random`` (uniform
    actions from a generator seeded with ``seed``) or a training run of ``train`` (its
    folder or its ``model.zip``), which acts on observations normalised as in training."""
    inner = cast("TensegrityEnv", env.unwrapped)
    if name == "scripted":
        gait = FaceGait(inner.backend.description, inner.task)
        return gait, gait.reset
    if name == "random":
        rng = np.random.default_rng(seed)
        low, high = env.action_space.low, env.action_space.high  # type: ignore[attr-defined]

        def random_policy(obs: np.ndarray) -> np.ndarray:
            return np.asarray(rng.uniform(low, high), dtype=np.float32)

        return random_policy, lambda: None
    path = Path(name)
    if not path.exists():
        raise ValueError(
            f"policy {name!r}: not one of {list(POLICIES)} and no training run at that path"
        )
    from agents.evaluation.evaluate import load_policy

    # A run folder from `train`, or its model.zip: the model with its normalisation.
    return load_policy(_run_folder(path)).act, lambda: None


def _run_folder(path: Path) -> Path:
    """A training run's folder, from it or its ``model.zip``."""
    return path if path.is_dir() else path.parent


def policy_env_kwargs(name: str) -> dict[str, Any]:
    """The ``gym.make`` arguments a training run's policy runs with (what its actions and
    observations mean: residual actions on a gait, the gait observed), read from its
    ``config.yaml``; none for the built-in policies, or where ``name`` is no readable run
    (:func:`make_policy` then says why)."""
    path = Path(name)
    if name in POLICIES or not path.exists():
        return {}
    from agents.evaluation.evaluate import action_kwargs

    try:
        config = yaml.safe_load((_run_folder(path) / "config.yaml").read_text())
    except (OSError, yaml.YAMLError):
        return {}
    return action_kwargs(config) if isinstance(config, dict) else {}


def record(
    env_id: str,
    policy: str,
    episodes: int,
    out: Path,
    *,
    steps: int | None = None,
    seed: int = 0,
    estimator: str = "ukf",
    flush_period: float = 1.0,
    driver: str | None = None,
    markers: bool = True,
    engine: str | None = None,
    randomization: str | None = None,
) -> list[Path]:
    """Run ``episodes`` episodes of ``policy`` on ``env_id`` and write one bag each into
    ``out``; ``driver`` (``"zenoh/tcp/HOST:PORT"``) runs a robot on the network instead
    of the id's default; ``engine`` the simulator's physics engine (None: the default);
    ``randomization`` the ranges each episode's world is drawn from (``gym.make``'s);
    ``markers`` writes what viewers draw (``/tf``, the robot as
    markers) at the control rate. Returns the bags written. An interruption (Ctrl-C, SIGTERM)
    closes the current bag properly before it propagates; a run that fails before it
    wrote anything removes the folders it made for ``out``."""
    if episodes < 1:
        raise ValueError(f"episodes must be at least 1, got {episodes}")
    new = _new_folders(Path(out))
    try:
        kwargs: dict[str, Any] = {"estimator": estimator, "record_dir": out}
        given = (("driver", driver), ("engine", engine), ("randomization", randomization))
        kwargs |= {k: v for k, v in given if v is not None}
        if steps is not None:
            kwargs["max_episode_steps"] = steps
        return _record(env_id, policy, episodes, seed, flush_period, markers, kwargs)
    except BaseException:
        _remove_if_empty(new)  # a run that failed before its first bag leaves no folder
        raise


def _new_folders(path: Path) -> list[Path]:
    """``path`` and those of its parents that do not exist yet, deepest first."""
    new = []
    for folder in [path, *path.parents]:
        if folder.exists():
            break
        new.append(folder)
    return new


def _remove_if_empty(folders: list[Path]) -> None:
    """Remove the folders, deepest first, as long as each is empty."""
    for folder in folders:
        try:
            folder.rmdir()
        except FileNotFoundError:  # never made
            continue
        except OSError:  # not empty: what is in it stays, and its parents
            return


def _record(
    env_id: str,
    policy: str,
    episodes: int,
    seed: int,
    flush_period: float,
    markers: bool,
    kwargs: dict[str, Any],
) -> list[Path]:
    """:func:`record`'s episodes, once its arguments are checked; ``kwargs`` go to
    ``gym.make``."""
    env = gym.make(env_id, **kwargs, **policy_env_kwargs(policy))
    inner = cast("TensegrityEnv", env.unwrapped)
    backend = inner.backend
    sink = backend.sink  # type: ignore[attr-defined]
    sink.flush_period = flush_period
    sink.markers = markers
    sink.run_info.update({"env": env_id, "policy": policy, "seed": seed})
    act, reset_policy = make_policy(policy, env, seed)
    try:
        for episode in range(episodes):
            obs, _ = env.reset(seed=seed + episode)
            reset_policy()
            done = False
            while not done:
                obs, _, terminated, truncated, _ = env.step(act(obs))
                done = terminated or truncated
            log.info("episode %d: %.1f s recorded", episode, backend.t_command)  # type: ignore[attr-defined]
    finally:
        env.close()  # closes the bag being written, even on Ctrl-C
    return list(sink.paths)


def write_tum(file: Path, t: NDArray[np.float64], poses: NDArray[np.float64]) -> None:
    """A TUM trajectory: ``t x y z qx qy qz qw`` per line, poses (T, 4, 4)."""
    quats = Rotation.from_matrix(poses[:, :3, :3]).as_quat()  # (x, y, z, w)
    rows = np.column_stack([t, poses[:, :3, 3], quats])
    np.savetxt(file, rows, fmt="%.9f", header="timestamp tx ty tz qx qy qz qw")


def _run_estimator(
    backend: ReplayBackend, estimator: str, seed: int, progress: bool
) -> tuple[list[Estimate], list[GroundTruth | None]]:
    from tqdm import tqdm

    est = make_estimator(estimator, backend)
    d = backend.description
    rng = np.random.default_rng(seed)
    start = backend.reset(rng)
    estimates = [est.reset(d, backend.calibration, start.samples, hold_command(d), rng)]
    truths = [backend.ground_truth()]
    ended = start.ended
    bar = tqdm(
        total=backend.steps_total,
        disable=not progress,
        unit="step",
        desc=Path(backend.reader.path).name,
        leave=False,
    )
    with bar:
        while not ended:
            command = backend.next_command
            assert command is not None
            result = backend.step(command)
            estimates.append(est.update(result.samples, command))
            truths.append(backend.ground_truth())
            ended = result.ended
            bar.update()
    return estimates, truths


def estimate_bag(
    bag: str | Path,
    estimator: str,
    out: Path,
    *,
    seed: int = 0,
    description: RobotDescription | None = None,
    strict: bool = False,
    settle: float = 2.0,
    progress: bool = True,
    calibration: str | Path | None = None,
    ray_address: str | None = None,
) -> list[dict[str, Any]]:
    """Run ``estimator`` over every bag at ``bag`` (one bag, or a folder of episodes),
    with the bag's own UWB calibration or a ``calibration`` file's; with
    ``ray_address``, each bag as a task on that Ray cluster (the bags on a path every
    node reads; the results come back here).

    Writes per bag, into ``out`` (``out/<bag name>`` for a folder of several):
    ``estimate.tum`` (the body frame of :func:`estimation.metrics.body_poses`, origin at
    the CoM), ``truth.tum`` and ``metrics.json`` (errors against the ground truth, where
    the bag has it), ``com_path.png``, ``error.png`` (with truth) and ``estimates.npz``.
    Returns the metrics of each bag.

    Raises:
        BAG_FAILURES: the one bag at ``bag`` cannot be estimated.
        BagsFailedError: some bags of a folder cannot be; the others were estimated,
            and each failure was logged in one line.
    """
    estimator_spec(estimator)  # an unknown name is refused before any bag is opened
    error = output_path_error(out, "--out", folder=True)
    if error is not None:
        raise ValueError(error)
    uwb = (
        None if calibration is None else load_uwb_calibration(calibration, argument="--calibration")
    )
    bags = find_bags(bag)
    with executor(ray_address) as jobs:
        run = partial(
            _estimate_job, estimator=estimator, seed=seed, description=description,
            strict=strict, settle=settle, progress=progress and jobs.local, uwb=uwb,
        )  # fmt: skip
        outcomes = jobs.map(run, bags)
    results, failures = [], []
    for path, outcome in zip(bags, outcomes, strict=True):
        if outcome.error is not None and len(bags) == 1:
            raise outcome.error
        if outcome.error is not None:
            text = " ".join(str(outcome.error).split())  # one line per bag, whatever it says
            why = text if str(path) in text else f"{path}: {type(outcome.error).__name__}: {text}"
            log.error("%s", why)
            failures.append((path, why))
            continue
        outcome.write(out if len(bags) == 1 else out / path.name)
        results.append(outcome.metrics)
    if failures:
        raise BagsFailedError(results, failures, len(bags))
    return results


@dataclass
class _BagOutcome:
    """What estimating one bag gave, to be written where the caller runs: the metrics
    and the files (name: content), or the error that stopped it."""

    metrics: dict[str, Any] = field(default_factory=dict)
    files: dict[str, bytes] = field(default_factory=dict)
    error: Exception | None = None

    def write(self, folder: Path) -> None:
        """The files into ``folder`` (made if need be)."""
        folder.mkdir(parents=True, exist_ok=True)
        for name, content in self.files.items():
            (folder / name).write_bytes(content)


def _estimate_job(path: Path, **kwargs: Any) -> _BagOutcome:
    """One bag, :func:`estimate_bag`'s job, here or as a Ray task: the results are made
    in a scratch folder and returned, so that they reach the caller's ``out`` from any
    node (``kwargs``: :func:`_estimate_one`'s)."""
    with tempfile.TemporaryDirectory(prefix="tensegrity-estimate-") as scratch:
        try:
            metrics = _estimate_one(path, out=Path(scratch), **kwargs)
        except BAG_FAILURES as err:
            return _BagOutcome(error=err)
        files = {f.name: f.read_bytes() for f in sorted(Path(scratch).iterdir()) if f.is_file()}
    return _BagOutcome(metrics, files)


def calibration_against_truth(backend: ReplayBackend) -> dict[str, Any]:
    """Which UWB calibration the estimator had (``"recorded"``: the bag's, else the
    file's path) and, where the bag's run info holds the simulator's own, how far the
    one used lies from it: anchors, robot-anchor and robot-robot offsets (m RMS)."""
    uwb = backend.uwb_calibration
    out: dict[str, Any] = {"calibration": "recorded" if uwb is None else uwb.source}
    truth = backend.reader.run_info.get("true_calibration")
    if not isinstance(truth, dict):
        return out
    used, n = backend.calibration, backend.description.n_nodes
    anchors = np.asarray(truth.get("anchors"), dtype=np.float64)
    offsets = np.asarray(truth.get("uwb_offsets"), dtype=np.float64)
    if anchors.shape != used.anchors.shape or offsets.shape != used.uwb_offsets.shape:
        return out
    robot = np.triu_indices(n, 1)

    def rms(x: NDArray[np.float64]) -> float:
        return round(float(np.sqrt(np.mean(np.square(x)))), 4)

    out["calibration_against_true"] = {
        "anchor_rms_m": rms(np.linalg.norm(used.anchors - anchors, axis=1)),
        "robot_anchor_offset_rms_m": rms(used.uwb_offsets[n:, :n] - offsets[n:, :n]),
        "robot_robot_offset_rms_m": rms(used.uwb_offsets[robot] - offsets[robot]),
    }
    return out


def _estimate_one(
    path: Path,
    *,
    estimator: str,
    out: Path,
    seed: int,
    description: RobotDescription | None,
    strict: bool,
    settle: float,
    progress: bool,
    uwb: UwbCalibration | None = None,
) -> dict[str, Any]:
    backend = ReplayBackend(path, description=description, strict=strict)
    backend.uwb_calibration = uwb
    try:
        missing = estimator_spec(estimator).missing(backend.sample_kinds(), backend.description)
        if missing is not None:
            raise ValueError(f"{path}: {missing}")
        wall = time.perf_counter()
        estimates, truths = _run_estimator(backend, estimator, seed, progress)
        wall = time.perf_counter() - wall
    finally:
        backend.close()
    d = backend.description
    out.mkdir(parents=True, exist_ok=True)
    t = np.array([e.t for e in estimates])
    nodes = np.array([e.node_positions for e in estimates])
    com = np.array([e.com for e in estimates])
    finite = np.all(np.isfinite(nodes), axis=(1, 2))
    poses = body_poses(nodes[finite], d.rod_nodes, d.node_masses)
    write_tum(out / "estimate.tum", t[finite], poses)
    duration = float(t[-1] - t[0]) if len(t) > 1 else 0.0
    metrics: dict[str, Any] = {
        "bag": str(path),
        "robot": d.name,
        "estimator": estimator,
        "seed": seed,
        "steps": len(estimates) - 1,
        "duration_s": round(duration, 3),
        "wall_s": round(wall, 3),
        "realtime_factor": round(duration / wall, 1) if wall > 0 else None,
        "recovered_bag": backend.reader.recovered,
        "skipped_messages": dict(backend.reader.skipped),
        "lost_spans": [span.as_dict() for span in backend.reader.lost_spans],
        "out_of_range": dict(backend.out_of_range),
        "reinitialisations": int(sum(e.reinitialised for e in estimates)),
        # Measurements the estimator's screen refused as physically impossible (a
        # range of -50 m), by kind: counted since its reset, so the last estimate's.
        "estimator_rejected": dict(sorted((estimates[-1].rejected or {}).items())),
        # Where the readings contradict the description (kept in use), a line each.
        "description_mismatch": list(estimates[-1].description_mismatch),
        "finite": bool(finite.all()),
        **calibration_against_truth(backend),
    }
    true_com = _against_truth(estimates, truths, d, finite, metrics, out, settle,
                              f"{path.name}: {estimator} against the ground truth")  # fmt: skip
    plot_com_paths(true_com, com[finite], out / "com_path.png", f"{path.name} ({estimator})")
    np.savez_compressed(
        out / "estimates.npz",
        t=t,
        node_positions=nodes,
        com=com,
        healthy=np.array([e.healthy for e in estimates]),
        reinitialised=np.array([e.reinitialised for e in estimates]),
    )
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
    return metrics


def _against_truth(
    estimates: list[Estimate],
    truths: list[GroundTruth | None],
    d: RobotDescription,
    finite: NDArray[np.bool_],
    metrics: dict[str, Any],
    out: Path,
    settle: float,
    title: str,
) -> NDArray[np.float64] | None:
    """Where the bag has ground truth: its errors into ``metrics``, ``truth.tum`` and
    ``error.png`` into ``out``; the true CoM path (k, 3) of the finite steps with truth,
    or None without truth."""
    has_truth = [x is not None for x in truths]
    if not any(has_truth):
        return None
    t = np.array([e.t for e in estimates])
    nodes = np.array([e.node_positions for e in estimates])
    com = np.array([e.com for e in estimates])
    keep = [i for i, ok in enumerate(has_truth) if ok and finite[i]]
    true_nodes = np.array([cast("GroundTruth", truths[i]).node_positions for i in keep])
    true_com = np.array([cast("GroundTruth", truths[i]).com for i in keep])
    true_poses = body_poses(true_nodes, d.rod_nodes, d.node_masses)
    write_tum(out / "truth.tum", t[keep], true_poses)
    metrics.update(estimation_errors(d, estimates, truths, settle))
    if len(keep) > 2:
        est_poses = body_poses(nodes[keep], d.rod_nodes, d.node_masses)
        traj = trajectory_errors(est_poses, true_poses)
        metrics.update(
            ate_rmse_m=round(traj.ate_rmse, 4),
            rpe_rmse_m=round(traj.rpe_rmse, 4),
            # The CoM's: not the bench's drift_percent (Tong et al. 2024's, rod 0's centre).
            com_final_error_m=round(traj.final_drift, 4),
            com_path_length_m=round(traj.path_length, 4),
            com_drift_percent=round(traj.drift_percentage, 2),
        )
    errors = np.linalg.norm(com[keep] - true_com, axis=-1)
    node_rms = np.sqrt(np.mean(np.sum((nodes[keep] - true_nodes) ** 2, axis=-1), axis=-1))
    marks = t[[i for i in keep if estimates[i].reinitialised]]
    plot_errors(
        t[keep] - t[0],
        {"CoM error": errors, "node RMS error": node_rms},
        out / "error.png",
        title,
        marks - t[0],
    )
    return true_com
