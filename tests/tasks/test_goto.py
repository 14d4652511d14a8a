"""The go-to-goal task: goals from the env's generator, reward for approach, a new goal
after each success, a bounded finite observation; and the task registry behind make."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from tensegrity_gym.envs.factory import make_env
from tensegrity_gym.model.description import load_robot
from tensegrity_gym.model.estimate import Estimate
from tensegrity_gym.model.protocols import Task
from tensegrity_gym.model.registry import TASKS, register_task
from tensegrity_gym.tasks.goto import GOAL_RANGE, SUCCESS_RADIUS, GoToTask
from tensegrity_gym.tasks.roll import RollTask

ROBOT = load_robot("three_bar")
L = ROBOT.characteristic_length


def estimate_at(x: float, y: float) -> Estimate:
    """The resting robot moved so that its CoM is at (x, y) on the ground."""
    nodes = ROBOT.initial_positions - ROBOT.initial_positions.mean(axis=0) + [x, y, 0.1]
    rest = ROBOT.rest_lengths[ROBOT.actuated]
    return Estimate(0.0, nodes, np.zeros_like(nodes), np.array([x, y, 0.1]), rest)


def started(seed: int = 0, **kwargs: Any) -> GoToTask:
    task = GoToTask(ROBOT, **kwargs)
    task.reset(estimate_at(0.0, 0.0), np.random.default_rng(seed))
    return task


def toward(task: GoToTask, start: Estimate, metres: float) -> Estimate:
    """``start`` moved ``metres`` straight toward the goal."""
    d = task.goal - start.com[:2]
    x, y = start.com[:2] + metres * d / np.linalg.norm(d)
    return estimate_at(x, y)


def test_both_tasks_follow_the_protocol() -> None:
    assert isinstance(GoToTask(ROBOT), Task) and isinstance(RollTask(ROBOT), Task)


def test_goals_come_from_the_generator_within_the_range() -> None:
    near, far = GOAL_RANGE[0] * L, GOAL_RANGE[1] * L
    goals = [started(seed).goal for seed in range(40)]
    distances = np.linalg.norm(goals, axis=1)
    assert np.all((distances >= near) & (distances <= far))
    assert np.ptp(np.arctan2(*np.transpose(goals)[::-1])) > np.pi  # all around
    np.testing.assert_array_equal(started(3).goal, started(3).goal)  # the seed fixes it
    assert not np.array_equal(started(3).goal, started(4).goal)
    assert started(0, goal_range=(2.0, 2.0)).info(estimate_at(0, 0))["distance_to_goal"] == (
        pytest.approx(2.0)
    )


def test_reward_is_positive_toward_the_goal_and_negative_away() -> None:
    task = started()
    start = estimate_at(0.0, 0.0)
    action = np.zeros(ROBOT.n_actuated, dtype=np.float32)
    closer, farther = toward(task, start, 0.05), toward(task, start, -0.05)
    assert task.reward(start, closer, action) == pytest.approx(10.0 * 0.05 / L)
    assert task.reward(start, farther, action) == pytest.approx(-10.0 * 0.05 / L)
    assert task.progress(closer) == pytest.approx(0.05)
    jump = toward(task, start, 5.0 * task.max_step)  # an estimate that jumped earns nothing
    assert task.implausible_step(start, jump) is not None
    assert task.reward(start, jump, action) == 0.0


def test_success_within_the_radius_draws_a_new_goal() -> None:
    task = started()
    first = task.goal.copy()
    action = np.zeros(ROBOT.n_actuated, dtype=np.float32)
    here = estimate_at(*(first - [1.2 * SUCCESS_RADIUS * L, 0.0]))  # short of the radius
    there = estimate_at(*(first - [0.4 * SUCCESS_RADIUS * L, 0.0]))  # within it
    assert not task.reached(here, here)
    task.advance(here, here)
    np.testing.assert_array_equal(task.goal, first)
    step = task.reward(here, there, action)
    assert step > 10.0  # the approach plus the success bonus
    task.advance(here, there)
    assert task.goals_reached == 1 and not np.array_equal(task.goal, first)
    assert np.linalg.norm(task.goal - there.com[:2]) >= GOAL_RANGE[0] * L  # from where it is
    assert not task.terminated(there)  # goals keep coming until the time limit
    drawn = np.linalg.norm(first)
    assert task.progress(there) == pytest.approx(drawn)  # the first goal's whole distance


def test_observation_is_bounded_finite_and_points_at_the_goal() -> None:
    task = started()
    space = task.observation_space
    assert space.shape == (6 * ROBOT.n_nodes + ROBOT.n_actuated + 3,)
    assert np.all(np.isfinite(space.low)) and np.all(np.isfinite(space.high))
    e = estimate_at(0.0, 0.0)
    obs = task.observation(e)
    assert space.contains(obs)
    goal = task.decode(obs).goal
    d = task.goal / np.linalg.norm(task.goal)
    np.testing.assert_allclose(goal[:2], d, atol=1e-6)
    assert goal[2] == pytest.approx(np.linalg.norm(task.goal) / L, rel=1e-6)
    # In the goal frame the CoM-to-goal direction is +x: the nodes turn with it.
    rel = task.decode(obs).positions * L
    world = e.node_positions - e.com
    np.testing.assert_allclose(rel[:, 0], world[:, :2] @ d, atol=1e-6)
    far = estimate_at(1e3, -1e3)
    assert space.contains(task.observation(far))  # clipped, not out of bounds
    nan = Estimate(0.0, np.full((6, 3), np.nan), np.full((6, 3), np.inf), np.full(3, np.nan),
                   np.full(6, np.nan))  # fmt: skip
    obs = task.observation(nan)
    assert space.contains(obs) and np.all(np.isfinite(obs))
    assert space.contains(task.observation(e))  # and the task recovers


def test_bad_arguments_are_refused_by_name() -> None:
    with pytest.raises(ValueError, match=r"goal_range\[1\]"):
        GoToTask(ROBOT, goal_range=(1.0, float("nan")))
    with pytest.raises(ValueError, match="far must not be below near"):
        GoToTask(ROBOT, goal_range=(2.0, 1.0))
    with pytest.raises(ValueError, match="success_radius"):
        GoToTask(ROBOT, goal_range=(1.0, 2.0), success_radius=1.5)
    with pytest.raises(ValueError, match=r"unknown argument 'goal_heading'.*'goto'"):
        make_env("three_bar", "goto", goal_heading=0.3)
    with pytest.raises(ValueError, match=r"unknown argument 'success_radius'.*'roll'"):
        make_env("three_bar", "roll", success_radius=0.3)
    with pytest.raises(ValueError, match=r"unknown task 'fly'.*'roll', 'goto'"):
        make_env("three_bar", "fly")


class StandStill(RollTask):
    """A lab's own task: rolling with a reward for staying put."""

    def __init__(self, description: Any, *, weight: float = 1.0, control_period: float) -> None:
        super().__init__(description, control_period=control_period)
        self.weight = weight

    def reward(self, previous: Estimate, estimate: Estimate, action: Any) -> float:
        return -self.weight * float(np.linalg.norm(estimate.com[:2] - previous.com[:2]))


def test_a_lab_task_plugs_in_by_name() -> None:
    register_task("stand_still", StandStill, arguments=("weight",))
    try:
        env = make_env("three_bar", "stand_still", estimator="oracle", weight=2.0)
        assert isinstance(env.task, StandStill) and env.task.weight == 2.0
        env.reset(seed=0)
        _, reward, *_ = env.step(np.zeros(6, dtype=np.float32))
        assert reward <= 0.0
        env.close()
    finally:
        TASKS.unregister("stand_still")
