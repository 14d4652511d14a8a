"""Uneven ground (issue 14): ``gym.make(ID, terrain=...)`` builds a PyBullet heightfield
whose surface is the map's heights, flat stays the plane bit for bit, a rough ground
is fixed by the reset's seed, the robot starts on the ground and stays on it, and a bad
terrain is refused in one line naming it."""

from __future__ import annotations

import pickle
import warnings
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from tensegrity_gym.model.description import load_robot
from tensegrity_gym.model.samples import ContactSample
from tensegrity_gym.sim.backend import SimBackend
from tensegrity_gym.sim.terrain import TERRAINS, Terrain, load_terrain, register_terrain, valley

if TYPE_CHECKING:
    from pathlib import Path

    from numpy.typing import NDArray

THREE_BAR = load_robot("three_bar")
LARGE = load_robot("three_bar_large")
ROLL = "tensegrity_gym/ThreeBarRoll-v0"
LARGE_ROLL = "tensegrity_gym/ThreeBarLargeRoll-v0"


def _reset(terrain: Any, seed: int = 0, **kwargs: Any) -> SimBackend:
    backend = SimBackend(THREE_BAR, terrain=terrain, **kwargs)
    backend.reset(np.random.default_rng(seed))
    return backend


def _map_points(terrain: Terrain, rng: np.random.Generator, k: int = 60) -> NDArray[np.float64]:
    """(k, 2) random world (x, y) inside the map, and away from the robot at the origin."""
    x0, x1, y0, y1 = terrain.extent
    pts = rng.uniform([x0, y0], [x1, y1], (4 * k, 2))
    return pts[np.hypot(pts[:, 0], pts[:, 1]) > 2.0 * THREE_BAR.characteristic_length][:k]


# ------------------------------------------------------------------ the heightfield


@pytest.mark.parametrize("name", ["valley", "rough"])
def test_ray_tests_meet_the_map_where_it_says(name: str) -> None:
    backend = _reset(name)
    terrain = backend.terrain
    assert terrain is not None and not terrain.is_flat
    rng = np.random.default_rng(1)
    # At grid nodes the surface is the map's value; between them Bullet's triangles
    # and the bilinear map differ by the curvature times a cell squared (under a mm).
    rows, cols = terrain.heights.shape
    r, c = rng.integers(0, rows), rng.integers(0, cols, 40)
    nodes = np.c_[c, np.full(40, r)] * terrain.cell_size + terrain.origin
    nodes = nodes[np.hypot(nodes[:, 0], nodes[:, 1]) > 2.0 * THREE_BAR.characteristic_length]
    for xy, tol in ((nodes, 1e-4), (_map_points(terrain, rng), 3e-3)):
        ray = backend.world.ground_heights(xy)
        np.testing.assert_allclose(ray, terrain.height_at(xy[:, 0], xy[:, 1]), atol=tol)
    backend.close()


def _write_map(
    folder: Path, heights: NDArray[np.float64], name: str = "hills", **sidecar: object
) -> Path:
    """``name.npy`` holding ``heights`` and its sidecar ``name.yaml`` of ``sidecar``."""
    path = folder / f"{name}.npy"
    np.save(path, heights)
    path.with_suffix(".yaml").write_text(
        "".join(f"{k}: {v}\n" for k, v in sidecar.items()), encoding="utf-8"
    )
    return path


def test_a_height_map_file_lies_where_its_sidecar_puts_it(tmp_path: Path) -> None:
    """Rows run along y and columns along x, from the sidecar's origin: a map that is
    not symmetric shows a swap of either."""
    rows, cols, cell = 30, 50, 0.05
    y, x = np.mgrid[0:rows, 0:cols] * cell
    heights = 0.04 * x + 0.1 * np.sin(3.0 * y) - 0.3
    path = _write_map(tmp_path, heights, cell_size=cell, origin=[-1.2, -0.7])
    backend = _reset(path)
    terrain = backend.terrain
    assert terrain is not None and terrain.name == "hills.npy"
    assert terrain.extent == pytest.approx((-1.2, -1.2 + 49 * cell, -0.7, -0.7 + 29 * cell))
    xy = np.array([[1.0, 0.5], [-1.0, -0.5], [1.1, -0.6], [-0.9, 0.6]])
    expected = 0.04 * (xy[:, 0] + 1.2) + 0.1 * np.sin(3.0 * (xy[:, 1] + 0.7)) - 0.3
    np.testing.assert_allclose(terrain.height_at(xy[:, 0], xy[:, 1]), expected, atol=1e-3)
    np.testing.assert_allclose(backend.world.ground_heights(xy), expected, atol=2e-3)
    backend.close()


def test_a_greyscale_png_is_a_map_seen_from_above(tmp_path: Path) -> None:
    from matplotlib.image import imsave

    image = np.zeros((20, 40))
    image[:5] = 1.0  # the top rows of the image: the map's largest y
    imsave(tmp_path / "step.png", image, cmap="gray", vmin=0.0, vmax=1.0)
    (tmp_path / "step.yaml").write_text("cell_size: 0.1\nheight_scale: 0.2\n", encoding="utf-8")
    terrain = load_terrain(tmp_path / "step.png")
    assert terrain.heights.shape == (20, 40)
    assert float(terrain.height_at(0.0, 0.9)) == pytest.approx(0.2, abs=1e-6)
    assert float(terrain.height_at(0.0, -0.9)) == pytest.approx(0.0, abs=1e-6)


def test_height_at_is_bilinear_and_holds_the_edge_beyond_the_map() -> None:
    terrain = Terrain(np.array([[0.0, 1.0], [2.0, 4.0]]), 2.0, (10.0, 20.0))
    assert float(terrain.height_at(11.0, 20.0)) == pytest.approx(0.5)
    assert float(terrain.height_at(11.0, 21.0)) == pytest.approx(1.75)
    assert float(terrain.height_at(50.0, 50.0)) == pytest.approx(4.0)
    assert terrain.height_at(np.zeros((3, 2)), 20.0).shape == (3, 2)
    with pytest.raises(ValueError, match="finite"):
        Terrain(np.array([[0.0, np.nan], [0.0, 0.0]]), 1.0)
    with pytest.raises(ValueError, match="cell_size"):
        Terrain(np.zeros((2, 2)), 0.0)


# ------------------------------------------------------------------ seeds and flat


def test_a_rough_ground_is_fixed_by_the_seed_bit_for_bit() -> None:
    first, again, other = (_reset("rough", seed) for seed in (7, 7, 8))
    heights = [b.terrain.heights for b in (first, again, other) if b.terrain is not None]
    assert np.array_equal(heights[0], heights[1])
    assert not np.allclose(heights[0], heights[2])
    rms = float(np.sqrt(np.mean(heights[0] ** 2)))
    assert rms == pytest.approx(0.02 * THREE_BAR.characteristic_length)
    truth = [b.ground_truth() for b in (first, again)]
    assert truth[0] is not None and truth[1] is not None
    assert np.array_equal(truth[0].node_positions, truth[1].node_positions)
    # A new ground each episode.
    first.reset(np.random.default_rng(9))
    assert first.terrain is not None and not np.array_equal(first.terrain.heights, heights[0])
    for b in (first, again, other):
        b.close()


def _rollout(env_id: str, seed: int, steps: int, **kwargs: Any) -> list[NDArray[np.float32]]:
    env = gym.make(env_id, **kwargs)
    obs, _ = env.reset(seed=seed)
    out = [obs]
    action = np.linspace(-1.0, 1.0, env.action_space.shape[0], dtype=np.float32)
    for k in range(steps):
        obs, *_ = env.step(action * (-1.0) ** k)
        out.append(obs)
    env.close()
    return out


def test_flat_is_the_plane_of_before_bit_for_bit() -> None:
    plain = _rollout(ROLL, 3, 8)
    flat = _rollout(ROLL, 3, 8, terrain="flat")
    assert all(np.array_equal(a, b) for a, b in zip(plain, flat, strict=True))
    backend = _reset("flat")
    assert backend.world.flat_ground
    np.testing.assert_array_equal(backend.world.ground_heights(np.ones((2, 2))), [0.0, 0.0])
    backend.close()


def test_the_same_seed_gives_the_same_rough_episode() -> None:
    a = _rollout(ROLL, 5, 4, terrain="rough", estimator="oracle")
    b = _rollout(ROLL, 5, 4, terrain="rough", estimator="oracle")
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))


# ------------------------------------------------------------------ the robot on it


def test_the_large_robot_on_the_valley_passes_gymnasiums_checker() -> None:
    env = gym.make(LARGE_ROLL, terrain="valley", estimator="oracle")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env.unwrapped, skip_render_check=True)
    env.close()


def test_the_robot_starts_on_the_valley_slope_and_stays_on_it() -> None:
    """Spawned in the trough, the robot rests on it (no rod sunk in, none floating),
    its contact sensors feel that ground, and a rollout stays on the surface."""
    length = LARGE.characteristic_length
    env = gym.make(LARGE_ROLL, terrain="valley", estimator="oracle", spawn_radius=4.0 * length)
    obs, _ = env.reset(seed=0)
    backend = env.unwrapped.backend
    terrain = backend.terrain
    radius = np.array([LARGE.rods[LARGE.node_rod[i]].endcap_radius for i in range(6)])
    truth = backend.ground_truth()
    com = truth.com
    assert float(terrain.height_at(com[0], com[1])) < -0.05 * length  # in the trough
    assert float(terrain.slope_at(com[0], com[1])) > 0.1
    clearance = terrain.clearance(truth.node_positions, radius)
    assert -0.005 < clearance.min() < 0.005
    env.action_space.seed(0)
    for _ in range(25):
        obs, _, _, _, info = env.step(env.action_space.sample())
        assert np.all(np.isfinite(obs)) and not info["sim_diverged"]
        clearance = terrain.clearance(backend.ground_truth().node_positions, radius)
        assert -0.005 < clearance.min() < 0.03, clearance
    env.close()


def test_contact_sensors_feel_the_terrain_not_the_plane_z_0() -> None:
    """On a plateau 0.2 m up the resting endcaps touch its top, 0.2 m above z = 0."""
    heights = np.full((41, 41), 0.2)
    heights[0, 0] = 0.19  # not flat: a heightfield, not the plane
    plateau = Terrain(heights, 0.1, (-2.0, -2.0))
    backend = _reset(plateau)
    contacts = [s for s in backend.reset(np.random.default_rng(0)).samples
                if isinstance(s, ContactSample)]  # fmt: skip
    truth = backend.ground_truth()
    assert contacts and truth is not None
    assert 2 <= int(contacts[0].in_contact.sum()) <= 4
    assert truth.node_positions[:, 2].min() > 0.2
    backend.close()


def test_a_labs_terrain_by_name_and_a_terrain_object(tmp_path: Path) -> None:
    def ramp(description: Any, rng: np.random.Generator) -> Terrain:
        x = np.linspace(-3.0, 3.0, 61)
        return Terrain(np.tile(0.05 * x, (61, 1)), 0.1, (-3.0, -3.0), name="ramp")

    register_terrain("test_ramp", ramp)
    try:
        env = gym.make(ROLL, terrain="test_ramp", estimator="oracle")
        env.reset(seed=0)
        assert env.unwrapped.backend.terrain.name == "ramp"
        env.close()
    finally:
        TERRAINS.unregister("test_ramp")
    made = valley(THREE_BAR, np.random.default_rng())
    env = gym.make(ROLL, terrain=made, estimator="oracle")
    env.reset(seed=0)
    assert env.unwrapped.backend.terrain is made
    clone = pickle.loads(pickle.dumps(env.unwrapped.backend))
    clone.reset(np.random.default_rng(0))
    assert np.array_equal(clone.terrain.heights, made.heights)
    clone.close()
    env.close()


# ------------------------------------------------------------------ bad arguments


def _bad_files(folder: Path) -> dict[str, object]:
    """Bad terrain arguments, each with a file where it needs one."""
    no_sidecar = folder / "lone.npy"
    np.save(no_sidecar, np.zeros((4, 4)))
    no_cell = _write_map(folder, np.zeros((4, 4)), "nocell", height_scale=2)
    line = _write_map(folder, np.zeros(5), "line", cell_size=0.1)
    holes = _write_map(folder, np.array([[0.0, np.nan], [0.0, 0.0]]), "holes", cell_size=0.1)
    junk = folder / "junk.png"
    junk.write_text("not an image", encoding="utf-8")
    (folder / "junk.yaml").write_text("cell_size: 0.1\n", encoding="utf-8")
    return {
        "unknown name": "hilly",
        "not a terrain": 3,
        "missing file": str(folder / "none.npy"),
        "not a height map": str(folder / "hills.txt"),
        "no sidecar": no_sidecar,
        "no cell size": no_cell,
        "one-dimensional": line,
        "not finite": holes,
        "not an image": junk,
    }


def test_bad_terrain_arguments_are_one_line_errors(tmp_path: Path) -> None:
    for why, terrain in _bad_files(tmp_path).items():
        with pytest.raises(ValueError, match="terrain=") as info:
            gym.make(ROLL, estimator="oracle", terrain=terrain)
        message = str(info.value)
        assert "\n" not in message, (why, message)
        if not isinstance(terrain, int):
            assert str(terrain) in message, (why, message)


def test_terrain_is_for_the_simulator_only(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="terrain='valley'") as info:
        gym.make(ROLL, estimator="oracle", terrain="valley", driver=f"bag:{tmp_path}")
    assert "\n" not in str(info.value)
