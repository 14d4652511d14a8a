"""What a robot carries: the description's ``carries`` (validated, round-tripped), the
simulator producing only those kinds, and ``make`` refusing an estimator whose needs
the robot lacks, also on the robot link before it is reached."""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, cast

import gymnasium as gym
import numpy as np
import pytest
import yaml

from hardware.link.process import free_port
from tensegrity_gym.model.description import (
    DescriptionError,
    dump_robot,
    load_robot,
    loads_robot,
    robot_document,
)
from tensegrity_gym.model.samples import GROUND_TRUTH, SAMPLE_KINDS, ContactSample
from tensegrity_gym.sim.backend import SimBackend

if TYPE_CHECKING:
    from hardware.link import ZenohDriver
    from tensegrity_gym.envs.tensegrity_env import TensegrityEnv

THREE_BAR = load_robot("three_bar")
SIM_ID = "tensegrity_gym/ThreeBarRoll-v0"
HW_ID = "tensegrity_gym_hardware/ThreeBarRoll-v0"


def _without(*kinds: str) -> tuple[str, ...]:
    return tuple(k for k in SAMPLE_KINDS if k not in kinds)


def _carrying(carries: object) -> str:
    """The three-bar preset's YAML text with ``carries`` set to ``carries``."""
    doc = robot_document(THREE_BAR) | {"carries": carries}
    return str(yaml.safe_dump(doc, sort_keys=False))


# ------------------------------------------------------------------ the description


def test_absent_carries_means_every_kind_and_is_not_written() -> None:
    assert THREE_BAR.carries is None
    assert THREE_BAR.sample_kinds == frozenset(SAMPLE_KINDS)
    assert GROUND_TRUTH not in THREE_BAR.sample_kinds
    assert "carries" not in robot_document(THREE_BAR)


def test_carries_round_trips_in_the_table_order() -> None:
    d = loads_robot(_carrying(["uwb", "imu", "encoders"]), "mem://robot")
    assert d.carries == ("imu", "encoders", "uwb")
    assert d.sample_kinds == frozenset({"imu", "encoders", "uwb"})
    back = loads_robot(dump_robot(d))
    assert back == d and back.carries == d.carries
    assert loads_robot(dump_robot(THREE_BAR)).carries is None


@pytest.mark.parametrize(
    ("carries", "words"),
    [
        (["imu", "lidar"], r"mem://robot: carries\[1\]: unknown name 'lidar'; valid: \[.*'rgbd'"),
        (["imu", "uwb", "imu"], r"mem://robot: carries\[2\]: 'imu' is named twice"),
        ("imu", r"mem://robot: carries: expected a list, got str"),
        ([], r"mem://robot: carries: expected at least 1"),
        (["imu", 3], r"mem://robot: carries\[1\]: expected a non-empty string"),
    ],
)
def test_a_bad_carries_is_refused_naming_file_and_field(carries: object, words: str) -> None:
    with pytest.raises(DescriptionError, match=words):
        loads_robot(_carrying(carries), "mem://robot")


# ------------------------------------------------------------------ the simulator


def test_the_simulator_gives_no_sample_of_a_kind_not_carried() -> None:
    d = dataclasses.replace(THREE_BAR, carries=_without("contacts", "ahrs"))
    backend = SimBackend(d, camera=True)
    try:
        samples = list(backend.reset(np.random.default_rng(0)).samples)
        samples += backend.step(d.rest_lengths[d.actuated]).samples
    finally:
        backend.close()
    names = {cls: name for name, cls in SAMPLE_KINDS.items()}
    produced = {names[type(s)] for s in samples}
    assert not any(isinstance(s, ContactSample) for s in samples)
    assert produced == d.sample_kinds == backend.sample_kinds() - {GROUND_TRUTH}


def test_the_simulator_says_rgbd_only_for_a_camera_it_carries_and_renders() -> None:
    assert "rgbd" not in SimBackend(THREE_BAR).sample_kinds()
    assert "rgbd" in SimBackend(THREE_BAR, camera=True).sample_kinds()
    no_camera = dataclasses.replace(THREE_BAR, carries=_without("rgbd"))
    assert "rgbd" not in SimBackend(no_camera, camera=True).sample_kinds()


@pytest.mark.parametrize(("estimator", "kind"), [("ukf", "uwb"), ("icp", "rgbd")])
def test_make_refuses_in_simulation_an_estimator_the_robot_cannot_serve(
    estimator: str, kind: str
) -> None:
    robot = dataclasses.replace(THREE_BAR, carries=_without(kind))
    with pytest.raises(ValueError, match=rf"^make: estimator '{estimator}' needs {kind} \(") as e:
        gym.make(SIM_ID, estimator=estimator, robot=robot)
    assert "\n" not in str(e.value)


# ------------------------------------------------------------------ the robot link


@pytest.mark.parametrize(("estimator", "kind"), [("ukf", "uwb"), ("icp", "rgbd")])
def test_make_refuses_on_the_link_without_reaching_the_robot(estimator: str, kind: str) -> None:
    """No robot listens on the port: the refusal comes from the description alone."""
    robot = dataclasses.replace(THREE_BAR, carries=_without(kind))
    driver = f"zenoh/tcp/127.0.0.1:{free_port()}"
    with pytest.raises(ValueError, match=rf"^make: estimator '{estimator}' needs {kind} \(") as e:
        gym.make(HW_ID, estimator=estimator, robot=robot, driver=driver)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("estimator", ["ukf", "icp", "oracle"])
def test_make_accepts_on_the_link_without_connecting(estimator: str) -> None:
    env = gym.make(HW_ID, estimator=estimator, driver=f"zenoh/tcp/127.0.0.1:{free_port()}")
    try:
        driver = cast("ZenohDriver", cast("TensegrityEnv", env.unwrapped).backend)
        assert not driver.connected
        assert driver.sample_kinds() == frozenset(SAMPLE_KINDS) | {GROUND_TRUTH}
    finally:
        env.close()
