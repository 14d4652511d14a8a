"""The scripted gait rolls the robot: the CoM moves and the support face changes."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from agents.demo import run_gait
from tensegrity_gym.envs.factory import make_roll_env
from tensegrity_gym.tasks.gaits import FaceGait


def test_three_bar_gait_rolls_face_to_face(tmp_path) -> None:
    summary = run_gait("tensegrity_gym/ThreeBarRoll-v0", steps=120, seed=1, out=tmp_path)
    assert not summary["diverged"]
    assert summary["face_changes"] >= 3, "it flips from one base triangle to the next"
    assert summary["distance"] > 0.4  # metres in 12 s; the robot is 0.36 m long
    # The gait reads the UKF's estimate, and the estimate follows the truth while rolling.
    assert summary["estimator"] == "ukf"
    assert summary["estimation_error_max"] < 0.05
    assert (tmp_path / "com_path.png").stat().st_size > 10_000
    assert (tmp_path / "summary.json").exists()


def test_superball_gait_goes_through_face_transitions(tmp_path) -> None:
    summary = run_gait("tensegrity_gym/SuperBallRoll-v0", steps=110, seed=2, out=tmp_path)
    assert not summary["diverged"]
    assert summary["face_changes"] >= 2
    assert summary["distance"] > 1.0  # metres; SUPERball's rods are 1.5 m
    assert summary["estimation_error_rms"] < 0.05


def test_large_three_bar_gait_rolls_it_forward(tmp_path) -> None:
    # The gait of three_bar_large.yaml (scripts/find_gait.py): 4.1 m in 300 steps, seed 0.
    summary = run_gait("tensegrity_gym/ThreeBarLargeRoll-v0", steps=140, seed=0, out=tmp_path)
    assert not summary["diverged"]
    assert summary["face_changes"] >= 4
    start, end = np.array(summary["com_start"]), np.array(summary["com_end"])
    assert end[0] - start[0] > 1.5  # metres forward in 14 s; its rods are 1.45 m
    assert abs(end[1] - start[1]) < 0.5 * (end[0] - start[0])  # forward, not sideways
    assert summary["estimation_error_max"] < 0.1


def test_gait_rejects_a_robot_without_one_and_bad_table() -> None:
    env = make_roll_env("three_bar")
    bare = replace(env.backend.description, gait=None)
    with pytest.raises(ValueError, match=r"no gait table for robot 'three_bar'.*find_gait"):
        FaceGait(bare, env.task)
    with pytest.raises(TypeError, match="decode"):
        FaceGait(env.backend.description, object())  # type: ignore[arg-type]
    env.close()
    env = make_roll_env("three_bar")
    with pytest.raises(ValueError, match="bad gait table entry"):
        FaceGait(env.backend.description, env.task, table={(0, 1, 2): ((9,), "hold")})
    env.close()


def test_gait_state_resets() -> None:
    env = make_roll_env("three_bar")
    gait = FaceGait(env.backend.description, env.task)
    obs, _ = env.reset(seed=0)
    first = [gait(obs) for _ in range(3)]
    gait.reset()
    again = [gait(obs) for _ in range(3)]
    assert all(np.array_equal(a, b) for a, b in zip(first, again, strict=True))
    env.close()
