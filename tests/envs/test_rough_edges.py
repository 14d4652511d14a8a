"""What a new user hit (issue 19): a closed env, reset options, a headless check_env,
PyBullet's banner, the command line's help and a failed ``record``."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from tensegrity_gym.envs.safety import StopOnError
from tensegrity_gym.sim.backend import SimBackend

ROLL = "tensegrity_gym/ThreeBarRoll-v0"


def test_step_and_reset_after_close_raise_and_close_twice_is_harmless() -> None:
    env = gym.make(ROLL)
    assert not isinstance(env, StopOnError)  # a simulated id has no motors to stop
    env.reset(seed=0)
    env.step(env.action_space.sample())
    env.close()
    env.close()  # harmless
    with pytest.raises(RuntimeError, match="step: the env was closed"):
        env.step(env.action_space.sample())
    with pytest.raises(RuntimeError, match="reset: the env was closed"):
        env.reset(seed=0)
    backend = env.unwrapped.backend
    assert isinstance(backend, SimBackend)
    assert backend._world is None  # no new world was built behind the user's back
    env.close()


def test_a_closed_backend_builds_no_new_world() -> None:
    env = gym.make(ROLL)
    env.reset(seed=0)
    backend = env.unwrapped.backend
    backend.close()
    backend.close()
    with pytest.raises(RuntimeError, match="step: the env was closed"):
        backend.step(np.zeros(backend.description.n_actuated) + 0.1)
    with pytest.raises(RuntimeError, match="reset: the env was closed"):
        backend.reset(np.random.default_rng(0))
    with pytest.raises(RuntimeError, match="the env was closed"):
        _ = backend.world
    env.close()


def _rollout(env: gym.Env, seed: int, options: dict | None, steps: int = 5) -> list[np.ndarray]:
    obs, _ = env.reset(seed=seed, options=options)
    out = [obs]
    rng = np.random.default_rng(seed)
    for _ in range(steps):
        out.append(env.step(rng.uniform(-1.0, 1.0, env.action_space.shape))[0])
    return out


def test_reset_without_options_is_unchanged(three_bar_env) -> None:
    plain = _rollout(three_bar_env, 3, None)
    empty = _rollout(three_bar_env, 3, {})
    assert all(np.array_equal(a, b) for a, b in zip(plain, empty, strict=True))


def test_reset_options_set_the_goal_for_that_episode_only(three_bar_env) -> None:
    env = three_bar_env
    obs, _ = env.reset(seed=0, options={"goal_heading": 0.5, "goal_distance": 0.2})
    task = env.unwrapped.task
    np.testing.assert_allclose(obs[-2:], [np.cos(0.5), np.sin(0.5)], rtol=1e-6)
    assert task.episode_goal_distance == 0.2
    obs, _ = env.reset(seed=0)
    assert task.heading == task.goal_heading and task.episode_goal_distance == task.goal_distance
    np.testing.assert_allclose(obs[-2:], [np.cos(task.heading), np.sin(task.heading)], rtol=1e-6)


def test_reset_option_goal_distance_ends_the_episode(three_bar_env) -> None:
    env = three_bar_env
    env.reset(seed=0, options={"goal_distance": 1e-9})
    rng = np.random.default_rng(0)
    for _ in range(20):
        _, _, terminated, _, info = env.step(rng.uniform(-1.0, 1.0, env.action_space.shape))
        assert terminated == (info["progress"] >= 1e-9)
        if terminated:
            break
    assert terminated


def test_reset_option_spawn_places_the_robot(three_bar_env) -> None:
    env = three_bar_env
    _, info = env.reset(seed=1, options={"spawn": {"x": 2.0, "y": -1.0, "yaw": 0.0}})
    np.testing.assert_allclose(info["com_true"][:2], [2.0, -1.0], atol=1e-3)
    nodes = env.unwrapped.backend.ground_truth().node_positions - info["com_true"]
    _, info = env.reset(seed=1, options={"spawn": {"x": 2.0, "y": -1.0, "yaw": np.pi / 2}})
    turned = env.unwrapped.backend.ground_truth().node_positions - info["com_true"]
    # a quarter turn about z: (x, y) -> (-y, x)
    np.testing.assert_allclose(turned[:, :2], np.stack([-nodes[:, 1], nodes[:, 0]], 1), atol=1e-3)


def test_reset_option_spawn_passes_through_a_recording(tmp_path) -> None:
    env = gym.make(ROLL, record_dir=str(tmp_path))
    _, info = env.reset(seed=0, options={"spawn": {"x": -1.5}})
    assert abs(info["com_true"][0] + 1.5) < 1e-3
    env.close()


def test_reset_option_goal_of_goto() -> None:
    env = gym.make("tensegrity_gym/ThreeBarGoTo-v0")
    _, info = env.reset(seed=0, options={"goal": (1.0, 2.0)})
    np.testing.assert_array_equal(info["goal"], [1.0, 2.0])
    with pytest.raises(ValueError, match=r"unknown options \['goal_heading'\]; valid: \['goal', "):
        env.reset(seed=0, options={"goal_heading": 0.0})
    with pytest.raises(ValueError, match=r"reset: goal=3.0 must be a point"):
        env.reset(seed=0, options={"goal": 3.0})
    env.close()


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (
            {"foo": 1},
            r"reset: unknown options \['foo'\]; valid: "
            r"\['goal_distance', 'goal_heading', 'spawn'\]",
        ),
        (
            {"spawn": {"z": 1.0}},
            r"reset: spawn has unknown keys \['z'\]; valid: \['x', 'y', 'yaw'\]",
        ),
        ({"spawn": {"x": float("nan")}}, r"reset: spawn\['x'\]=nan"),
        ({"spawn": 2.0}, r"reset: spawn=2.0 must be a dict"),
        ({"goal_distance": -1.0}, r"reset: goal_distance=-1.0"),
        ({"goal_heading": "north"}, r"reset: goal_heading='north'"),
        ("spawn", r"reset: options must be a dict, got str"),
    ],
)
def test_reset_refuses_bad_options(three_bar_env, options, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        three_bar_env.reset(seed=0, options=options)
    three_bar_env.reset(seed=0)  # and the env goes on


def test_check_env_with_its_defaults_passes_headless(monkeypatch) -> None:
    from gymnasium.utils.env_checker import check_env

    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.setattr("sys.platform", "linux")
    env = gym.make(ROLL)
    with pytest.warns(RuntimeWarning, match=r"render_mode='human' needs a display"):
        check_env(env.unwrapped)  # makes and renders each of metadata's modes, "human" too
    env.close()


def test_human_without_a_display_warns_and_runs_headless(monkeypatch) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.setattr("sys.platform", "linux")
    with pytest.warns(RuntimeWarning, match=r"render_mode='human' needs a display"):
        env = gym.make(ROLL, render_mode="human")
    assert env.unwrapped.backend.gui is False
    env.reset(seed=0)
    assert env.render() is None
    env.close()


def test_importing_pybullet_prints_no_banner_and_stderr_comes_back() -> None:
    import subprocess
    import sys

    code = "import sys, tensegrity_gym.sim.world, pybullet; print('still here', file=sys.stderr)"
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True
    )
    assert "pybullet build time" not in done.stderr
    assert "pybullet build time" not in done.stdout
    assert done.stderr.strip() == "still here"


@pytest.mark.parametrize("command", ["train", "record", "gait"])
def test_subcommand_help_shows_defaults_and_the_registered_ids(command: str, capsys) -> None:
    from agents.cli import main

    with pytest.raises(SystemExit) as done:
        main([command, "--help"])
    assert done.value.code == 0
    text = " ".join(capsys.readouterr().out.split())  # argparse wraps lines
    assert "tensegrity_gym/SuperBallGoTo-v0" in text  # a registered id, not only the default
    assert "(default: tensegrity_gym/ThreeBarRoll-v0)" in text
    assert "(default: ukf)" in text
    assert "(default: None)" not in text


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"policy": "no/such/run"}, "no training run at that path"),
        ({"policy": "scripted", "estimator": "nope"}, "nope"),
    ],
)
def test_a_failed_record_leaves_no_folder_it_made(tmp_path, kwargs, message: str) -> None:
    from agents.recordings.offline import record

    out = tmp_path / "new" / "bags"
    with pytest.raises(ValueError, match=message):
        record(ROLL, episodes=1, out=out, steps=2, **kwargs)
    assert list(tmp_path.iterdir()) == []  # neither bags/ nor new/
    existing = tmp_path / "mine"
    existing.mkdir()
    with pytest.raises(ValueError, match=message):
        record(ROLL, episodes=1, out=existing, steps=2, **kwargs)
    assert existing.is_dir()  # the user's own folder stays


def test_a_record_that_wrote_a_bag_keeps_it(tmp_path) -> None:
    from agents.recordings.offline import record

    paths = record(ROLL, "random", 1, tmp_path / "out", steps=2)
    assert paths and all(p.exists() for p in paths)


def _rl_zoo3_commands() -> dict[str, list[str]]:
    """The training page's rl-zoo3 commands (``train``, ``enjoy``), as written."""
    import re
    import shlex
    from pathlib import Path

    text = (Path(__file__).parents[2] / "docs" / "training.md").read_text()
    found = {}
    for line in re.findall(r"^python -m rl_zoo3\.\w+ .*?[^\\]$", text, re.M | re.S):
        command = shlex.split(line.replace("\\\n", " "))
        found[command[2].removeprefix("rl_zoo3.")] = command
    assert set(found) == {"train", "enjoy"}, "docs/training.md: an rl-zoo3 command is gone"
    return found


@pytest.mark.slow
def test_the_rl_zoo3_commands_train_and_enjoy(tmp_path) -> None:
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    commands = _rl_zoo3_commands()
    configs = Path(__file__).parents[2] / "agents" / "training" / "configs"
    shutil.copytree(configs, tmp_path / "agents" / "training" / "configs")  # relative path
    tiny = {
        "train": ["--n-timesteps", "64", "--hyperparams", "n_envs:1", "n_steps:32",
                  "batch_size:32"],
        "enjoy": ["-n", "20"],
    }  # fmt: skip
    for name in ("train", "enjoy"):
        done = subprocess.run(
            [sys.executable, *commands[name][1:], *tiny[name]],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert done.returncode == 0, f"{name}: {done.stderr[-2000:]}"
    assert list((tmp_path / "logs" / "ppo").glob("*/tensegrity_gym-ThreeBarRoll-v0.zip"))
