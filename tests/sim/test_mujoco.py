"""The MuJoCo engine (issue 41): the MJCF is the description's robot, its cables pull as
the PyBullet world's do (held to :func:`~tensegrity_gym.sim.cables.cable_wrenches`, the
reference), its motors slew as :func:`~tensegrity_gym.sim.cables.slew_motors`, and the two
engines agree on a robot at rest and on a gait's roll."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from typing import TYPE_CHECKING

import mujoco
import numpy as np
import pytest

from agents.gait import run_gait
from tensegrity_gym.model.description import PRESETS, load_robot
from tensegrity_gym.model.kinematics import (
    member_lengths,
    rod_node_states,
    rod_quaternion_from_axis,
    weighted_kabsch,
)
from tensegrity_gym.model.lie import quat_to_matrix
from tensegrity_gym.sim.backend import SimBackend, settled_pose
from tensegrity_gym.sim.cables import cable_wrenches, slew_motors
from tensegrity_gym.sim.engines import ENGINES, check_engine, register_engine
from tensegrity_gym.sim.mjcf import MIN_CONTACT_STEPS, robot_mjcf, site_name
from tensegrity_gym.sim.mujoco_world import MujocoWorld

if TYPE_CHECKING:
    from tensegrity_gym.model.description import RobotDescription

THREE_BAR = load_robot("three_bar")


def _nodes(
    description: RobotDescription, positions: np.ndarray, quaternions: np.ndarray
) -> np.ndarray:
    """The nodes (n, 3) of rods at ``positions`` (r, 3) and ``quaternions`` (r, 4)."""
    half = np.array([0.5 * r.length for r in description.rods])
    zero = np.zeros_like(positions)
    return rod_node_states(positions, quaternions, zero, zero, half, description.rod_nodes)[0]


# ------------------------------------------------------------------ the model


@pytest.mark.parametrize("name", PRESETS)
def test_the_mjcf_is_the_description(name: str) -> None:
    d = load_robot(name)
    model = mujoco.MjModel.from_xml_string(robot_mjcf(d, time_step=0.001))
    assert model.nbody == d.n_rods + 1 and model.ntendon == d.n_cables == model.nu
    assert model.na == d.n_actuated and model.opt.timestep == 0.001
    np.testing.assert_allclose(model.body_mass[1:], [r.mass for r in d.rods])
    np.testing.assert_allclose(model.body_inertia[1:], [r.inertia for r in d.rods])
    for k, cable in enumerate(d.cables):
        ends = model.wrap_objid[model.tendon_adr[k] : model.tendon_adr[k] + 2]
        assert [model.site(int(s)).name for s in ends] == [site_name(n) for n in cable.nodes]
        assert model.actuator_gainprm[k, 0] == cable.stiffness
        np.testing.assert_array_equal(
            model.actuator_biasprm[k, :3], [0.0, -cable.stiffness, -cable.damping]
        )
        assert model.actuator_forcerange[k, 1] <= 0.0  # cables only pull
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    # The nodes (sites) stand where the description builds the robot.
    sites = [data.site(site_name(n)).xpos for n in range(d.n_nodes)]
    np.testing.assert_allclose(sites, d.initial_positions, atol=1e-6)  # rounded in YAML


def test_the_mjcf_is_plain_xml_with_no_hand_written_part() -> None:
    root = ET.fromstring(robot_mjcf(THREE_BAR, time_step=0.002))
    assert root.get("model") == "three_bar"
    assert [b.get("name") for b in root.iter("body")] == [r.name for r in THREE_BAR.rods]


def _solref(text: str) -> set[tuple[float, float]]:
    return {
        tuple(float(v) for v in g.get("solref", "").split())  # type: ignore[misc]
        for g in ET.fromstring(text).iter("geom")
    }


def test_stiff_contacts_take_the_shortest_stable_time_constant() -> None:
    (default,) = _solref(robot_mjcf(THREE_BAR, time_step=0.001))
    (stiff,) = _solref(robot_mjcf(THREE_BAR, time_step=0.001, contact_steps=MIN_CONTACT_STEPS))
    assert default[0] == pytest.approx(0.005) and stiff[0] == pytest.approx(0.002)
    assert stiff[1] == default[1]  # the restitution's damping ratio is the description's
    with pytest.raises(ValueError, match=r"^contact_steps must be at least 2\.0 .*got 1\.5$"):
        robot_mjcf(THREE_BAR, time_step=0.001, contact_steps=1.5)


def test_the_stiff_engine_sinks_the_robot_at_rest_less() -> None:
    """``engine="mujoco_stiff"``: the same robot, its contacts 2.5 times stiffer in time
    (about 6 times in force), so it rests less deep in the floor."""
    d = THREE_BAR
    sunk = []
    for engine in ("mujoco", "mujoco_stiff"):
        nodes = _nodes(d, *settled_pose(d, 0.001, 3.0, engine))
        sunk.append(float(d.node_radii[np.argmin(nodes[:, 2])] - nodes[:, 2].min()))
    assert 0.0 < sunk[1] < 0.5 * sunk[0]


def _random_pose(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    d = THREE_BAR
    x = d.initial_positions + rng.normal(0.0, 0.01, d.initial_positions.shape)
    rn = d.rod_nodes
    axes = x[rn[:, 1]] - x[rn[:, 0]]
    q = rod_quaternion_from_axis(axes / np.linalg.norm(axes, axis=1, keepdims=True))
    return 0.5 * (x[rn[:, 0]] + x[rn[:, 1]]) + np.array([0.0, 0.0, 0.5]), q


def test_cable_forces_are_those_of_the_pybullet_world() -> None:
    """At rest in mid-air, the actuators' generalised forces are the reference's wrenches
    (force in the world frame, torque in the rod's frame for a free joint)."""
    d = THREE_BAR
    world = MujocoWorld(d, 0.001)
    rest = d.rest_lengths * np.linspace(0.8, 1.05, d.n_cables)  # some slack, some taut
    world.set_rest_lengths(rest)
    positions, quaternions = _random_pose(np.random.default_rng(3))
    world.set_rod_states(positions, quaternions)
    poses = np.c_[positions, quaternions]
    nodes = _nodes(d, positions, quaternions)
    lengths = member_lengths(nodes, d.cable_nodes)
    wrench = np.empty((d.n_rods, 6))
    half = np.array([0.5 * r.length for r in d.rods])
    reel = np.full(d.n_cables, np.nan)
    node_of = np.asarray(d.rod_nodes, dtype=np.int64)
    cable_wrenches(
        poses, half, node_of, np.asarray(d.cable_nodes, dtype=np.int64),
        np.array([c.stiffness for c in d.cables]), np.array([c.damping for c in d.cables]),
        rest, reel, rest.copy(), lengths.copy(), 1000.0, d.n_nodes, wrench,
    )  # fmt: skip
    assert (lengths > rest).any() and (lengths < rest).any()
    forces = world.data.qfrc_actuator.reshape(d.n_rods, 6)
    np.testing.assert_allclose(forces[:, :3], wrench[:, :3], rtol=1e-9, atol=1e-9)
    body_torque = np.einsum("rji,rj->ri", quat_to_matrix(quaternions), wrench[:, 3:])
    np.testing.assert_allclose(forces[:, 3:], body_torque, rtol=1e-9, atol=1e-9)


def test_motors_slew_as_the_reference_does() -> None:
    d = THREE_BAR
    world = MujocoWorld(d, 0.001)
    world.set_node_positions(d.initial_positions + np.array([0.0, 0.0, 0.5]))
    lo, hi, speed = d.motor_limits
    targets = np.where(np.arange(d.n_actuated) % 2 == 0, lo, hi)
    targets[-1] = d.rest_lengths[d.actuated[-1]] + 2.5e-4  # arrives between steps
    rest = d.rest_lengths.copy()
    for n in (1, 7, 40, 1000):
        world.advance(n, targets, [False] * n)
        for _ in range(n):
            slew_motors(rest, np.asarray(d.actuated, dtype=np.int64), targets, speed * 0.001)
        np.testing.assert_allclose(world.rest_lengths, rest, atol=1e-12)
    np.testing.assert_array_equal(np.array(world.rest_lengths)[d.actuated], targets)


# ------------------------------------------------------------------ the engines agree


@pytest.mark.parametrize(("name", "tolerance"), [("three_bar", 1e-3), ("superball", 2e-3),
                                                 ("three_bar_large", 0.01)])  # fmt: skip
def test_a_robot_at_rest_settles_to_the_same_shape(name: str, tolerance: float) -> None:
    d = load_robot(name)
    shapes = [_nodes(d, *settled_pose(d, 0.001, 5.0, e)) for e in ("pybullet", "mujoco")]
    rotation, shift = weighted_kabsch(shapes[1], shapes[0], np.ones(d.n_nodes))
    error = np.linalg.norm(shapes[1] @ rotation.T + shift - shapes[0], axis=1)
    assert error.max() < tolerance
    np.testing.assert_allclose(shapes[0][:, 2].min(), shapes[1][:, 2].min(), atol=1e-3)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_gait_rolls_alike_in_both_engines(seed: int) -> None:
    """30 s of the three-bar's gait from the same resting face: the same faces at the
    start of the first periods, CoM travel within 20 %."""
    runs = [
        run_gait(estimator="oracle", engine=e, steps=300, seed=seed) for e in ("pybullet", "mujoco")
    ]
    assert runs[0]["rest_faces"][:5] == runs[1]["rest_faces"][:5]
    distances = [r["distance"] for r in runs]
    assert min(distances) > 0.5
    assert abs(distances[1] - distances[0]) < 0.2 * distances[0]


# ------------------------------------------------------------------ the registry


def test_engines_are_found_by_name_and_refused_in_one_line() -> None:
    assert {"pybullet", "mujoco", "mujoco_stiff"} <= set(ENGINES.names())
    with pytest.raises(ValueError, match=r"unknown engine 'bullet'.*pybullet"):
        check_engine("bullet")
    register_engine("missing", "no_such_module_here:World", install="pip install it")
    try:
        with pytest.raises(ImportError, match="engine 'missing' is not installed: pip install"):
            check_engine("missing")
    finally:
        ENGINES.unregister("missing")


def test_the_backend_pickles_its_engine() -> None:
    import pickle

    backend = SimBackend(THREE_BAR, engine="mujoco")
    clone = pickle.loads(pickle.dumps(backend))
    assert clone.engine == "mujoco" and type(clone.world).__name__ == "MujocoWorld"


def test_a_blown_up_mujoco_state_ends_the_episode_as_on_pybullet() -> None:
    """MuJoCo resets a blown-up state to the model's start and goes on; the world marks it
    NaN instead, so the env truncates with ``sim_diverged`` as it does on PyBullet."""
    import gymnasium as gym

    env = gym.make("tensegrity_gym/ThreeBarRoll-v0", engine="mujoco", estimator="oracle")
    inner = env.unwrapped
    obs, _ = inner.reset(seed=0)
    world = inner.backend.world
    world.data.qvel[:] = 1e12  # beyond any integration: MuJoCo warns of a bad velocity
    obs, reward, terminated, truncated, info = inner.step(np.zeros(6, dtype=np.float32))
    assert truncated and not terminated and info["sim_diverged"] is True
    assert np.all(np.isfinite(obs)) and reward == 0.0
    inner.reset(seed=0)  # and a reset recovers
    assert inner.step(np.zeros(6, dtype=np.float32))[4]["sim_diverged"] is False
    env.close()


def test_the_encoders_read_the_same_slew_on_both_engines() -> None:
    """The encoders sample the motors' rest lengths within a period (100 Hz): the same
    readings on both engines, as the slew is the motors' own, not the physics'."""
    from tensegrity_gym.model.samples import EncoderSample

    d = THREE_BAR
    lo, hi, _ = d.motor_limits
    targets = np.where(np.arange(d.n_actuated) % 2 == 0, lo, hi)
    readings = []
    for engine in ("pybullet", "mujoco"):
        backend = SimBackend(d, engine=engine)
        backend.reset(np.random.default_rng(0))
        samples = [s for _ in range(2) for s in backend.step(targets).samples]
        readings.append(np.array([s.rest_lengths for s in samples if isinstance(s, EncoderSample)]))
        backend.close()
    assert len(readings[0]) == 20
    assert np.ptp(readings[0][:10, 0]) > 0.01  # the motors move within a period
    np.testing.assert_array_equal(readings[0], readings[1])


def test_damping_and_the_minimum_tension_pull_as_the_reference() -> None:
    """The 1.45 m robot (its motors hold a minimum tension) moving: the actuators'
    generalised forces equal :func:`cable_wrenches`' with the damping rate taken exact
    (the reference's backward difference fed the length a step before)."""
    d = load_robot("three_bar_large")
    world = MujocoWorld(d, 0.001)
    rng = np.random.default_rng(7)
    x = d.initial_positions + rng.normal(0.0, 0.01, d.initial_positions.shape)
    rn = d.rod_nodes
    axes = x[rn[:, 1]] - x[rn[:, 0]]
    q = rod_quaternion_from_axis(axes / np.linalg.norm(axes, axis=1, keepdims=True))
    p = 0.5 * (x[rn[:, 0]] + x[rn[:, 1]]) + np.array([0.0, 0.0, 1.0])
    v, w = rng.normal(0.0, 0.02, (d.n_rods, 3)), rng.normal(0.0, 0.02, (d.n_rods, 3))
    half = np.array([0.5 * r.length for r in d.rods])
    nodes, velocities = rod_node_states(p, q, v, w, half, d.rod_nodes)
    lengths = member_lengths(nodes, d.cable_nodes)
    ends = d.cable_nodes
    along = (nodes[ends[:, 1]] - nodes[ends[:, 0]]) / lengths[:, None]
    rate = np.sum(along * (velocities[ends[:, 1]] - velocities[ends[:, 0]]), axis=1)
    least = d.motor_min_stretch
    rest = lengths - 0.01  # taut by 1 cm
    rest[d.actuated[:3]] = lengths[d.actuated[:3]]  # slack but for the motor's minimum
    world.set_rest_lengths(rest)
    world.set_rod_states(p, q, v, w)
    reel = np.full(d.n_cables, np.nan)
    reel[d.actuated] = least
    wrench = np.empty((d.n_rods, 6))
    cable_wrenches(
        np.c_[p, q], half, np.asarray(rn, dtype=np.int64), np.asarray(ends, dtype=np.int64),
        np.array([c.stiffness for c in d.cables]), np.array([c.damping for c in d.cables]),
        rest, reel, rest.copy(), lengths - 0.001 * rate, 1000.0, d.n_nodes, wrench,
    )  # fmt: skip
    forces = world.data.qfrc_actuator.reshape(d.n_rods, 6)
    np.testing.assert_allclose(forces[:, :3], wrench[:, :3], rtol=1e-6, atol=1e-6)
    body_torque = np.einsum("rji,rj->ri", quat_to_matrix(q), wrench[:, 3:])
    np.testing.assert_allclose(forces[:, 3:], body_torque, rtol=1e-6, atol=1e-6)


def test_a_traced_period_replays_to_the_same_state_bit_for_bit() -> None:
    """The benchmark's ceiling is the env's own physics: the ``mj_step`` calls a period
    made, replayed from the state it began at, end where the period ended, and the
    trace is off unless asked for."""
    d = load_robot("three_bar")
    backend = SimBackend(d, engine="mujoco")
    backend.reset(np.random.default_rng(0))
    world = backend.world
    assert isinstance(world, MujocoWorld) and world.trace is None
    start, world.trace = world.save_state(), []
    lo, hi, _ = d.motor_limits
    for k in range(3):
        backend.step(np.where(np.arange(len(lo)) % 2 == k % 2, lo, hi))
    trace, world.trace = world.trace, None
    period = round(backend.control_period / backend.time_step)
    assert len(trace) > 3 and sum(n for _, _, n in trace) == 3 * period
    end = world.data.qpos.copy()
    world.restore_state(start)
    assert np.abs(world.data.qpos - end).max() > 1e-3  # the motors moved the robot
    world.replay(trace)
    np.testing.assert_array_equal(world.data.qpos, end)
    backend.close()
