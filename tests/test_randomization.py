"""Domain randomisation (issue 16): the ranges, the draws, and the worlds they make."""

from __future__ import annotations

import numpy as np
import pytest

from tensegrity_gym.model.description import load_robot
from tensegrity_gym.model.randomization import (
    RANDOMIZATIONS,
    Randomization,
    register_randomization,
    resolve_randomization,
)

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


@pytest.mark.parametrize("name", ["mild", "strong"])
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
        assert np.all((offsets[actuated] >= low - 1e-5) & (offsets[actuated] <= high + 1e-5))
        low, high = r.passive_rest_offset
        assert np.all((offsets[~actuated] >= low - 1e-5) & (offsets[~actuated] <= high + 1e-5))
        assert len(s["motor_speed"]) == int(actuated.sum())
        assert r.friction[0] <= s["friction"] <= r.friction[1]
        assert 0.0 <= s["gravity_tilt_deg"] <= np.degrees(r.gravity_tilt[1]) + 1e-9
        assert np.linalg.norm(world.gravity) == pytest.approx(D.gravity)
        assert r.command_latency[0] <= world.command_latency <= r.command_latency[1]
        # The robot's geometry is the description's: only its physics departs.
        assert world.robot.nodes == D.nodes
        assert [rod.length for rod in world.robot.rods] == [rod.length for rod in D.rods]


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
    ],
)
def test_bad_ranges_are_refused_by_field(kwargs: dict[str, object], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        Randomization(**kwargs)  # type: ignore[arg-type]


def test_names_resolve_and_a_lab_registers_its_own() -> None:
    assert resolve_randomization(None) is None
    assert resolve_randomization("mild") is RANDOMIZATIONS["mild"]
    with pytest.raises(ValueError, match=r"randomization='wild' must be None, one of \['mild'"):
        resolve_randomization("wild")
    mine = Randomization(rod_mass=(0.95, 1.05))
    register_randomization("lab_test", mine)
    try:
        assert resolve_randomization("lab_test") is mine
    finally:
        del RANDOMIZATIONS["lab_test"]
    with pytest.raises(TypeError, match="expected a Randomization"):
        register_randomization("bad", {"rod_mass": (1, 2)})  # type: ignore[arg-type]
