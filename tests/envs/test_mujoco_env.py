"""``gym.make(ID, engine="mujoco")`` (issue 41): every simulated id passes Gymnasium's
and SB3's checks on MuJoCo, two seeded rollouts are equal, the camera renders where the
machine can (else the camera's estimator is refused in one line), terrains and
randomised worlds are the same on both engines, and a bag recorded on MuJoCo replays and
estimates as one from PyBullet does."""

from __future__ import annotations

import warnings
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import tensegrity_gym
from tensegrity_gym.sim.engines import ENGINES, EngineSpec

if TYPE_CHECKING:
    from pathlib import Path

SIMULATED = tensegrity_gym.env_ids()
ROLL = "tensegrity_gym/ThreeBarRoll-v0"


@pytest.mark.parametrize(
    "env_id",
    # The large 3-bar's ids take 35-40 s each here; PyBullet's check covers every id.
    [pytest.param(i, marks=pytest.mark.slow) if "Large" in i else i for i in SIMULATED],
)
def test_gymnasium_and_sb3_check_env_on_mujoco(env_id: str) -> None:
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    env = gym.make(env_id, engine="mujoco")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            check_env(env.unwrapped, skip_render_check=True)
            sb3_check_env(env.unwrapped, warn=True)
        assert type(env.unwrapped.backend.world).__name__ == "MujocoWorld"
    finally:
        env.close()


def test_check_env_and_seeded_rollouts_on_the_stiff_engine() -> None:
    """``engine="mujoco_stiff"`` (MuJoCo with stiff contacts) is an engine like the others."""
    env = gym.make(ROLL, engine="mujoco_stiff")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            check_env(env.unwrapped, skip_render_check=True)
        assert env.unwrapped.backend.world.contact_steps == 2.0
    finally:
        env.close()
    stiff = _rollout(3, steps=8, engine="mujoco_stiff")
    assert _equal(stiff, _rollout(3, steps=8, engine="mujoco_stiff"))
    assert not _equal(stiff, _rollout(3, steps=8))


def _rollout(seed: int, env_id: str = ROLL, steps: int = 20, **kwargs: Any) -> list[Any]:
    kwargs.setdefault("engine", "mujoco")
    env = gym.make(env_id, **kwargs)
    rng = np.random.default_rng(seed + 100)
    obs, info = env.reset(seed=seed)
    record = [obs, info["com_true"]]
    for _ in range(steps):
        a = rng.uniform(-1, 1, env.action_space.shape).astype(np.float32)
        obs, reward, terminated, truncated, info = env.step(a)
        record += [obs, reward, terminated, truncated, info["com_true"], info["com_estimate"]]
    env.close()
    return record


def _equal(a: list[Any], b: list[Any]) -> bool:
    return all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))


@pytest.mark.parametrize("env_id", [ROLL, "tensegrity_gym/ThreeBarGoTo-v0"])
def test_same_seed_same_episode_bit_for_bit_on_mujoco(env_id: str) -> None:
    assert _equal(_rollout(7, env_id), _rollout(7, env_id))
    assert not _equal(_rollout(7, env_id), _rollout(8, env_id))


def test_the_engines_are_different_worlds_under_the_same_seed() -> None:
    a = gym.make(ROLL, engine="mujoco", estimator="oracle")
    b = gym.make(ROLL, estimator="oracle")
    com = [env.reset(seed=3)[1]["com_true"] for env in (a, b)]
    # The same start, drawn from the same seed, settled by each engine.
    np.testing.assert_allclose(com[0], com[1], atol=0.01)
    action = np.full(6, -0.6, dtype=np.float32)
    for _ in range(5):
        ta, tb = (env.step(action)[4]["com_true"] for env in (a, b))
    assert not np.array_equal(ta, tb)
    a.close()
    b.close()


def test_rgb_array_render_and_the_rgbd_camera_on_mujoco() -> None:
    env = gym.make(ROLL, engine="mujoco", estimator="icp", render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.shape == (360, 480, 3)
    assert frame.reshape(-1, 3).std(axis=0).max() > 5.0  # a scene, not a blank image
    for _ in range(3):
        obs, reward, *_ = env.step(np.zeros(6, dtype=np.float32))
    assert np.all(np.isfinite(obs)) and np.isfinite(reward)
    backend = env.unwrapped.backend
    d = backend.description
    rgb, depth = backend.world.camera_image(d.sensors.camera)
    cam = np.asarray(d.sensors.camera.position)
    com = backend.ground_truth().com
    # The robot is in view: the nearest depth is about the camera's distance to it.
    assert rgb.shape[:2] == depth.shape == (d.sensors.camera.height, d.sensors.camera.width)
    assert abs(float(depth.min()) - np.linalg.norm(com - cam)) < 0.5 * np.linalg.norm(com - cam)
    env.close()


def test_a_machine_that_cannot_render_refuses_the_camera_in_one_line(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    spec = ENGINES["mujoco"]
    blind = EngineSpec(spec.name, spec.factory, spec.install, lambda: "no OpenGL context")
    monkeypatch.setitem(ENGINES._entries, "mujoco", blind)
    with pytest.raises(ValueError, match=r"^make: estimator 'icp' needs the RGB-D camera: "
                                         r"engine 'mujoco' cannot render") as err:  # fmt: skip
        gym.make(ROLL, engine="mujoco", estimator="icp")
    assert "\n" not in str(err.value)
    gym.make(ROLL, engine="mujoco", estimator="ukf").close()  # no camera, no refusal


def test_bad_engines_are_refused_in_one_line() -> None:
    with pytest.raises(ValueError, match=r"make: unknown engine 'bullet'; valid choices"):
        gym.make(ROLL, engine="bullet")
    with pytest.raises(ValueError, match="engine must be a name"):
        gym.make(ROLL, engine=3)
    with pytest.raises(ValueError, match="driver='bag:x' has a real robot"):
        gym.make(ROLL, engine="mujoco", driver="bag:x")


def test_a_terrain_is_the_same_ground_on_mujoco() -> None:
    env = gym.make(ROLL, engine="mujoco", terrain="valley", estimator="oracle")
    env.reset(seed=0)
    backend = env.unwrapped.backend
    terrain = backend.terrain
    rows, cols = terrain.heights.shape
    rng = np.random.default_rng(1)
    r, c = rng.integers(0, rows, 30), rng.integers(0, cols, 30)
    xy = np.c_[c, r] * terrain.cell_size + terrain.origin
    far = np.hypot(xy[:, 0], xy[:, 1]) > 2.0 * backend.description.characteristic_length
    heights = backend.world.ground_heights(xy[far])
    np.testing.assert_allclose(heights, terrain.heights[r[far], c[far]], atol=1e-3)
    nodes = backend.ground_truth().node_positions
    clearance = terrain.clearance(nodes, 0.0)
    assert clearance.min() > -0.005  # resting on the valley's floor, not sunk in
    env.close()


def test_a_randomised_world_draws_the_same_factors_on_both_engines() -> None:
    draws = []
    for engine in ("pybullet", "mujoco"):
        env = gym.make(ROLL, engine=engine, randomization="mild", estimator="oracle")
        draws.append(env.reset(seed=5)[1]["randomization"])
        backend = env.unwrapped.backend
        robot, nominal, world = backend.world_draw.robot, backend.description, backend.world
        env.close()
    assert draws[0] == draws[1]
    # And the MuJoCo model is the drawn robot, not the nominal one.
    model = world.model
    np.testing.assert_allclose(model.body_mass[1:], [r.mass for r in robot.rods])
    np.testing.assert_allclose(model.actuator_gainprm[:, 0], [c.stiffness for c in robot.cables])
    assert not np.allclose(model.body_mass[1:], [r.mass for r in nominal.rods])


def test_a_bag_recorded_on_mujoco_replays_and_estimates(tmp_path: Path) -> None:
    from agents.recordings.offline import estimate_bag
    from hardware.bag import read_run

    env = gym.make(ROLL, engine="mujoco", estimator="ukf", record_dir=tmp_path / "bags",
                   max_episode_steps=15)  # fmt: skip
    obs, _ = env.reset(seed=11)
    live = [obs]
    zeros = np.zeros(6, dtype=np.float32)
    for _ in range(15):
        live.append(env.step(np.full(6, -0.5, dtype=np.float32))[0])
    env.close()
    bag = tmp_path / "bags" / "episode_000"
    run = read_run(bag)
    assert len(run.steps) == 15 and run.description.name == "three_bar"
    replay = gym.make(ROLL, estimator="ukf", driver=f"bag:{bag}")
    assert np.array_equal(replay.reset(seed=11)[0], live[0])
    for k, expected in enumerate(live[1:], 1):
        assert np.array_equal(replay.step(zeros)[0], expected), k
    replay.close()
    metrics = estimate_bag(bag, "ukf", tmp_path / "est", progress=False, settle=0.5)
    assert metrics[0]["finite"] and metrics[0]["steps_scored"] > 5
    assert metrics[0]["com_rmse_m"] < 0.05  # the UKF places the MuJoCo robot


def test_without_mujoco_installed_make_says_what_to_install(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import sys

    monkeypatch.setitem(sys.modules, "mujoco", None)  # import mujoco raises ImportError
    monkeypatch.delitem(sys.modules, "tensegrity_gym.sim.mujoco_world", raising=False)
    with pytest.raises(ImportError) as err:
        gym.make(ROLL, engine="mujoco")
    assert str(err.value) == (
        "make: engine 'mujoco' is not installed: pip install 'tensegrity-gym[mujoco]'"
    )
    gym.make(ROLL).close()  # PyBullet, the default, needs nothing more


def test_a_reset_reuses_the_model_and_repeats_the_episode() -> None:
    env = gym.make(ROLL, engine="mujoco", estimator="oracle")
    runs = []
    for _ in range(2):
        obs, _ = env.reset(seed=11)
        model = env.unwrapped.backend.world.model
        runs.append([obs] + [env.step(np.full(6, -0.5, dtype=np.float32))[0] for _ in range(8)])
        runs[-1].append(model)
    assert runs[0][-1] is runs[1][-1]  # flat ground each reset: not compiled again
    assert _equal(runs[0][:-1], runs[1][:-1])
    env.close()


def test_a_level_map_off_the_plane_is_ground_on_mujoco() -> None:
    from tensegrity_gym.sim.terrain import Terrain

    level = Terrain(np.full((30, 30), 0.3), 0.5, origin=(-7.0, -7.0), name="plateau")
    env = gym.make(ROLL, engine="mujoco", estimator="oracle", terrain=level)
    env.reset(seed=0)
    for _ in range(5):
        env.step(np.zeros(6, dtype=np.float32))
    nodes = env.unwrapped.backend.ground_truth().node_positions
    d = env.unwrapped.backend.description
    assert abs(nodes[:, 2].min() - (0.3 + d.rods[0].endcap_radius)) < 0.005
    env.close()


def test_a_checkpoint_restored_after_a_blow_up_runs_on() -> None:
    from tensegrity_gym.model.description import load_robot
    from tensegrity_gym.sim.mujoco_world import MujocoWorld

    d = load_robot("three_bar")
    world = MujocoWorld(d, 0.001)
    world.set_node_positions(d.initial_positions)
    saved = world.save_state()
    world.data.qvel[:] = 1e12
    world.advance(10, world.targets, [False] * 9 + [True])
    assert not np.isfinite(world.snapshot().rod_positions).all()
    world.restore_state(saved)
    snaps = world.advance(10, world.targets, [False] * 9 + [True])
    assert np.isfinite(snaps[-1].rod_positions).all() and world.time_ns == saved[-1] + 10**7
