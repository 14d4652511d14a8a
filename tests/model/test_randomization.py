"""Domain randomisation (issue 16): the ranges, the draws, and the worlds they make."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
import pytest

import tensegrity_gym  # noqa: F401  (registers the envs)
from agents.benchmarks.sim2real import bench_randomized_ukf
from tensegrity_gym.model.description import load_robot
from tensegrity_gym.model.randomization import (
    RANDOMIZATIONS,
    Randomization,
    register_randomization,
    resolve_randomization,
)

if TYPE_CHECKING:
    from pathlib import Path

D = load_robot("three_bar")


def test_nominal_ranges_draw_nothing_and_keep_the_robot() -> None:
    rng = np.random.default_rng(0)
    world = Randomization().draw(D, rng)
    assert world.n_draws == 0
    assert world.robot == D
    np.testing.assert_array_equal(world.gravity, [0.0, 0.0, -D.gravity])
    assert world.command_latency == 0.0
    # Nothing drawn: the generator is where it was, so episodes stay as they were.
    assert rng.uniform() == np.random.default_rng(0).uniform()


def test_the_same_generator_state_draws_the_same_world() -> None:
    strong = RANDOMIZATIONS["strong"]
    a = strong.draw(D, np.random.default_rng(3))
    b = strong.draw(D, np.random.default_rng(3))
    c = strong.draw(D, np.random.default_rng(4))
    assert a.robot == b.robot and np.array_equal(a.gravity, b.gravity)
    assert a.robot != c.robot


@pytest.mark.parametrize("name", ["mild", "strong", "description"])
def test_every_draw_lies_in_its_range(name: str) -> None:
    r = RANDOMIZATIONS[name]
    for seed in range(20):
        world = r.draw(D, np.random.default_rng(seed))
        s = world.summary(D)
        assert all(r.rod_mass[0] <= v <= r.rod_mass[1] for v in s["rod_mass"])
        assert all(r.cable_stiffness[0] <= v <= r.cable_stiffness[1] for v in s["cable_stiffness"])
        assert all(r.cable_damping[0] <= v <= r.cable_damping[1] for v in s["cable_damping"])
        offsets = np.array(s["rest_length_offset"])
        actuated = np.array([c.actuated for c in D.cables])
        low, high = r.actuated_rest_offset
        zero = np.array(r.encoder_zero) / D.rest_lengths[actuated].min()
        low, high = low + zero[0], high + zero[1]
        assert np.all((offsets[actuated] >= low - 1e-5) & (offsets[actuated] <= high + 1e-5))
        low, high = r.passive_rest_offset
        assert np.all((offsets[~actuated] >= low - 1e-5) & (offsets[~actuated] <= high + 1e-5))
        assert len(s["motor_speed"]) == int(actuated.sum())
        assert r.friction[0] <= s["friction"] <= r.friction[1]
        assert 0.0 <= s["gravity_tilt_deg"] <= np.degrees(r.gravity_tilt[1]) + 1e-9
        assert np.linalg.norm(world.gravity) == pytest.approx(D.gravity)
        assert r.command_latency[0] <= world.command_latency <= r.command_latency[1]
        assert world.robot.nodes == D.nodes  # where the robot is built, before it settles
        # The rods' lengths: the scale and both endcaps' offsets.
        low = r.rod_length[0] + 2.0 * r.endcap_offset[0] / max(x.length for x in D.rods)
        high = r.rod_length[1] + 2.0 * r.endcap_offset[1] / min(x.length for x in D.rods)
        assert all(low - 1e-5 <= v <= high + 1e-5 for v in s["rod_length"])
        zero = r.actuated_rest_offset[1] * D.rest_lengths.max() + r.encoder_zero[1]
        assert np.all(np.abs(s["encoder_zero_m"]) <= zero + 1e-5)
        assert np.all(np.abs(s["motor_range_offset_m"]) <= r.motor_range_offset[1] + 1e-5)
        if name == "mild":  # the mild worlds keep the description's geometry and motors
            assert [x.length for x in world.robot.rods] == [x.length for x in D.rods]
            assert s["motor_range_offset_m"] == [0.0] * len(s["motor_range_offset_m"])


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"rod_mass": (0.0, 1.2)}, r"rod_mass=\(0.0, 1.2\): a scale must be > 0"),
        ({"cable_stiffness": (1.2, 0.8)}, r"cable_stiffness=.* low <= high"),
        ({"uwb_packet_loss": (0.3, 1.0)}, r"uwb_packet_loss=.* must lie in \[0, 1\)"),
        ({"passive_rest_offset": (-0.6, 0.0)}, r"passive_rest_offset=.* \(-0.5, 0.5\)"),
        ({"command_latency": (-0.1, 0.0)}, r"command_latency=.* must be >= 0"),
        ({"gravity_tilt": (0.0, 2.0)}, r"gravity_tilt=.* must be < pi/2"),
        ({"friction": 1.2}, r"friction=1.2 must be a \(low, high\) pair"),
        ({"encoder_zero": (-30.0, 30.0)}, r"encoder_zero=.* must lie in \(-0.5, 0.5\) m"),
        ({"rod_length": (0.0, 1.0)}, r"rod_length=.*: a scale must be > 0"),
    ],
)
def test_bad_ranges_are_refused_by_field(kwargs: dict[str, object], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        Randomization(**kwargs)  # type: ignore[arg-type]


def test_the_description_error_family_moves_geometry_motors_and_encoders() -> None:
    """``"description"``: rods, endcaps, motor ranges and encoder zeros drawn per part;
    the sensor models and the ground stay the description's."""
    r = RANDOMIZATIONS["description"]
    world = r.draw(D, np.random.default_rng(2))
    s = world.summary(D)
    assert len(set(s["rod_length"])) == len(D.rods) and 1.0 not in s["rod_length"]
    assert len(set(s["motor_range_offset_m"])) == D.n_actuated
    motors = [(a.motor, b.motor) for a, b in zip(world.robot.cables, D.cables, strict=True)
              if a.motor is not None and b.motor is not None]  # fmt: skip
    for a, b in motors:  # the range shifted whole: the same span
        assert a.max_rest_length - a.min_rest_length == pytest.approx(
            b.max_rest_length - b.min_rest_length
        )
    assert world.robot.ground == D.ground and world.robot.sensors == D.sensors
    assert np.all(world.gravity == [0.0, 0.0, -D.gravity]) and world.command_latency == 0.0
    # An error that leaves a rod shorter than its endcaps, or a motor range below 0 m.
    with pytest.raises(ValueError, match=r"leave rod 'red' -0.275 m long, no longer than"):
        Randomization(endcap_offset=(-0.3, -0.3)).draw(D, np.random.default_rng(0))
    with pytest.raises(ValueError, match=r"moves cable .* motor range to -0.*\(not > 0\)"):
        Randomization(motor_range_offset=(-0.3, -0.3)).draw(D, np.random.default_rng(0))


def test_a_world_with_description_error_is_built_as_drawn() -> None:
    """The simulator builds the drawn rods (their endcaps' distance) and drives the
    motors within the drawn ranges; the estimator's description stays nominal."""
    env = _env("description")
    _, info = env.reset(seed=3)
    backend = env.unwrapped.backend  # type: ignore[attr-defined]
    drawn = backend.world.description
    nodes = backend.ground_truth().node_positions
    lengths = [float(np.linalg.norm(nodes[a] - nodes[b])) for a, b in D.rod_nodes]
    np.testing.assert_allclose(lengths, [x.length for x in drawn.rods], atol=1e-6)
    assert info["randomization"]["rod_length"] == [
        round(x.length / y.length, 5) for x, y in zip(drawn.rods, D.rods, strict=True)
    ]
    assert env.unwrapped.backend.description == D  # type: ignore[attr-defined]
    lo = np.array([c.motor.min_rest_length for c in D.cables if c.motor is not None])
    for _ in range(12):  # command the lowest rest lengths; the motors stop at their own
        env.step(env.unwrapped.targets_to_action(lo))  # type: ignore[attr-defined]
    rest = backend.ground_truth().rest_lengths[D.actuated]
    drawn_lo = np.array([c.motor.min_rest_length for c in drawn.cables if c.motor is not None])
    zero = np.array(info["randomization"]["encoder_zero_m"])
    np.testing.assert_allclose(rest, np.maximum(lo + zero, drawn_lo), atol=1e-5)  # zero: 5 dp
    env.close()


def test_names_resolve_and_a_lab_registers_its_own() -> None:
    assert resolve_randomization(None) is None
    assert resolve_randomization("mild") is RANDOMIZATIONS["mild"]
    with pytest.raises(ValueError, match=r"'wild' must be None, one of \['description', 'mild'"):
        resolve_randomization("wild")
    mine = Randomization(rod_mass=(0.95, 1.05))
    register_randomization("lab_test", mine)
    try:
        assert resolve_randomization("lab_test") is mine
    finally:
        del RANDOMIZATIONS["lab_test"]
    with pytest.raises(TypeError, match="expected a Randomization"):
        register_randomization("bad", {"rod_mass": (1, 2)})  # type: ignore[arg-type]


# ---------------------------------------------------------------- in the simulator

ENV_ID = "tensegrity_gym/ThreeBarRoll-v0"


def _env(randomization: object, **kwargs: object) -> gym.Env[Any, Any]:
    return gym.make(ENV_ID, estimator="oracle", calibration="true",
                    randomization=randomization, **kwargs)  # fmt: skip


def _rollout(env: gym.Env[Any, Any], seed: int, steps: int = 15) -> tuple[Any, list[Any]]:
    obs, info = env.reset(seed=seed)
    out = [obs]
    action = np.linspace(-1.0, 1.0, 6, dtype=np.float32)
    for k in range(steps):
        obs, *_ = env.step(action if k % 10 < 5 else -action)
        out.append(obs)
    return info, out


def test_a_randomised_world_is_drawn_at_reset_and_kept_from_the_estimators() -> None:
    env = _env("strong")
    info, first = _rollout(env, seed=3)
    backend = env.unwrapped.backend  # type: ignore[attr-defined]
    drawn = info["randomization"]
    assert set(drawn) >= {"rod_mass", "cable_stiffness", "friction", "gravity_tilt_deg"}
    # The simulator builds the drawn robot; the estimators get the nominal one.
    assert backend.description == D
    assert backend.world.description != D
    masses = [r.mass / n.mass for r, n in zip(backend.world.description.rods, D.rods, strict=True)]
    np.testing.assert_allclose(masses, drawn["rod_mass"], rtol=1e-4)
    tilt = np.degrees(np.arccos(-backend.world.gravity[2] / D.gravity))
    assert tilt == pytest.approx(drawn["gravity_tilt_deg"], abs=1e-3)
    # Same seed, same world and episode, bit for bit; another seed, another world.
    again = _env("strong")
    info_again, second = _rollout(again, seed=3)
    assert info_again["randomization"] == drawn
    for a, b in zip(first, second, strict=True):
        np.testing.assert_array_equal(a, b)
    _, other = env.reset(seed=4)
    assert other["randomization"] != drawn
    env.close()
    again.close()


def test_without_randomisation_nothing_is_drawn_and_info_says_nothing() -> None:
    plain, nominal = _env(None), _env(Randomization())
    info, a = _rollout(plain, seed=2)
    info_nominal, b = _rollout(nominal, seed=2)
    assert "randomization" not in info
    assert info_nominal["randomization"]["rod_mass"] == [1.0, 1.0, 1.0]
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)  # nominal ranges draw nothing: the same episode
    plain.close()
    nominal.close()


def test_encoder_zero_errors_and_command_latency_act_on_the_motors() -> None:
    """An actuated cable 2 % longer than its encoder reads; commands acting 50 ms late."""
    r = Randomization(actuated_rest_offset=(0.02, 0.02), command_latency=(0.05, 0.05))
    late, prompt = _env(r), _env(None)
    for env in (late, prompt):
        env.reset(seed=0)
    inner = late.unwrapped
    backend = inner.backend  # type: ignore[attr-defined]
    truth = backend.ground_truth()
    actuated = D.actuated
    rest = D.rest_lengths[actuated]
    np.testing.assert_allclose(truth.rest_lengths[actuated], 1.02 * rest)
    encoders = [s for s in backend.step(rest).samples if type(s).__name__ == "EncoderSample"]
    np.testing.assert_allclose(encoders[-1].rest_lengths, rest, atol=D.sensors.encoder.resolution)
    # A command far from the rest lengths: the motors slew toward it for 50 ms, not 100.
    lo = np.array([c.motor.min_rest_length for c in D.cables if c.motor is not None])
    moved = []
    for env in (late, prompt):
        before = env.unwrapped.backend.ground_truth().rest_lengths[actuated]  # type: ignore[attr-defined]
        env.step(env.unwrapped.targets_to_action(lo))  # type: ignore[attr-defined]
        after = env.unwrapped.backend.ground_truth().rest_lengths[actuated]  # type: ignore[attr-defined]
        moved.append(np.abs(after - before).max())
    speed = max(c.motor.max_speed for c in D.cables if c.motor is not None)
    assert moved[1] == pytest.approx(0.1 * speed, rel=0.02)
    assert moved[0] == pytest.approx(0.05 * speed, rel=0.05)
    late.close()
    prompt.close()


def test_randomisation_is_refused_on_a_real_robot_and_when_malformed() -> None:
    with pytest.raises(ValueError, match=r"randomization='wild' must be None, one of"):
        _env("wild")
    with pytest.raises(ValueError, match=r"command_latency=\(0.0, 0.2\) must stay below"):
        _env(Randomization(command_latency=(0.0, 0.2)))
    with pytest.raises(ValueError, match="leave randomization at None"):
        gym.make(ENV_ID, driver="bag:/nowhere", randomization="mild")


def test_the_draws_go_into_the_bag(tmp_path: Path) -> None:
    from hardware.bag.reader import BagReader

    env = _env("mild", record_dir=tmp_path)
    _, info = env.reset(seed=5)
    env.step(env.action_space.sample())
    env.close()
    with BagReader(next(tmp_path.iterdir())) as reader:
        assert reader.run_info["randomization"] == info["randomization"]


@pytest.mark.slow
def test_the_ukf_stays_consistent_on_a_rolling_robot_in_mild_worlds() -> None:
    """Issue 16's figure on one seed: the 3-bar gait, the UKF on the nominal model. Its
    NEES per dof within the chi-square band of one run, nominal and under ``"mild"``;
    the CoM error under ``"mild"`` within 1.5x the nominal one; no divergence under
    ``"strong"``. Measured on this seed (the gait's ramped commands): NEES 0.77 and
    1.40, CoM 1.15x; over seeds 0-2, 0.76 and 1.21. Without the AHRS frame's alignment
    in the state a slope turned every AHRS axis, and the NEES under mild was 1.77."""
    figures = bench_randomized_ukf(seeds=(0,), steps=200)
    low, high = figures["nees_band_per_dof"]
    for world in ("nominal", "mild"):
        nees = figures["rows"][world]["nees_per_dof"]
        assert low < nees < high, f"{world}: NEES per dof {nees} outside ({low}, {high})"
    assert figures["mild_over_nominal_com_rmse"] < 1.5
    assert figures["rows"]["strong"]["reinitialisations"] == 0


def test_the_ukf_finds_the_turn_of_the_ahrs_frame_on_a_sloping_floor() -> None:
    """On a floor sloping by 3 degrees the AHRS (z against gravity, x toward the magnetic
    field) gives every rod axis turned by the rotation from its frame to the anchors'. The
    UKF estimates that rotation with the nodes: after 10 s of the gait, 0.5 degrees off a
    7.3 degree turn, and its nodes 7.7 mm off against 14.1 with the frames taken as one
    (measured on this seed; seeds 0-1: 1.5 and 1.0 degrees off, nodes 9.8 against 11.8
    and 8.8 against 8.8 mm)."""
    from agents.benchmarks.estimation import record_face_transition
    from agents.recordings.runs import replay, trajectory_errors
    from estimation.ukf import UkfConfig, UkfEstimator
    from tensegrity_gym.model.lie import so3_log

    slope = Randomization(gravity_tilt=(np.radians(3.0), np.radians(3.0)))
    run = record_face_transition(
        "tensegrity_gym/ThreeBarRoll-v0", 2, 100, calibration="true", randomization=slope
    )
    env = _env(slope)
    env.reset(seed=2)
    gravity = env.unwrapped.backend.world_draw.gravity  # type: ignore[attr-defined]
    env.close()
    field = np.array(D.sensors.imu.magnetic_field)
    up = -gravity / np.linalg.norm(gravity)
    north = field - (field @ up) * up
    north /= np.linalg.norm(north)
    turn = so3_log(np.column_stack([north, np.cross(up, north), up]))
    assert np.degrees(np.linalg.norm(turn)) > 5.0
    estimator = UkfEstimator()
    aligned = trajectory_errors(run, replay(run, estimator))
    assert np.degrees(np.linalg.norm(estimator.ahrs_alignment - turn)) < 1.5
    plain = trajectory_errors(run, replay(run, UkfEstimator(UkfConfig(alignment_sigma=None))))
    assert aligned["node_rmse_m"] < 0.75 * plain["node_rmse_m"]


def test_a_reset_rests_until_the_estimator_can_start() -> None:
    # In strong worlds most UWB packets are lost: a reset whose first round reaches too
    # few anchors rests on, sampling, as a robot's driver waits; the UKF starts placed.
    from tensegrity_gym.sim.backend import READY_WAIT, SimBackend

    d = load_robot("three_bar")
    backend = SimBackend(d)
    calls: list[int] = []

    def ready(samples: Any) -> str | None:
        calls.append(len(samples))
        return "a stand-in lack" if len(calls) < 3 else None

    plain, waiting = np.random.default_rng(0), np.random.default_rng(0)
    first = backend.reset(plain).samples
    waited = backend.reset(waiting, ready=ready).samples
    assert calls[0] == len(first) and len(calls) == 3 and calls[2] > calls[1] > calls[0]
    # The wait draws from a child generator: the episode's own stream is where it was.
    assert waiting.bit_generator.state == plain.bit_generator.state
    assert max(s.t for s in waited) == pytest.approx(2 * backend.control_period)
    calls.clear()
    backend.reset(np.random.default_rng(0), ready=lambda samples: calls.append(0) or "never")
    assert len(calls) == round(READY_WAIT / backend.control_period)  # then it gives up
    backend.close()
    env = gym.make("tensegrity_gym/ThreeBarRoll-v0", estimator="ukf", randomization="strong")
    for seed in (1017, 1026):  # their first rounds reach 2 and 3 anchors
        obs, info = env.reset(seed=seed)
        assert np.all(np.isfinite(obs)) and info["estimator_healthy"]
    env.close()


@pytest.mark.parametrize(
    ("randomization", "held"),
    [
        (Randomization(encoder_zero=(-0.015, -0.015)), -0.015),  # the zeros off
        (Randomization(motor_range_offset=(-0.03, -0.03)), None),  # the range below them
    ],
)
def test_a_robot_whose_cables_are_not_as_described_rests_at_reset(
    randomization: Randomization, held: float | None
) -> None:
    """Cables 1.5 cm shorter than their encoders read, or motors whose range ends below
    the description's rest lengths: the robot settles at the lengths its motors hold
    before the episode starts, so that holding the description's rest lengths moves it
    by millimetres (a pose settled with other lengths snapped into shape at the first
    step)."""
    env = _env(randomization)
    env.reset(seed=0)
    backend = env.unwrapped.backend  # type: ignore[attr-defined]
    before = backend.ground_truth().node_positions
    rest = D.rest_lengths[D.actuated]
    true_rest = backend.ground_truth().rest_lengths[D.actuated]
    if held is None:  # at the shifted range's top
        top = np.array([c.motor.max_rest_length for c in backend.world.description.cables
                        if c.motor is not None])  # fmt: skip
        np.testing.assert_allclose(true_rest, top)
        assert np.all(top < rest)
    else:
        np.testing.assert_allclose(true_rest, rest + held)
    env.step(env.unwrapped.targets_to_action(rest))  # type: ignore[attr-defined]
    moved = np.linalg.norm(backend.ground_truth().node_positions - before, axis=1)
    assert moved.max() < 0.005, moved
    env.close()
