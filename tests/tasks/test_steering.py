"""The steering gait: several contractions per face, each with the move it makes, and
FaceGait choosing the one that rolls furthest toward the goal; it rolls toward any
heading and to goals, which the forward gait cannot."""

from __future__ import annotations

import cmath
import re
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from agents.evaluation.evaluate import (
    GAIT_POLICY,
    STEER_POLICY,
    condition,
    evaluate_policy,
    gait_policy,
    true_progress,
)
from agents.training.train import load_hyperparams
from tensegrity_gym.envs.factory import make_env, make_roll_env
from tensegrity_gym.model.description import (
    STEER_GAIT,
    DescriptionError,
    dump_robot,
    load_robot,
    loads_robot,
    robot_document,
)
from tensegrity_gym.tasks.gaits import FaceGait, face_yaw, lowest_face, turned


def test_the_steering_gait_loads_and_round_trips() -> None:
    d = load_robot("three_bar")
    steer = d.gaits[STEER_GAIT]
    faces = [e.face for e in steer.faces]
    assert len(set(faces)) < len(faces)  # faces have several entries to choose from
    assert all(e.move is not None and e.to is not None for e in steer.faces)
    assert all(e.to != e.face for e in steer.faces)  # every entry leaves its face
    assert loads_robot(dump_robot(d)) == d
    assert d.gait is not None and all(e.move is None for e in d.gait.faces)


def _broken(doc: dict[str, Any], field: str) -> dict[str, Any]:
    faces = doc["gaits"]["steer"]["faces"]
    if field == "gaits.steer.faces[1]":
        del faces[1]["to"]  # a move without the face it leads to
    elif field == "gaits.steer.faces[0].move":
        faces[0]["move"] = [0.1, 0.2]
    elif field == "gaits.steer.faces[2].to":
        faces[2]["to"] = ["n0", "n1", "n9"]
    elif field == "gait.faces[1].face":  # a plain gait's face listed twice
        doc["gait"]["faces"][1]["face"] = doc["gait"]["faces"][0]["face"]
    return doc


@pytest.mark.parametrize(
    "field",
    [
        "gaits.steer.faces[1]",
        "gaits.steer.faces[0].move",
        "gaits.steer.faces[2].to",
        "gait.faces[1].face",
    ],
)
def test_a_bad_steering_entry_names_the_file_and_field(field: str) -> None:
    doc = _broken(robot_document(load_robot("three_bar")), field)
    with pytest.raises(DescriptionError, match="^" + re.escape(f"robot.yaml: {field}")):
        loads_robot(yaml.safe_dump(doc, sort_keys=False), "robot.yaml")


def _reference_values(gait: FaceGait, face: tuple[int, ...], yaw: float) -> list[float]:
    """A slow reference for the face's entries: every path of ``gait.horizon`` periods
    written out (no memo), complex numbers for the turns; each entry's best path (m)."""
    entries = gait_entries(gait)

    def best(face: tuple[int, ...], yaw: float, periods: int) -> float:
        paths = [
            (complex(e.move[0], e.move[1]) * cmath.exp(1j * yaw)).real
            + (best(e.to, yaw + e.move[2], periods - 1) if periods > 1 else 0.0)
            for e in entries
            if e.face == face
        ]
        return max(paths) if paths else 0.0

    return [
        (complex(e.move[0], e.move[1]) * cmath.exp(1j * yaw)).real
        + (best(e.to, yaw + e.move[2], gait.horizon - 1) if gait.horizon > 1 else 0.0)
        for e in entries
        if e.face == face
    ]


def gait_entries(gait: FaceGait) -> Any:
    return gait.task.description.gaits[STEER_GAIT].faces


@pytest.mark.parametrize("horizon", [1, 2, 3])
def test_the_choice_matches_a_slow_reference_at_every_yaw(horizon: int) -> None:
    env = make_roll_env("three_bar", estimator="oracle")
    gait = FaceGait(env.backend.description, env.task, gait=STEER_GAIT, horizon=horizon)
    assert gait.steers
    rng = np.random.default_rng(0)
    obs, _ = env.reset(seed=0)
    positions = env.task.decode(obs).positions.astype(np.float64)
    face = lowest_face(positions)
    entries = [e for e in gait_entries(gait) if e.face == face]
    seen = set()
    for angle in rng.uniform(-np.pi, np.pi, 24):
        spun = positions.copy()
        spun[:, :2] = turned(positions[:, :2], angle)
        values = _reference_values(gait, face, face_yaw(spun, face))
        gait.reset()  # each a first period on the face (not a stall)
        action = gait.action_for_face(face, spun)
        chosen = [i for i, e in enumerate(entries) if np.array_equal(_action(gait, e), action)]
        # The choice is the reference's best, up to the memo's 2-degree yaw bins.
        assert max(values[i] for i in chosen) == pytest.approx(max(values), abs=2e-3)
        seen.add(action.tobytes())
    assert len(seen) >= 2  # the goal's direction changes the choice
    env.close()


def _action(gait: FaceGait, entry: Any) -> np.ndarray:
    out = np.ones(6, dtype=np.float32) if entry.others == "out" else gait.hold_action.copy()
    out[list(entry.contract)] = -1.0
    return out


def test_a_horizon_below_one_period_is_refused() -> None:
    env = make_roll_env("three_bar", estimator="oracle")
    with pytest.raises(ValueError, match="horizon must be an integer >= 1"):
        FaceGait(env.backend.description, env.task, gait=STEER_GAIT, horizon=0)
    env.close()


def test_a_move_that_stalled_is_not_chosen_again_on_that_face() -> None:
    env = make_roll_env("three_bar", estimator="oracle")
    gait = FaceGait(env.backend.description, env.task, gait=STEER_GAIT)
    obs, _ = env.reset(seed=0)
    face = lowest_face(env.task.decode(obs).positions)
    n = len([e for e in gait_entries(gait) if e.face == face])
    period = gait.hold_steps + gait.settle_steps
    # The same observation period after period: the robot stayed on its face each time.
    holds = [gait(obs) for _ in range((n + 1) * period)][gait.ramp_steps :: period]
    tried = [h.tobytes() for h in holds]
    assert len(set(tried[:n])) == n  # each move tried once
    assert tried[n] == tried[0]  # every one stalled: all open again, the best first
    gait.reset()  # a new episode forgets the stalls
    assert [gait(obs) for _ in range(period)][gait.ramp_steps].tobytes() == tried[0]
    env.close()


def _on_face(obs: np.ndarray, face: tuple[int, ...], n: int) -> np.ndarray:
    """``obs`` with the nodes of ``face`` lowest (z -1 L, the others +1 L)."""
    out = obs.copy()
    z = np.ones(n, dtype=np.float32)
    z[list(face)] = -1.0
    out[2 : 3 * n : 3] = z
    return out


def test_a_move_is_not_taken_for_stalled_after_a_face_of_one_entry() -> None:
    # A -> B (one entry) -> A: the move from A worked, and stays open.
    d = load_robot("three_bar")
    steer = d.gaits[STEER_GAIT]
    a = steer.faces[0].face
    b = next(e.to for e in steer.faces if e.face == a)
    faces = tuple(e for e in steer.faces if e.face != b)
    only = next(e for e in steer.faces if e.face == b)
    robot = replace(d, named_gaits=((STEER_GAIT, replace(steer, faces=(*faces, only))),))
    env = make_roll_env(robot, estimator="oracle")
    gait = FaceGait(robot, env.task, gait=STEER_GAIT, ramp_steps=0)
    obs, _ = env.reset(seed=0)
    period = gait.hold_steps + gait.settle_steps
    on_a, on_b = _on_face(obs, a, robot.n_nodes), _on_face(obs, b, robot.n_nodes)
    commands = [gait(on_a).tobytes() for _ in range(period)]  # a whole period on A
    for _ in range(period):
        gait(on_b)
    assert gait(on_a).tobytes() == commands[0]  # not struck off: it led to B
    env.close()


def _progress(
    task: str, gait: str, seed: int, steps: int, robot: str = "three_bar", **kwargs: Any
) -> float:
    """Metres the true CoM came toward the goal (along its heading, or to its point)."""
    env = make_env(robot, task, estimator="oracle", **kwargs)
    policy = FaceGait(env.backend.description, env.task, gait=gait)
    obs, _ = env.reset(seed=seed)
    for _ in range(steps):
        obs, _, _, _, info = env.step(policy(obs))
    # The oracle's estimate is the truth: the task's own progress (for goto, goals
    # reached count their whole distance).
    out = float(info["progress"])
    env.close()
    return out


# Measured on the oracle, 210 steps (6 periods) from reset(0): the steering gait makes
# 1.03, 0.12, 1.01 and 0.27 m toward the four headings (the prism rolls fast along one
# axis and turns slowly); the forward gait rolls its own way, backward for two of them.
HEADINGS = (0.0, 0.5 * np.pi, np.pi, -0.5 * np.pi)


@pytest.mark.slow  # 22 s; the default run is near its 15 minutes
def test_the_steering_gait_rolls_toward_every_heading() -> None:
    steer = [_progress("roll", STEER_GAIT, 0, 210, goal_heading=h) for h in HEADINGS]
    forward = [_progress("roll", "forward", 0, 210, goal_heading=h) for h in HEADINGS]
    assert min(steer) > 0.05 and np.mean(steer) > 0.5, steer
    assert np.mean(steer) > np.mean(forward) + 0.3, (steer, forward)  # the forward can't aim


def test_superballs_steering_gait_rolls_both_ways() -> None:
    # Measured on the oracle, 140 steps from reset(0): steer 2.74 and 2.49 m (the forward
    # gait -1.05 and 1.05 m).
    steer = [_progress("roll", STEER_GAIT, 0, 140, "superball", goal_heading=h) for h in (0, np.pi)]
    assert min(steer) > 1.5, steer


def test_the_steering_gait_comes_to_a_goal_point() -> None:
    # The go-to task's goal frame points at the goal, which moves on once reached.
    assert _progress("goto", STEER_GAIT, 1, 210) > 0.3


def test_residual_actions_correct_the_gait_named_by_base_gait() -> None:
    env = make_roll_env("three_bar", estimator="oracle", residual_gait=0.5, base_gait="steer")
    assert isinstance(env.action_base, FaceGait) and env.action_base.gait == STEER_GAIT
    env.close()
    with pytest.raises(ValueError, match=r"^make: base_gait: .*'sideways'.*\['forward', 'steer'\]"):
        make_roll_env("three_bar", residual_gait=0.5, base_gait="sideways")


def test_evaluate_has_a_steering_gait_row_where_the_robot_has_one() -> None:
    three_bar = gait_policy("tensegrity_gym/ThreeBarRoll-v0", STEER_POLICY)
    assert three_bar is not None and three_bar.name == STEER_POLICY
    assert gait_policy("tensegrity_gym/ThreeBarLargeRoll-v0", STEER_POLICY) is None
    assert gait_policy("tensegrity_gym/ThreeBarLargeRoll-v0", GAIT_POLICY) is not None


@pytest.mark.parametrize(
    ("env_id", "width"),
    [
        ("tensegrity_gym/ThreeBarRoll-v0", 64),
        ("tensegrity_gym/ThreeBarGoTo-v0", 64),
        ("tensegrity_gym/SuperBallGoTo-v0", 128),
    ],
)
def test_the_long_runs_config_explores_with_small_plain_noise(env_id: str, width: int) -> None:
    config = Path(__file__).resolve().parents[2] / "agents" / "training" / "configs" / "steer.yml"
    params = load_hyperparams("ppo", env_id, config)
    assert params["use_sde"] is False and params["n_timesteps"] == 81920
    assert params["policy_kwargs"]["log_std_init"] == -3.0
    assert params["policy_kwargs"]["net_arch"]["pi"] == [width, width]


def test_true_progress_toward_goal_points_counts_each_goal_to_where_it_was_reached() -> None:
    true = np.array([[0.0, 0, 0], [1.0, 0, 0], [1.0, 1, 0], [1.0, 2, 0]])
    goals = np.array([[1.0, 0], [1.0, 3], [1.0, 3]])  # the first reached on step 1
    assert true_progress(true, None, goals) == pytest.approx(1.0 + 1.0 + 1.0)
    assert true_progress(true, np.array([0.0, 1.0])) == pytest.approx(2.0)
    with pytest.raises(ValueError, match="heading or the goals"):
        true_progress(true, None)


def test_evaluate_measures_the_goto_task_as_the_task_does_on_truth() -> None:
    # Under the oracle the task's own progress is the truth's, but for the goals reached:
    # the task counts each one's whole distance, the truth up to where it was reached
    # (within the success radius).
    steering = gait_policy("tensegrity_gym/ThreeBarGoTo-v0", STEER_POLICY)
    assert steering is not None
    (result,) = evaluate_policy(steering, condition("oracle"), episodes=1, seed=1)
    env = make_env("three_bar", "goto", estimator="oracle")
    policy = FaceGait(env.backend.description, env.task, gait=STEER_GAIT)
    obs, info = env.reset(seed=1)
    path, goals = [info["com_true"]], []
    for _ in range(600):  # the id's episode
        goals.append(info["goal"])
        obs, _, _, _, info = env.step(policy(obs))
        path.append(info["com_true"])
    env.close()
    assert result.progress == pytest.approx(true_progress(np.array(path), None, np.array(goals)))
    reached, radius = info["goals_reached"], env.task.success_radius
    assert info["progress"] - reached * radius <= result.progress <= info["progress"] + 1e-9
    assert result.progress > 0.5


def test_gait_noise_measures_the_gait_itself_at_zero_noise() -> None:
    import importlib.util

    import gymnasium as gym

    path = Path(__file__).resolve().parents[2] / "scripts" / "gait_noise.py"
    spec = importlib.util.spec_from_file_location("gait_noise", path)
    assert spec is not None and spec.loader is not None
    gait_noise = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gait_noise)
    env = gym.make(
        "tensegrity_gym/ThreeBarRoll-v0",
        estimator="oracle",
        residual_gait=0.5,
        base_gait=STEER_GAIT,
        max_episode_steps=140,
    )
    steering = _progress("roll", STEER_GAIT, 1000, 140, goal_heading=0.0)
    assert gait_noise.progress(env, 0.0, 1000) == pytest.approx(steering, abs=1e-9)
    noisy = [gait_noise.progress(env, 0.5, 1000) for _ in range(2)]
    assert noisy[0] == noisy[1] != pytest.approx(steering)  # seeded by the episode
    env.close()
