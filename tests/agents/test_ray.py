"""Training, evaluation and offline estimation on a Ray cluster: two Ray nodes on this
machine (``ray.cluster_utils.Cluster``), shared by the whole module."""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest
import yaml

ray = pytest.importorskip("ray")

from gymnasium.wrappers import TimeLimit  # noqa: E402
from stable_baselines3.common.callbacks import BaseCallback  # noqa: E402
from stable_baselines3.common.env_util import make_vec_env  # noqa: E402
from stable_baselines3.common.monitor import Monitor  # noqa: E402

from agents.cli import main  # noqa: E402
from agents.evaluation.evaluate import condition, evaluate_policies, load_policy  # noqa: E402
from agents.training.cluster import LocalExecutor, RayExecutor  # noqa: E402
from agents.training.cluster.vec_env import RayVecEnv  # noqa: E402
from agents.training.train import qualified_id, train  # noqa: E402
from tests.agents.test_train import _tiny_config  # noqa: E402

if TYPE_CHECKING:
    from collections.abc import Iterator
    from pathlib import Path

pytestmark = pytest.mark.xdist_group("ray_cluster")  # one cluster, in one worker

THREE_BAR = "tensegrity_gym/ThreeBarRoll-v0"
ORACLE = {"estimator": "oracle", "max_episode_steps": 12}


@pytest.fixture(scope="module")
def cluster() -> Iterator[str]:
    """Two Ray nodes of 2 CPUs each on this machine, each with a small object store
    (what the tests pass is small); the address of the head."""
    from ray.cluster_utils import Cluster

    node = {"num_cpus": 2, "object_store_memory": 100 * 1024**2}
    made = Cluster(initialize_head=True, head_node_args=node)
    try:
        made.add_node(**node)
        ray.init(address=made.address, include_dashboard=False, log_to_driver=False)
        yield made.address
    finally:
        ray.shutdown()
        made.shutdown()


# ---------------------------------------------------------------------- the vec env


@pytest.fixture
def vec(cluster: str) -> Iterator[RayVecEnv]:
    """3 envs on 2 workers (2 + 1)."""
    venv = RayVecEnv(qualified_id(THREE_BAR), 3, 7, ORACLE, workers=2)
    yield venv
    venv.close()


def test_steps_as_a_dummy_vec_env_with_the_same_seeds_does(vec: RayVecEnv) -> None:
    """SB3's conventions, step for step: shapes, dtypes, auto-reset at an episode's
    end, terminal_observation, TimeLimit.truncated, and the seeds ``seed + i``."""
    ref = make_vec_env(qualified_id(THREE_BAR), n_envs=3, seed=7, env_kwargs=ORACLE)
    rng = np.random.default_rng(0)
    obs, ref_obs = vec.reset(), ref.reset()
    assert obs.shape == (3, *vec.observation_space.shape) and obs.dtype == ref_obs.dtype
    np.testing.assert_array_equal(obs, ref_obs)
    ended = 0
    for k in range(15):
        actions = rng.uniform(-1, 1, (3, *vec.action_space.shape)).astype(np.float32)
        if k % 2:
            vec.step_async(actions)
            obs, rewards, dones, infos = vec.step_wait()
        else:
            obs, rewards, dones, infos = vec.step(actions)
        ref_obs, ref_rewards, ref_dones, ref_infos = ref.step(actions)
        np.testing.assert_array_equal(obs, ref_obs)
        np.testing.assert_array_equal(rewards, ref_rewards)
        np.testing.assert_array_equal(dones, ref_dones)
        assert rewards.shape == dones.shape == (3,) and len(infos) == 3
        for info, ref_info in zip(infos, ref_infos, strict=True):
            assert info.keys() - {"episode"} == ref_info.keys() - {"episode"}
            if "terminal_observation" in info:
                ended += 1
                np.testing.assert_array_equal(
                    info["terminal_observation"], ref_info["terminal_observation"]
                )
                assert info["TimeLimit.truncated"]
    assert ended == 3  # each env's first episode ended at step 12
    ref.close()


def test_env_method_get_set_attr_seed_and_wrappers(vec: RayVecEnv) -> None:
    assert vec.get_attr("render_mode") == [None, None, None]
    vec.set_attr("lab_note", "a", indices=[0, 2])
    vec.set_attr("lab_note", "b", indices=1)
    assert vec.get_attr("lab_note") == ["a", "b", "a"]
    assert vec.get_attr("lab_note", indices=[2, 1]) == ["a", "b"]
    spaces = vec.env_method("get_wrapper_attr", "action_space", indices=[1, 2])
    assert spaces == [vec.action_space] * 2
    assert vec.env_method("get_wrapper_attr", name="render_mode", indices=0) == [None]
    assert vec.env_is_wrapped(TimeLimit) == [True] * 3
    assert vec.env_is_wrapped(Monitor, indices=[0]) == [False]  # the Monitor log is kept here
    with pytest.raises(AttributeError):
        vec.get_attr("no_such_attribute")
    assert vec.seed(11) == [11, 12, 13]
    first = vec.reset()
    vec.seed(11)
    np.testing.assert_array_equal(vec.reset(), first)
    vec.close()
    assert vec.workers == []


# ---------------------------------------------------------------------- training


class _Kept(logging.Handler):
    """Keeps the records it is handed."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


class _KillOneWorker(BaseCallback):
    """Kills worker 0's process after ``at`` steps of the first rollout; notes where the
    workers ran and every info that says its worker restarted."""

    def __init__(self, at: int) -> None:
        super().__init__()
        self.at = at
        self.nodes: set[str] = set()
        self.restarted = 0
        self.logged: list[str] = []

    def _on_step(self) -> bool:
        venv = self.training_env.unwrapped
        assert isinstance(venv, RayVecEnv)
        if self.n_calls == self.at:
            where = venv.where()
            self.nodes = {node for _, node in where}
            os.kill(where[0][0], signal.SIGKILL)
        self.restarted += sum(bool(i.get("worker_restarted")) for i in self.locals["infos"])
        return True


@pytest.fixture(scope="module")
def ray_run(cluster: str, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, _KillOneWorker]:
    """2,048 steps of PPO over 2 workers (2 envs each, rollouts of 4 x 256 steps), one
    killed mid-rollout."""
    tmp = tmp_path_factory.mktemp("ray_train")
    killer = _KillOneWorker(at=100)
    config = _tiny_config(tmp, n_steps=256, batch_size=256, n_epochs=1)
    logger = logging.getLogger("agents.training.cluster.vec_env")
    handler = _Kept()
    logger.addHandler(handler)
    try:
        train(
            THREE_BAR, "ppo", "oracle", tmp / "run", timesteps=2048, seed=3, n_envs=4,
            config_file=config, progress_bar=False, checkpoint_every=1024,
            env_kwargs={"max_episode_steps": 50}, callbacks=[killer], ray_address=cluster,
            workers=2,
        )  # fmt: skip
    finally:
        logger.removeHandler(handler)
    killer.logged = [r.getMessage() for r in handler.records]
    return tmp / "run", killer


@pytest.mark.slow  # a PPO run over two nodes (the fixture) is the module's heaviest part
def test_training_over_two_nodes_survives_a_killed_worker(
    ray_run: tuple[Path, _KillOneWorker],
) -> None:
    run, killer = ray_run
    assert len(killer.nodes) == 2  # one worker on each node
    assert killer.restarted == 2  # the killed worker's two envs ended their episodes
    config = yaml.safe_load((run / "config.yaml").read_text())
    assert config["completed_timesteps"] >= 2048 and not config["interrupted"]
    assert config["worker_restarts"] == 1 and config["ray_workers"] == 2
    for name in ("model.zip", "vecnormalize.pkl", "monitor/ray.monitor.csv"):
        assert (run / name).is_file(), name
    assert sorted(p.name for p in (run / "checkpoints").iterdir())[0].startswith("model_")
    events = list((run / "tb").rglob("events.out.tfevents.*"))
    assert any(b"ray/worker_restarts" in f.read_bytes() for f in events)  # SB3's logger
    [warning] = killer.logged
    assert "Ray worker 0 died" in warning and "1 worker restarts" in warning


@pytest.mark.slow
def test_a_run_is_the_same_over_one_worker_or_two(cluster: str, tmp_path: Path) -> None:
    from stable_baselines3 import PPO

    config = _tiny_config(tmp_path, n_steps=128, batch_size=128, n_epochs=1)
    weights = []
    for workers in (1, 2):
        model = train(
            THREE_BAR, "ppo", "oracle", tmp_path / str(workers), timesteps=512, seed=5,
            n_envs=2, config_file=config, progress_bar=False,
            env_kwargs={"max_episode_steps": 40}, ray_address=cluster, workers=workers,
        )  # fmt: skip
        weights.append(PPO.load(model).policy.state_dict())
    for name, value in weights[0].items():
        assert value.equal(weights[1][name]), name


def test_an_unreachable_cluster_is_one_line_within_the_timeout(tmp_path: Path) -> None:
    run = subprocess.run(
        [sys.executable, "-m", "agents.cli", "train", "--ray", "127.0.0.1:9", "--out",
         str(tmp_path / "t"), "--estimator", "oracle", "--timesteps", "64"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert run.returncode == 2
    errors = [ln for ln in run.stderr.splitlines() if ln.startswith("ERROR")]
    assert len(errors) == 1 and "cannot reach the Ray cluster" in errors[0], run.stderr
    assert "Traceback" not in run.stderr


# ---------------------------------------------------------------------- evaluation


@pytest.mark.slow  # the two-node PPO run, then 1,000-step UKF episodes here and there
@pytest.mark.filterwarnings("ignore:No artists with labels")  # the report's error plot: no UKF
def test_evaluation_on_ray_gives_the_numbers_it_gives_here(
    ray_run: tuple[Path, _KillOneWorker], tmp_path: Path
) -> None:
    # The trained policy alone here (the random one is the report's below): each
    # policy is a 1,000-step UKF episode on each side.
    policies = [load_policy(ray_run[0])]
    conditions = [condition("ukf")]
    here = evaluate_policies(policies, conditions, 1, 1000, LocalExecutor())
    there = evaluate_policies(policies, conditions, 1, 1000, RayExecutor())
    for name, by_condition in here.items():
        for cond, episodes in by_condition.items():
            for a, b in zip(episodes, there[name][cond], strict=True):
                assert a.episode_return == b.episode_return
                np.testing.assert_array_equal(a.true_path, b.true_path)
                np.testing.assert_array_equal(a.est_path, b.est_path)
    assert main(["evaluate", str(ray_run[0]), "--episodes", "1", "--conditions", "oracle",
                 "--out", str(tmp_path / "report"), "--ray", "auto"]) == 0  # fmt: skip
    report = json.loads((tmp_path / "report" / "report.json").read_text())
    assert report["results"]["random"]["oracle"]["episodes"] == 1


# ---------------------------------------------------------------------- estimation


def _comparable(metrics: dict[str, Any]) -> dict[str, Any]:
    """The metrics but the wall time and what follows from it."""
    return {k: v for k, v in metrics.items() if k not in ("wall_s", "realtime_factor")}


@pytest.mark.slow  # the estimation study's replays, here and on the cluster: over 20 s
def test_estimation_on_ray_gives_the_results_it_gives_here(
    cluster: str, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    from agents.recordings.offline import record

    bags = tmp_path / "bags"
    record(THREE_BAR, "scripted", 2, bags, steps=30, seed=4, estimator="oracle")
    assert main(["estimate", str(bags), "--out", str(tmp_path / "here"), "--no-progress"]) == 0
    with caplog.at_level(logging.INFO):
        assert main(["estimate", str(bags), "--out", str(tmp_path / "there"),
                     "--ray", cluster]) == 0  # fmt: skip
    for episode in ("episode_000", "episode_001"):
        here, there = tmp_path / "here" / episode, tmp_path / "there" / episode
        assert sorted(p.name for p in here.iterdir()) == sorted(p.name for p in there.iterdir())
        a = json.loads((here / "metrics.json").read_text())
        b = json.loads((there / "metrics.json").read_text())
        assert _comparable(a) == _comparable(b) and "com_rmse_m" in a
        for name in ("estimate.tum", "truth.tum"):
            assert (here / name).read_bytes() == (there / name).read_bytes()


@pytest.mark.slow
def test_the_estimation_study_maps_its_replays_on_ray(cluster: str) -> None:
    from agents.benchmarks.estimation import bench_estimation

    here = bench_estimation(seeds=(0,), steps=30)
    there = bench_estimation(seeds=(0,), steps=30, executor=RayExecutor())
    assert here == there and len(here["table"]) == 9


@pytest.mark.slow
def test_the_ray_bench_measures_its_figures(cluster: str) -> None:
    from agents.benchmarks.ray_cluster import bench_ray

    result = bench_ray(steps=20, turn=10)
    assert set(result["env_steps_per_s"]) == {
        "in_process_1_env", "subproc_2_workers", "ray_1_worker", "ray_2_workers",
        "ray_2_workers_of_2_envs",
    }  # fmt: skip
    assert all(rate > 0 for rate in result["env_steps_per_s"].values())
    sizing = result["sizing"]
    assert (
        sizing["t_env_ms"] > 0 and sizing["t_call_ms"] > 0 and sizing["t_learn_ms_per_env_step"] > 0
    )
