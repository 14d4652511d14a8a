"""Training with stable-baselines3, evaluation, the report, and their bad input."""

from __future__ import annotations

import json
import pickle
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import yaml
from stable_baselines3.common.callbacks import BaseCallback

import tensegrity_gym
from agents.demo import across_seeds, against_reference, run_main_job_seeds
from agents.evaluation.evaluate import (
    CONDITIONS,
    count_rolls,
    evaluate_policy,
    goal_reached,
    load_policy,
)
from agents.evaluation.report import _gait_share, _monitor_curve, write_report
from agents.training.train import load_hyperparams, parse_config_value, train
from tensegrity_gym.model.description import load_robot

THREE_BAR = "tensegrity_gym/ThreeBarRoll-v0"


def _tiny_config(tmp: Path, **overrides: Any) -> Path:
    """A PPO config small enough to train in seconds (``overrides``: other values)."""
    config = {
        THREE_BAR: {
            "n_envs": 1,
            "policy": "MlpPolicy",
            "normalize": "dict(norm_obs=True, norm_reward=True)",
            "n_steps": 64,
            "batch_size": 32,
            "n_epochs": 2,
            "policy_kwargs": "dict(net_arch=dict(pi=[16], vf=[16]))",
        }
        | overrides
    }
    path = tmp / "tiny.yml"
    path.write_text(yaml.safe_dump(config))
    return path


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    tmp = tmp_path_factory.mktemp("train")
    out = tmp / "run"
    train(
        THREE_BAR,
        "ppo",
        "oracle",
        out,
        timesteps=128,
        seed=3,
        config_file=_tiny_config(tmp),
        progress_bar=False,
        checkpoint_every=64,
        env_kwargs={"max_episode_steps": 50},  # episodes end, so the Monitor has a curve
        hyperparams={"gamma": 0.97},
    )
    return out


# ---------------------------------------------------------------------- configs


def test_shipped_configs_load_for_every_registered_id() -> None:
    ids = tensegrity_gym.env_ids(hardware=None)
    for algo in ("ppo", "sac"):
        for env_id in ids:
            params = load_hyperparams(algo, env_id)
            assert params["n_timesteps"] > 0 and params["policy"] == "MlpPolicy"
            assert isinstance(params["policy_kwargs"], dict)
            assert isinstance(params["normalize"], dict)


def test_config_values_are_read_without_eval() -> None:
    assert parse_config_value("dict(net_arch=dict(pi=[64, 64]), log_std_init=-0.5)", "x") == {
        "net_arch": {"pi": [64, 64]},
        "log_std_init": -0.5,
    }
    for bad in ("__import__('os').system('true')", "nn.ReLU", "dict(a=open('f'))"):
        with pytest.raises(ValueError, match="not a literal"):
            parse_config_value(bad, "policy_kwargs")
    with pytest.raises(ValueError, match="not an expression"):
        parse_config_value("dict(", "policy_kwargs")


def test_hyperparams_are_put_over_the_configs() -> None:
    """``--hyperparams`` (rl-zoo3's): each given key replaces the config's, a
    ``dict(...)`` text is parsed as the config's is, and the others stay."""
    base = load_hyperparams("ppo", THREE_BAR)
    given = {"learning_rate": 1e-4, "policy_kwargs": "dict(log_std_init=-2.0)"}
    params = load_hyperparams("ppo", THREE_BAR, overrides=given)
    assert params["learning_rate"] == 1e-4 and params["policy_kwargs"] == {"log_std_init": -2.0}
    assert {k: v for k, v in params.items() if k not in given} == {
        k: v for k, v in base.items() if k not in given
    }
    with pytest.raises(ValueError, match=r"^--hyperparams: unknown keys \['lr'\] for ppo"):
        load_hyperparams("ppo", THREE_BAR, overrides={"lr": 1e-4})
    with pytest.raises(ValueError, match=r"^--hyperparams.policy_kwargs: 'open\(1\)' is not"):
        load_hyperparams("ppo", THREE_BAR, overrides={"policy_kwargs": "dict(a=open(1))"})


def test_bad_config_keys_ids_estimators_and_algorithms_fail_with_the_choices(
    tmp_path: Path,
) -> None:
    config = tmp_path / "bad.yml"
    config.write_text(yaml.safe_dump({THREE_BAR: {"n_steps": 64, "learning_rat": 0.1}}))
    with pytest.raises(ValueError, match=r"unknown keys \['learning_rat'\].*learning_rate"):
        load_hyperparams("ppo", THREE_BAR, config)
    with pytest.raises(ValueError, match="no entry for 'tensegrity_gym/Nope-v0'"):
        load_hyperparams("ppo", "tensegrity_gym/Nope-v0")
    with pytest.raises(
        ValueError, match=r"unknown algorithm 'dqn'; valid choices: \['ppo', 'sac'\]"
    ):
        load_hyperparams("dqn", THREE_BAR)
    with pytest.raises(ValueError, match="unknown estimator 'kalman'"):
        train(THREE_BAR, "ppo", "kalman", tmp_path / "x")
    with pytest.raises(ValueError, match=r"unknown env id.*ThreeBarRoll-v0"):
        train("tensegrity_gym/Nope-v0", "ppo", "ukf", tmp_path / "x")
    with pytest.raises(ValueError, match=r"unknown argument 'ctrl_cst'.*'ctrl_cost'"):
        train(THREE_BAR, "ppo", "ukf", tmp_path / "x", env_kwargs={"ctrl_cst": 0.0})
    with pytest.raises(ValueError, match=r"\['task'\]: the env id names the robot and the task"):
        train(THREE_BAR, "ppo", "ukf", tmp_path / "x", env_kwargs={"task": "goto"})
    assert not (tmp_path / "x").exists()  # refused before the run folder is made


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--env-kwargs", "ctrl_cost"], "expected KEY:VALUE, got 'ctrl_cost'"),
        (["--env-kwargs", "terrain:valley"], "terrain: 'valley' is not a Python literal"),
        (["--env-kwargs", "estimator:'icp'"], "--env-kwargs estimator: use --estimator"),
        (
            ["--env-kwargs", "ctrl_cost:0.1", "--env-kwargs", "ctrl_cost:0.2"],
            "ctrl_cost is given twice",
        ),
        (["--env-kwargs", "robot:'three_bar_large'"], "--env-kwargs robot: use --env"),
        (["--hyperparams", "gamma:0.9", "gamma:0.8"], "--hyperparams gamma is given twice"),
        (["--hyperparams", "gama:0.9"], "--hyperparams: unknown keys ['gama'] for ppo"),
        (["--hyperparams", "gamma:0.9.9"], "--hyperparams gamma: '0.9.9' is not a Python literal"),
        (["--moves", "steer", "--algo", "sac"], "sac cannot take (a discrete action)"),
        (["--moves", "steer", "--residual-gait", "0.5"], "leave out --residual-gait"),
        (["--move-tempos", "15/0"], "--move-ranks set the choice of --moves: give --moves"),
        (["--moves", "steer", "--move-ranks", "9"], "ranks must be a whole number from 1 to"),
        (["--moves", "steer", "--move-tempos", "15-0"], "must be HOLD/SETTLE control steps"),
        (["--moves", "steer", "--move-tempos", "5/0"], "tempo [5, 0]: a tempo is (hold, settle)"),
        (
            ["--moves", "forward", "--env", "tensegrity_gym/ThreeBarGoTo-v0"],
            "--moves forward: MoveChoice: the gait 'forward' of three_bar has one entry a face",
        ),
    ],
)
def test_bad_env_kwargs_are_one_line_and_exit_2(
    argv: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str],
    caplog: pytest.LogCaptureFixture,
) -> None:  # fmt: skip
    from agents.cli import main

    try:
        code = main(["train", "--out", str(tmp_path / "t"), *argv])
    except SystemExit as exit_:  # argparse refuses a malformed value itself
        code = int(exit_.code or 0)
    assert code == 2
    assert message in capsys.readouterr().err + caplog.text
    assert not (tmp_path / "t").exists()


# ---------------------------------------------------------------------- training


def test_training_writes_model_statistics_config_logs_and_checkpoints(tiny_run: Path) -> None:
    for name in ("model.zip", "vecnormalize.pkl", "config.yaml"):
        assert (tiny_run / name).stat().st_size > 0
    config = yaml.safe_load((tiny_run / "config.yaml").read_text())
    assert config["env_id"] == THREE_BAR and config["estimator"] == "oracle"
    assert config["seed"] == 3 and config["completed_timesteps"] == 128
    assert config["hyperparams"]["n_steps"] == 64 and not config["interrupted"]
    assert config["diverged"] is None
    assert config["hyperparams"]["gamma"] == 0.97  # --hyperparams, over the config's
    assert sorted(p.name for p in (tiny_run / "checkpoints").glob("*.zip")) == [
        "model_128_steps.zip",
        "model_64_steps.zip",
    ]
    assert list((tiny_run / "monitor").glob("*.monitor.csv"))
    assert list((tiny_run / "tb").rglob("events.out.tfevents.*"))  # TensorBoard reads these


def test_a_trained_policy_loads_and_acts_on_the_env(tiny_run: Path) -> None:
    policy = load_policy(tiny_run)
    assert policy.env_id == THREE_BAR and policy.trained_on == "oracle"
    results = evaluate_policy(policy, CONDITIONS["ukf"], episodes=1, seed=5)
    [r] = results
    assert np.isfinite(r.progress) and r.true_path.shape[1] == 3
    assert r.com_error_mean > 0.0  # the UKF is not the truth
    again = evaluate_policy(policy, CONDITIONS["ukf"], episodes=1, seed=5)
    assert again[0].progress == r.progress  # the same seed, the same episode


def test_a_policy_of_moves_trains_and_evaluates_through_the_gait(tmp_path: Path) -> None:
    """``train --moves steer``: PPO picks the steering gait's moves, a step a gait
    period; the run keeps ``moves``, and its policy drives the plain env step by step
    (MovePolicy; its episodes equal the wrapper's: tests/envs/test_moves.py)."""
    goto = "tensegrity_gym/ThreeBarGoTo-v0"
    out = tmp_path / "moves"
    train(goto, "ppo", "oracle", out, timesteps=16, seed=1, progress_bar=False,
          config_file=_tiny_config(tmp_path, use_sde=True, sde_sample_freq=8, n_steps=16,
                                   batch_size=16),
          env_kwargs={"max_episode_steps": 140}, moves="steer",
          move_tempos=[(25, 10)], move_ranks=2)  # fmt: skip
    config = yaml.safe_load((out / "config.yaml").read_text())
    assert config["moves"] == "steer" and config["completed_timesteps"] == 16
    assert config["move_tempos"] == [[25, 10]]  # the gait's own again: same periods
    assert config["move_ranks"] == 2
    assert config["hyperparams"]["use_sde"] is False  # gSDE is for continuous actions
    # The Monitor, beneath the choice, counts control steps: four periods of 35.
    log = next((out / "monitor").glob("*.monitor.csv"))
    lengths = np.loadtxt(log, delimiter=",", skiprows=2, usecols=1, ndmin=1)
    assert len(lengths) == 4 and set(lengths) == {140.0}
    policy = load_policy(out)
    assert policy.env_kwargs == {}  # the plain env's actions, the gait in the policy
    [episode] = evaluate_policy(policy, CONDITIONS["oracle"], episodes=1, seed=7)
    assert len(episode.true_path) == 601  # the id's own 600 control steps (60 s)
    assert np.isfinite(episode.progress) and episode.rolls > 0


@pytest.mark.slow  # 15 s; the default run is near its 15 minutes
def test_mismatch_conditions_evaluate_in_randomised_worlds(tiny_run: Path) -> None:
    """``oracle_strong``: the same policy and seed in a world drawn from the strong
    randomisation moves the robot otherwise than in the nominal world."""
    policy = load_policy(tiny_run)
    assert CONDITIONS["ukf_strong"].randomization == "strong"
    assert CONDITIONS["ukf_mild"].randomization == "mild"
    [nominal] = evaluate_policy(policy, CONDITIONS["oracle"], episodes=1, seed=5)
    [strong] = evaluate_policy(policy, CONDITIONS["oracle_strong"], episodes=1, seed=5)
    assert np.abs(strong.true_path - nominal.true_path).max() > 1e-3
    [again] = evaluate_policy(policy, CONDITIONS["oracle_strong"], episodes=1, seed=5)
    np.testing.assert_array_equal(again.true_path, strong.true_path)


def test_a_corrupted_or_foreign_model_gives_a_clear_error(tiny_run: Path, tmp_path: Path) -> None:
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "config.yaml").write_text((tiny_run / "config.yaml").read_text())
    (broken / "model.zip").write_bytes(b"not a zip at all")
    with pytest.raises(ValueError, match="cannot load a ppo model"):
        load_policy(broken)
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "model.zip").write_bytes((tiny_run / "model.zip").read_bytes())
    config = yaml.safe_load((tiny_run / "config.yaml").read_text())
    config["env_id"] = "tensegrity_gym/SuperBallRoll-v0"
    (foreign / "config.yaml").write_text(yaml.safe_dump(config))
    with pytest.raises(ValueError, match="a model of another env"):
        load_policy(foreign)
    with pytest.raises(ValueError, match="not a training run"):
        load_policy(tmp_path)


class _Interrupt(BaseCallback):
    def _on_step(self) -> bool:
        if self.num_timesteps >= 96:
            raise KeyboardInterrupt
        return True


def test_ctrl_c_during_training_leaves_a_usable_model(tmp_path: Path) -> None:
    out = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        train(
            THREE_BAR,
            "ppo",
            "oracle",
            out,
            timesteps=10_000,
            config_file=_tiny_config(tmp_path),
            progress_bar=False,
            callbacks=[_Interrupt()],
        )
    config = yaml.safe_load((out / "config.yaml").read_text())
    assert config["interrupted"] and 96 <= config["completed_timesteps"] < 10_000
    policy = load_policy(out)
    obs = np.zeros(gym.make(THREE_BAR).observation_space.shape, dtype=np.float32)
    assert policy.act(obs).shape == (6,)


def test_an_env_with_the_ukf_pickles_for_worker_processes() -> None:
    env = gym.make(THREE_BAR, estimator="ukf")
    env.reset(seed=0)
    env.step(env.action_space.sample())
    clone = pickle.loads(pickle.dumps(env.unwrapped))
    a, _ = clone.reset(seed=4)
    b, _ = env.unwrapped.reset(seed=4)
    assert np.array_equal(a, b)
    env.close()
    clone.close()


# ---------------------------------------------------------------------- evaluation


def test_count_rolls_counts_net_tips_onto_new_base_triangles() -> None:
    def heights(faces: list[tuple[int, ...]], repeat: int = 4) -> np.ndarray:
        z = []
        for face in faces:
            row = np.ones(6)
            row[list(face)] = 0.0
            z += [row] * repeat
        return np.array(z)

    assert count_rolls(heights([(0, 1, 2)])) == 0
    assert count_rolls(heights([(0, 1, 2), (1, 2, 3), (2, 3, 4)])) == 2
    assert count_rolls(heights([(0, 1, 2), (1, 2, 3), (0, 1, 2), (1, 2, 3)])) == 1  # rocking
    assert count_rolls(heights([(0, 1, 2), (1, 2, 3)], repeat=2)) == 0  # too brief to count


def test_a_goal_counts_as_reached_in_truth_only() -> None:
    """Success on a go-to id: the true CoM within the radius of the goal in force after
    a step; a goal passed before it was in force, or an estimate near it, does not count."""
    true = np.array([[0.0, 0.0, 0.2], [0.5, 0.0, 0.2], [0.9, 0.0, 0.2], [0.9, 0.5, 0.2]])
    goals = np.array([[1.0, 0.0], [1.0, 0.0], [3.0, 0.0]])
    assert goal_reached(true, goals, 0.15)  # after the second step: 0.1 m from it
    assert not goal_reached(true, goals, 0.05)
    far = np.array([[0.9, 0.0], [5.0, 5.0], [5.0, 5.0]])  # near the CoM only before step 1
    assert not goal_reached(true, far, 0.15)
    assert not goal_reached(true[:1], np.zeros((0, 2)), 1.0)


@pytest.mark.slow  # 35-42 s on a fresh clone; the default run is at its 15 minutes
def test_report_compares_policies_under_conditions(tiny_run: Path, tmp_path: Path) -> None:
    report = write_report(
        [tiny_run], tmp_path / "report", episodes=1, conditions=("oracle", "ukf_4_anchors")
    )
    assert set(report["results"]) == {
        "trained on oracle",
        "random",
        "scripted gait",
        "steering gait",
    }
    steering = report["results"]["steering gait"]["oracle"]
    assert steering["progress_mean_m"] > 0.3, steering  # it rolls toward the goal
    # The gait rolls (some 1.5 m in 30 s), the random policy hardly moves.
    gait, random = report["results"]["scripted gait"], report["results"]["random"]
    assert gait["oracle"]["progress_mean_m"] > 0.5 > abs(random["oracle"]["progress_mean_m"])
    row = report["results"]["trained on oracle"]["ukf_4_anchors"]
    assert row["episodes"] == 1 and row["com_error_mean_m"] > 0
    assert report["results"]["random"]["oracle"]["com_error_mean_m"] == 0.0
    check = report["checks"]["trained on oracle"]
    assert check["condition"] == "oracle" and "progress_vs_random" in check
    trained = report["results"]["trained on oracle"]["oracle"]["progress_mean_m"]
    gait_progress = gait["oracle"]["progress_mean_m"]
    assert check["progress_vs_gait"] == round(trained / gait_progress, 2)
    # The gait rolled at least as far as it progressed toward the goal.
    assert gait["oracle"]["distance_mean_m"] >= abs(gait["oracle"]["progress_mean_m"]) - 1e-3
    assert check["gait_distance_m"] == gait["oracle"]["distance_mean_m"]
    assert check["progress_vs_gait_distance"] == round(
        trained / gait["oracle"]["distance_mean_m"], 2
    )
    backwards = {**check, "gait_progress_m": -0.5, "progress_vs_gait": None}
    assert _gait_share({**backwards, "gait_target_met": False}).startswith(
        "; the scripted gait made no progress toward the goal (-0.50 m; target, progress of "
        "its own: NOT met), and "
    )
    # Speed in rod lengths per second: the progress over the episode's seconds.
    length = load_robot("three_bar").characteristic_length
    assert steering["speed_m_per_s"] == pytest.approx(steering["progress_mean_m"] / 30.0, rel=0.02)
    assert steering["speed_rod_lengths_per_s"] == pytest.approx(
        steering["speed_m_per_s"] / length, rel=0.02
    )
    assert check["steering_progress_m"] == steering["progress_mean_m"]
    text = (tmp_path / "report" / "report.md").read_text()
    headline = text.split("## Headline")[1].split("##")[0]
    assert "- **trained on oracle**, under `oracle`:" in headline
    assert "the steering gait's" in headline and "rod lengths/s" in headline
    assert "of the scripted gait's progress" in text and "| scripted gait | oracle |" in text
    assert "of the distance the gait rolls its own way" in text
    assert "| trained on oracle | ukf_4_anchors |" in text and "![CoM paths]" in text
    for name in ("com_paths.png", "estimation_error.png", "training.png", "report.json"):
        assert (tmp_path / "report" / name).stat().st_size > 0
    assert json.loads((tmp_path / "report" / "report.json").read_text())["env"] == THREE_BAR
    with pytest.raises(ValueError, match="unknown condition"):
        write_report([tiny_run], tmp_path / "r2", conditions=("ukf", "fog"))


def test_the_training_curve_reads_monitor_logs_in_the_order_episodes_ended(
    tmp_path: Path,
) -> None:
    """SB3's reader puts the episodes of every log on one clock; no log, no curve; a
    broken log is one line naming the folder."""
    monitor = tmp_path / "monitor"
    monitor.mkdir()
    assert _monitor_curve(tmp_path) is None
    header = "r,l,t\n"
    (monitor / "0.monitor.csv").write_text(
        '#{"t_start": 100.0}\n' + header + "1.0,10,2.0\n3.0,30,9.0\n"
    )
    (monitor / "1.monitor.csv").write_text('#{"t_start": 104.0}\n' + header + "2.0,20,1.0\n")
    curve = _monitor_curve(tmp_path)
    assert curve is not None
    np.testing.assert_array_equal(curve[0], [10, 30, 60])
    np.testing.assert_array_equal(curve[1], [1.0, 2.0, 3.0])
    (monitor / "1.monitor.csv").write_text("r,l,t\n")
    with pytest.raises(ValueError, match=r"monitor: a Monitor log lacks its '#\{\.\.\.\}' header"):
        _monitor_curve(tmp_path)
    (monitor / "1.monitor.csv").write_text('#{"t_start": 104.0}\nr,l,t\n2.0,2x,1.0\n')
    with pytest.raises(ValueError, match=r"monitor: unreadable Monitor log \(") as e:
        _monitor_curve(tmp_path)
    assert str(monitor) in str(e.value) and "\n" not in str(e.value)
    (monitor / "1.monitor.csv").write_text('#{"t_start": 104.0}\nr,l,t\n')
    (monitor / "0.monitor.csv").write_text('#{"t_start": 100.0}\nr,l,t\n')
    assert _monitor_curve(tmp_path) is None  # no episode ended


@pytest.mark.slow
def test_training_is_reproducible_over_its_first_10000_steps(tmp_path: Path) -> None:
    def rewards(out: Path) -> list[str]:
        train(THREE_BAR, "ppo", "ukf", out, timesteps=10_240, seed=7, progress_bar=False)
        rows = []
        for f in sorted((out / "monitor").glob("*.monitor.csv")):
            rows += [line.split(",")[:2] for line in f.read_text().splitlines()[2:]]
        return [",".join(r) for r in rows]

    first, second = rewards(tmp_path / "a"), rewards(tmp_path / "b")
    assert len(first) >= 30  # 10,240 steps: 34 episodes of 300 steps
    assert first == second


def test_record_takes_a_training_run_as_its_policy(tiny_run: Path) -> None:
    from agents.recordings.offline import make_policy

    env = gym.make(THREE_BAR, estimator="oracle")
    obs, _ = env.reset(seed=0)
    for path in (tiny_run, tiny_run / "model.zip"):
        act, _ = make_policy(str(path), env, 0)
        # the same action as the evaluated policy: observations normalised as in training
        assert np.array_equal(act(obs), load_policy(tiny_run).act(obs))
    env.close()
    with pytest.raises(ValueError, match="no training run at that path"):
        make_policy("nowhere/run", env, 0)


def test_figures_across_seeds_give_mean_spread_and_each_seed() -> None:
    def report(progress: float, rolls: float) -> dict[str, Any]:
        row = {
            "progress_mean_m": progress,
            "distance_mean_m": 2 * progress,
            "rolls_per_episode": rolls,
            "success_rate": 0.5,
            "com_error_mean_m": 0.01,
        }
        return {"results": {"trained on ukf": {"ukf": row, "oracle": row}}}

    summary = across_seeds({2: report(0.3, 1.0), 0: report(0.1, 3.0)})
    assert summary["seeds"] == [0, 2]
    progress = summary["results"]["trained on ukf"]["ukf"]["progress_mean_m"]
    assert progress == {"mean": 0.2, "std": 0.1, "min": 0.1, "max": 0.3, "per_seed": [0.1, 0.3]}
    rolls = summary["results"]["trained on ukf"]["oracle"]["rolls_per_episode"]
    assert rolls["mean"] == 2.0 and rolls["per_seed"] == [3.0, 1.0]
    distance = summary["results"]["trained on ukf"]["ukf"]["distance_mean_m"]
    assert distance["per_seed"] == [0.2, 0.6]
    with pytest.raises(ValueError, match="distinct seeds"):
        run_main_job_seeds(Path("unused"), [1, 1])


def test_one_seed_states_its_result_against_the_multi_seed_run() -> None:
    def row(progress: float, rolls: float) -> dict[str, Any]:
        return {"progress_mean_m": progress, "rolls_per_episode": rolls}

    def spread(mean: float, lo: float, hi: float) -> dict[str, float]:
        return {"mean": mean, "std": 0.01, "min": lo, "max": hi}

    settings = {"ukf_timesteps": 10, "oracle_timesteps": 0, "episodes": 1, "residual_gait": 0.5}
    reference = {
        "seeds": [0, 1, 2],
        "settings": settings,
        "results": {
            "trained on ukf": {
                "ukf": {
                    "progress_mean_m": spread(0.37, 0.36, 0.38),
                    "rolls_per_episode": spread(3.0, 2.2, 4.4),
                }
            },
            "random policy": {"ukf": {}},
        },
    }
    report = {"results": {"trained on ukf": {"ukf": row(0.30, 2.5)}}}
    lines = against_reference(report, settings, reference)
    assert lines[-1] == (
        "- **trained on ukf** under `ukf`: progress (m) 0.30 against 0.37 ± 0.01 "
        "[0.36, 0.38] (outside the seeds' range); rolls 2.50 against 3.00 ± 0.01 "
        "[2.20, 4.40] (within the seeds' range)."
    )
    other = against_reference(report, {**settings, "residual_gait": None}, reference)
    assert "not compared" in other[0]
    assert "No multi-seed run" in against_reference(report, settings, None)[0]


def test_the_stored_multi_seed_run_ran_with_the_demos_own_settings() -> None:
    """A one-seed demo with its defaults is set against ``demo_seeds.json``: that run's
    settings must be the defaults, or the comparison is never made."""
    import inspect

    from agents.demo import demo_settings, load_reference, run_main_job

    reference = load_reference()
    assert reference is not None
    parameters = inspect.signature(run_main_job).parameters
    own = inspect.signature(demo_settings).parameters
    assert reference["settings"] == demo_settings(**{k: parameters[k].default for k in own})
    assert set(reference["seeds"]) >= {0, 1, 2}


@pytest.mark.slow
def test_the_demo_over_two_seeds_writes_each_report_and_the_summary(tmp_path: Path) -> None:
    summary = run_main_job_seeds(
        tmp_path, [0, 1], ukf_timesteps=256, oracle_timesteps=0, episodes=1, progress_bar=False
    )
    assert summary["seeds"] == [0, 1]
    for seed in (0, 1):
        assert (tmp_path / f"seed_{seed}" / "report" / "report.md").exists()
    gait = summary["results"]["scripted gait"]["ukf"]["progress_mean_m"]
    assert len(gait["per_seed"]) == 2 and gait["min"] <= gait["mean"] <= gait["max"]
    text = (tmp_path / "seeds.md").read_text()
    assert "| scripted gait | ukf |" in text and "±" in text
    assert "- seed 1, **trained on ukf** under `ukf`: " in text and "rolls per episode" in text


@pytest.mark.slow  # 21 s; the default run is near its 15 minutes
def test_a_policy_trained_in_randomised_worlds_is_named_so(tmp_path: Path) -> None:
    out = tmp_path / "run"
    train(
        THREE_BAR,
        "ppo",
        "oracle",
        out,
        timesteps=64,
        seed=3,
        config_file=_tiny_config(tmp_path),
        progress_bar=False,
        env_kwargs={"max_episode_steps": 20, "randomization": "mild"},
    )
    policy = load_policy(out)
    assert policy.name == "trained on oracle in mild worlds"
    assert policy.env_kwargs == {}  # the condition says which worlds it is evaluated in
    assert load_policy(out, "mine").name == "mine"


def test_the_demo_runs_on_its_own_budget_unless_told(
    monkeypatch: pytest.MonkeyPatch,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    caplog: pytest.LogCaptureFixture,
) -> None:
    import agents.demo
    from agents.cli import main

    given: list[dict[str, Any]] = []

    def fake(out: Path, **kwargs: Any) -> dict[str, Any]:
        given.append(kwargs)
        return {"checks": {}, "timing_s": {}}

    monkeypatch.setattr(agents.demo, "run_main_job", fake)
    assert main(["demo", "--out", str(tmp_path), "--no-progress"]) == 0
    assert "ukf_timesteps" not in given[0] and "oracle_timesteps" not in given[0]
    assert given[0]["residual_gait"] == agents.demo.RESIDUAL_GAIT
    budget = ["--timesteps", "7", "--oracle-timesteps", "0"]
    assert main(["demo", "--out", str(tmp_path), *budget]) == 0
    assert given[1]["ukf_timesteps"] == 7 and given[1]["oracle_timesteps"] == 0
    assert "wall time per stage" in capsys.readouterr().out
    assert "base_gait" not in given[0]  # the demo's own: the steering gait
    assert main(["demo", "--out", str(tmp_path), "--base-gait", "forward"]) == 0
    assert given[2]["base_gait"] == "forward"
    assert (
        main(["demo", "--out", str(tmp_path), "--base-gait", "forward", "--absolute-actions"]) == 2
    )
    assert "--absolute-actions policies correct none" in capsys.readouterr().err + caplog.text


def test_runs_of_the_same_name_are_told_apart_by_their_folders(tmp_path: Path) -> None:
    from agents.evaluation.report import _distinct_labels

    runs = [tmp_path / "seed_0" / "ppo_ukf", tmp_path / "seed_1" / "ppo_ukf", tmp_path / "x"]
    assert _distinct_labels(runs) == ["seed_0/ppo_ukf", "seed_1/ppo_ukf", "x"]
    with pytest.raises(ValueError, match=r"the run .*seed_0/ppo_ukf is given twice"):
        _distinct_labels([runs[0], runs[1], runs[0]])
    # named as given: a link keeps its own name, a folder at the root its own
    runs[0].parent.mkdir()
    (tmp_path / "latest").symlink_to(runs[0].parent)
    assert _distinct_labels([tmp_path / "latest" / "ppo_ukf", runs[1]]) == [
        "latest/ppo_ukf",
        "seed_1/ppo_ukf",
    ]
    assert _distinct_labels([Path("/ppo_ukf"), Path("/tmp/ppo_ukf")]) == ["/ppo_ukf", "tmp/ppo_ukf"]
    with pytest.raises(ValueError, match="given twice"):
        _distinct_labels([tmp_path / "latest" / "ppo_ukf", runs[0]])


@pytest.mark.parametrize(
    ("mine", "gait", "distance", "share", "met", "own_way"),
    [
        (0.10, 0.20, 1.5, 0.5, True, 0.07),  # half the gait's progress: met
        (0.0994, 0.20, 1.5, 0.5, True, 0.07),  # judged on the share as printed
        (0.09, 0.20, 1.5, 0.45, False, 0.06),
        (0.05, -0.30, 1.5, None, True, 0.03),  # the gait went backwards: progress is enough
        (-0.05, -0.30, 1.5, None, False, -0.03),
        (0.0, 0.0, 1.5, None, False, 0.0),
        (0.2, 0.1, 0.001, 2.0, True, None),  # a gait that stayed put: no share of its way
        (0.2, 0.1, float("nan"), 2.0, True, None),
    ],
)
def test_a_policy_is_set_against_the_gait_by_its_targets(
    mine: float, gait: float, distance: float, share: float | None, met: bool,
    own_way: float | None,
) -> None:  # fmt: skip
    from agents.evaluation.report import _checks, check_sentence

    def row(progress: float, rolls: float = 2.0, distance: float = 0.3) -> dict[str, float]:
        return {"progress_mean_m": progress, "rolls_per_episode": rolls,
                "distance_mean_m": distance}  # fmt: skip

    table = {
        "trained on ukf": {"ukf": row(mine)},
        "random": {"ukf": row(0.01, 0.2)},
        "scripted gait": {"ukf": row(gait, 9.0, distance)},
    }
    check = _checks(table, ["trained on ukf"], ["oracle", "ukf"])["trained on ukf"]
    assert check["condition"] == "ukf"
    assert check["progress_vs_gait"] == share and check["gait_target_met"] is met
    assert check["progress_vs_gait_distance"] == own_way
    sentence = check_sentence(check)
    assert ("target 50%: met" in sentence or "progress of its own: met" in sentence) is met
    assert ("rolls its own way" in sentence) is (own_way is not None)
    assert "nan" not in sentence


@pytest.mark.parametrize(("steering", "share"), [(1.0, 0.8), (-0.1, None)])
def test_a_policy_is_set_against_the_steering_gait_where_there_is_one(
    steering: float, share: float | None
) -> None:
    from agents.evaluation.report import _checks, check_sentence, steering_sentence

    def row(progress: float) -> dict[str, float]:
        return {"progress_mean_m": progress, "rolls_per_episode": 3.0, "distance_mean_m": 1.0}

    table = {"trained on ukf": {"ukf": row(0.8)}, "random": {"ukf": row(0.0)}}
    check = _checks(table, ["trained on ukf"], ["ukf"])["trained on ukf"]
    assert "steering_progress_m" not in check and "steering" not in check_sentence(check)
    table["steering gait"] = {"ukf": row(steering)}
    check = _checks(table, ["trained on ukf"], ["ukf"])["trained on ukf"]
    assert check["steering_progress_m"] == steering and check["progress_vs_steering"] == share
    sentence = check_sentence(check)
    assert f"steering gait made {steering:.2f} m" in sentence
    assert ("the policy made 80% of that" in sentence) is (share is not None)
    # 80 % of the gait is short of the 110 % target; ahead of a gait that went nowhere
    # any progress of its own meets it.
    assert check["steering_target_met"] is (share is None)
    assert ("target 110%: NOT met" in sentence) is (share is not None)
    headline = steering_sentence("trained on ukf", check)
    assert headline.startswith("**trained on ukf**, under `ukf`: 0.80 m toward the goal, ")
    assert "rod lengths/s against -" in headline and "nan" not in headline
    table["trained on ukf"]["ukf"] |= {"speed_rod_lengths_per_s": 0.02, "success_rate": 0.5}
    table["steering gait"]["ukf"] |= {"speed_rod_lengths_per_s": 0.01, "success_rate": 0.25}
    table["steering gait"]["ukf"]["progress_mean_m"] = 0.7
    ahead = _checks(table, ["trained on ukf"], ["ukf"])["trained on ukf"]
    assert ahead["progress_vs_steering"] == 1.14 and ahead["steering_target_met"]
    assert steering_sentence("p", ahead).endswith(
        "114% of the steering gait's 0.70 m (target 110%: met); 0.020 rod lengths/s against "
        "0.010; success 50 % against 25 %."
    )
