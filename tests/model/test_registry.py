"""Estimators by name: one registry read by make, estimate, train, evaluate and the
command line; a lab's estimator plugs in from outside the package (register_estimator
or an entry point); requirements are checked before anything runs."""

from __future__ import annotations

from importlib.metadata import EntryPoint
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
import pytest

from agents.cli import main
from agents.evaluation.evaluate import condition, evaluate_policy, random_policy
from agents.recordings.offline import estimate_bag
from tensegrity_gym.model import registry
from tensegrity_gym.model.estimate import Estimate
from tensegrity_gym.model.kinematics import center_of_mass
from tensegrity_gym.model.registry import ESTIMATORS, estimator_spec, register_estimator
from tensegrity_gym.model.samples import EncoderSample
from tensegrity_gym.sim.backend import SimBackend
from tests.hardware.test_bag_robustness import _rewrite

if TYPE_CHECKING:
    from collections.abc import Iterator, Sequence
    from pathlib import Path

    from numpy.typing import NDArray

ENV_ID = "tensegrity_gym/ThreeBarRoll-v0"


class RestShapeEstimator:
    """A lab's toy estimator, defined outside the package: the resting shape, never
    moving, with the encoders' rest lengths."""

    needs_camera = False

    def reset(self, description: Any, calibration: Any, samples: Sequence[Any],
              command: NDArray[np.float64], rng: np.random.Generator) -> Estimate:  # fmt: skip
        self.nodes = description.initial_positions
        self.com = center_of_mass(self.nodes, description.node_masses)
        self.rest = np.asarray(command, dtype=np.float64)
        self.t = 0.0
        return self.update(samples, command)

    def update(self, samples: Sequence[Any], command: NDArray[np.float64]) -> Estimate:
        for s in samples:
            if isinstance(s, EncoderSample):
                self.rest, self.t = s.rest_lengths, s.t
        zero = np.zeros_like(self.nodes)
        return Estimate(self.t, self.nodes, zero, self.com, self.rest)


@pytest.fixture
def toy() -> Iterator[str]:
    register_estimator("rest_shape", RestShapeEstimator, requires=("encoders",),
                       summary="the resting shape (a test's toy)")  # fmt: skip
    yield "rest_shape"
    ESTIMATORS.unregister("rest_shape")


def test_the_built_in_estimators_and_a_clear_unknown_name() -> None:
    assert {"ukf", "icp", "oracle"} <= set(ESTIMATORS.names())
    assert estimator_spec("icp").camera and "rgbd" in estimator_spec("icp").requires
    assert estimator_spec("oracle").ground_truth
    with pytest.raises(ValueError, match=r"unknown estimator 'kalman'; valid choices: \['ukf'"):
        gym.make(ENV_ID, estimator="kalman")
    with pytest.raises(ValueError, match="unknown kinds"):
        register_estimator("bad", RestShapeEstimator, requires=("lidar",))
    with pytest.raises(ValueError, match="already registered"):
        register_estimator("ukf", RestShapeEstimator)


def test_a_lab_estimator_runs_through_make_estimate_and_evaluate(toy: str, tmp_path: Path) -> None:
    env = gym.make(ENV_ID, estimator=toy, record_dir=tmp_path / "runs", max_episode_steps=25)
    assert isinstance(env.unwrapped.estimator.inner, RestShapeEstimator)  # type: ignore[attr-defined]
    env.reset(seed=0)
    for _ in range(25):  # 2.5 s: the metrics start after 2 s of settling
        obs, reward, *_ = env.step(env.action_space.sample())
        assert np.all(np.isfinite(obs)) and reward == pytest.approx(-0.05, abs=0.05)
    env.close()
    [metrics] = estimate_bag(tmp_path / "runs" / "episode_000", toy, tmp_path / "est",
                             progress=False)  # fmt: skip
    assert metrics["steps"] == 25 and (tmp_path / "est" / "metrics.json").exists()
    assert main(["estimate", str(tmp_path / "runs"), "--estimator", toy, "--out",
                 str(tmp_path / "cli"), "--no-progress"]) == 0  # fmt: skip
    results = evaluate_policy(random_policy(ENV_ID, 0), condition(toy), episodes=1, seed=3)
    assert len(results) == 1 and np.isfinite(results[0].episode_return)
    assert condition(toy).about == "the resting shape (a test's toy)"


def test_an_installed_package_registers_through_the_entry_point_group(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    group = "tensegrity_gym.estimators"
    found = [EntryPoint("rest_shape_ep", f"{__name__}:RestShapeEstimator", group),
             EntryPoint("broken_ep", "no_such_module:Thing", group)]  # fmt: skip
    monkeypatch.setattr(registry, "entry_points", lambda group: found)
    monkeypatch.setattr(ESTIMATORS, "_plugins_read", False)
    try:
        assert "rest_shape_ep" in ESTIMATORS.names()
        assert "broken_ep" not in ESTIMATORS.names()  # logged, the others still load
        env = gym.make(ENV_ID, estimator="rest_shape_ep")
        env.reset(seed=0)
        env.step(env.action_space.sample())
        env.close()
    finally:
        ESTIMATORS.unregister("rest_shape_ep")


class _NoCamera(SimBackend):
    """A robot without a camera."""

    def sample_kinds(self) -> frozenset[str]:
        return super().sample_kinds() - {"rgbd"}


def test_an_estimator_without_what_it_needs_is_refused_at_make() -> None:
    from tensegrity_gym.model.description import load_robot

    backend = _NoCamera(load_robot("three_bar"))
    with pytest.raises(ValueError, match=r"make: estimator 'icp' needs rgbd \(RGB-D camera"):
        gym.make(ENV_ID, estimator="icp", driver=backend)


def _drop_uwb(topic: str, msgtype: str, ns: int, raw: bytes) -> Iterator[Any]:
    if topic != "/uwb/ranges":
        yield topic, msgtype, ns, raw


def test_estimate_on_a_bag_without_what_the_estimator_needs_is_one_line(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    env = gym.make(ENV_ID, estimator="oracle", record_dir=tmp_path / "runs", max_episode_steps=3)
    env.reset(seed=0)
    for _ in range(3):
        env.step(env.action_space.sample())
    env.close()
    bag = _rewrite(tmp_path / "runs" / "episode_000", tmp_path / "no_uwb", _drop_uwb)
    code = main(["estimate", str(bag), "--estimator", "ukf", "--out", str(tmp_path / "x")])
    assert code == 2
    errors = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
    assert len(errors) == 1 and "needs uwb (UWB ranges to anchors" in errors[0], errors


def test_evaluate_refuses_a_task_it_cannot_measure_in_one_line() -> None:
    import gymnasium as gym

    from agents.evaluation.evaluate import LoadedPolicy

    roll = gym.spec("tensegrity_gym/ThreeBarRoll-v0")
    gym.register(
        "tensegrity_gym/ThreeBarStandStill-v0",
        entry_point=roll.entry_point,
        kwargs={**roll.kwargs, "task": "stand_still"},
    )
    try:
        policy = LoadedPolicy("still", "tensegrity_gym/ThreeBarStandStill-v0", "-", lambda o: o)
        with pytest.raises(ValueError, match=r"does not evaluate the 'stand_still' task$"):
            evaluate_policy(policy, condition("oracle"), episodes=1)
    finally:
        del gym.registry["tensegrity_gym/ThreeBarStandStill-v0"]


def test_evaluate_refuses_an_estimator_the_robot_has_not_before_any_episode() -> None:
    """The InEKF serves 3-bar prisms only: evaluating a SUPERball policy under it fails
    at once, in one line naming the env, the condition and the structure it needs."""
    from agents.evaluation.evaluate import evaluate_policies

    policy = random_policy("tensegrity_gym/SuperBallRoll-v0", seed=0)
    message = (
        r"^tensegrity_gym/SuperBallRoll-v0: condition 'inekf': estimator 'inekf' cannot "
        r"serve robot 'superball': it needs a 3-bar prism \(three rods\); this robot has 6 "
        r"rods$"
    )
    with pytest.raises(ValueError, match=message):
        evaluate_policies([policy], [condition("oracle"), condition("inekf")], episodes=1)


def test_the_simulator_says_exactly_the_kinds_it_produces() -> None:
    from tensegrity_gym.model.description import load_robot
    from tensegrity_gym.model.samples import GROUND_TRUTH, SAMPLE_KINDS

    backend = SimBackend(load_robot("three_bar"), camera=True)
    backend.reset(np.random.default_rng(0))
    d = backend.description
    samples = backend.step(d.rest_lengths[d.actuated]).samples
    backend.close()
    names = {cls: name for name, cls in SAMPLE_KINDS.items()}
    produced = {names[type(s)] for s in samples}
    assert backend.sample_kinds() == produced | {GROUND_TRUTH}


def test_estimators_declare_what_robot_structure_they_serve() -> None:
    """The ICP tracker and the InEKF are refused on SUPERball by structure, each naming
    why in one line; the 3-bar robots of any name pass."""
    from tensegrity_gym.model.description import load_robot

    superball, three_bar = load_robot("superball"), load_robot("three_bar")
    assert estimator_spec("icp").missing(None, superball) == (
        "estimator 'icp' cannot serve robot 'superball': the RGB-D tracker follows the three "
        "rods of a 3-bar prism; this robot has 6 rods, on which it loses track"
    )
    with pytest.raises(ValueError, match=r"^make: estimator 'inekf' cannot serve robot 'superb"):
        gym.make("tensegrity_gym/SuperBallRoll-v0", estimator="inekf")
    for name in ("icp", "inekf", "ukf"):
        assert estimator_spec(name).missing(None, three_bar) is None
        assert estimator_spec(name).missing(None, "superball") is None  # a name alone
