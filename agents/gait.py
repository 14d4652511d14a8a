"""The ``gait`` command: a robot's scripted rolling gait, with a plot of where it went."""

from __future__ import annotations

import itertools
import json
import logging
from typing import TYPE_CHECKING, Any, cast

import gymnasium as gym
import numpy as np

import tensegrity_gym  # noqa: F401  (registers the envs)
from agents.evaluation.plots import plot_com_paths
from tensegrity_gym.model.description import DEFAULT_GAIT
from tensegrity_gym.sim.engines import DEFAULT_ENGINE
from tensegrity_gym.tasks.gaits import FaceGait

if TYPE_CHECKING:
    from pathlib import Path

    from numpy.typing import NDArray

    from tensegrity_gym.envs.tensegrity_env import TensegrityEnv

log = logging.getLogger(__name__)

__all__ = ["heading_change", "run_gait"]


def heading_change(points: NDArray[np.float64], span: int = 1) -> float:
    """How far a path turns (degrees, counter-clockwise seen from above: left > 0): the
    change of direction, unwrapped (twice round is 720), from its first chord to its
    last, each chord from a point to the one ``span`` later. ``points``: positions (m),
    (n, 3) or (n, 2). 0 where fewer than two chords move."""
    p = np.asarray(points, dtype=np.float64)[:, :2]
    if span < 1 or len(p) < span + 2:
        return 0.0
    chords = p[span:] - p[:-span]
    chords = chords[np.linalg.norm(chords, axis=1) > 1e-3]
    if len(chords) < 2:
        return 0.0
    angles = np.arctan2(chords[:, 1], chords[:, 0])
    turns = (np.diff(angles) + np.pi) % (2.0 * np.pi) - np.pi
    return float(np.degrees(turns.sum()))


def run_gait(
    env_id: str = "tensegrity_gym/ThreeBarRoll-v0",
    *,
    steps: int = 300,
    seed: int = 0,
    estimator: str = "ukf",
    gait: str = DEFAULT_GAIT,
    out: Path | None = None,
    engine: str = DEFAULT_ENGINE,
) -> dict[str, Any]:
    """Roll the robot with its scripted gait ``gait`` (a name of the robot's
    ``gaits``: ``"forward"``, and for three_bar_large ``"backward"``, ``"left"``,
    ``"right"``) for ``steps`` control steps.

    Returns a summary (start and end of the true CoM, m; its distance and path length,
    m; its heading change, degrees; support-face changes, the faces in turn and those it
    rests on as each gait period starts) and, if ``out`` is given, writes
    ``com_path.png`` and ``summary.json`` there. ValueError, before any step, for
    a gait the robot lacks.
    """
    env = gym.make(env_id, estimator=estimator, max_episode_steps=steps, engine=engine)
    inner = cast("TensegrityEnv", env.unwrapped)
    try:
        policy = FaceGait(inner.backend.description, inner.task, gait=gait)
    except ValueError:
        env.close()
        raise
    obs, info = env.reset(seed=seed)
    true_path = [info["com_true"]]
    errors = [info["estimation_error"]]
    est_path = [info["com_estimate"]]
    faces = [policy.support_face(obs)]  # the support face after each step
    diverged = False
    for _ in range(steps):
        obs, _, terminated, truncated, info = env.step(policy(obs))
        est_path.append(info["com_estimate"])
        if "com_true" in info:
            true_path.append(info["com_true"])
            errors.append(info["estimation_error"])
        faces.append(policy.support_face(obs))
        if terminated or truncated:
            diverged = bool(info.get("sim_diverged", False))
            break
    env.close()
    path = np.array(true_path)
    start, end = path[0], path[-1]
    summary: dict[str, Any] = {
        "env": env_id,
        "gait": gait,
        "seed": seed,
        "steps": len(est_path) - 1,
        "seconds": (len(est_path) - 1) * inner.backend.control_period,
        "com_start": start.round(4).tolist(),
        "com_end": end.round(4).tolist(),
        "distance": float(np.linalg.norm(end[:2] - start[:2])),
        "path_length": float(np.linalg.norm(np.diff(path[:, :2], axis=0), axis=1).sum()),
        **_turn(path, policy),
        "face_changes": sum(a != b for a, b in itertools.pairwise(faces)),
        "faces": [list(f) for f, _ in itertools.groupby(faces)],
        "rest_faces": [list(f) for f in faces[:: policy.hold_steps + policy.settle_steps]],
        "engine": engine,
        "estimator": estimator,
        "estimation_error_rms": float(np.sqrt(np.mean(np.square(errors)))),
        "estimation_error_max": float(np.max(errors)),
        "diverged": diverged,
    }
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        plot_com_paths(path, np.array(est_path), out / "com_path.png", env_id.split("/")[-1])
        (out / "summary.json").write_text(json.dumps(summary, indent=2))
        summary["plot"] = str(out / "com_path.png")
    return summary


def _turn(path: NDArray[np.float64], gait: FaceGait) -> dict[str, Any]:
    """The summary's rest path and turn. The true CoM ``path`` (one point per step) is
    taken as each gait period starts, where the robot rests: the length (m) of that
    path from rest to rest (the rolls without the sway of the contractions), and its
    heading change (degrees, left > 0) over chords as many periods long as the gait's
    table has faces (so that they span its cycle and its zig-zag is left out)."""
    rests = path[:: gait.hold_steps + gait.settle_steps]
    return {
        "rest_path_length": float(np.linalg.norm(np.diff(rests[:, :2], axis=0), axis=1).sum()),
        "heading_change_deg": heading_change(rests, len(gait.table)),
    }
