"""Where the invariant EKF starts: orientation from gravity and the magnetic field, gyro
bias from the robot at rest, position by convention.

What a robot carrying only an IMU, encoders and contacts can know at reset: its tilt
(gravity, through the accelerometer), its heading (the magnetometer against the local
field the description gives, as a lab would look it up), and that it is at rest (the
gyro then reads its bias). Where it stands it cannot know: the estimator's world frame
puts the robot's centre of mass above the origin, its lowest endcap on the ground
(z = its endcap radius), as odometry does.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from tensegrity_gym.model.kinematics import center_of_mass
from tensegrity_gym.model.lie import so3_exp
from tensegrity_gym.model.samples import ImuSample

if TYPE_CHECKING:
    from collections.abc import Sequence

    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.samples import Sample

__all__ = ["base_imu_readings", "initial_position", "levelled", "triad_orientation"]


def base_imu_readings(
    samples: Sequence[Sample], rod: int
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """The gyro (k, 3) rad/s, accelerometer (k, 3) m/s^2 and magnetometer (k, 3) T
    readings of the IMU on rod ``rod`` among ``samples``, in their order."""
    imu = [s for s in samples if isinstance(s, ImuSample) and s.rod == rod]
    if not imu:
        empty = np.zeros((0, 3))
        return empty, empty, empty
    return (
        np.array([s.gyro for s in imu], dtype=np.float64),
        np.array([s.accel for s in imu], dtype=np.float64),
        np.array([s.mag for s in imu], dtype=np.float64),
    )


def _unit(v: NDArray[np.float64]) -> NDArray[np.float64] | None:
    n = float(np.linalg.norm(v))
    return v / n if np.isfinite(n) and n > 1e-12 else None


def levelled(R: NDArray[np.float64], accel: NDArray[np.float64]) -> NDArray[np.float64]:
    """The body-to-world rotation (3, 3) nearest ``R`` under which the specific force
    ``accel`` (3,) (up, in the body frame) points up: ``R`` turned by the least rotation
    that takes its up onto the world's, so that its heading is kept. ``R`` itself where
    ``accel`` gives no direction."""
    up_b = _unit(accel)
    if up_b is None:
        return R
    a, b = R @ up_b, np.array([0.0, 0.0, 1.0])
    axis = np.cross(a, b)
    sin, cos = float(np.linalg.norm(axis)), float(a @ b)
    if sin < 1e-12:  # already up, or upside down: half a turn about a horizontal axis
        return R if cos > 0 else so3_exp(np.array([np.pi, 0.0, 0.0])) @ R
    return np.asarray(so3_exp(axis / sin * np.arctan2(sin, cos)) @ R)


def triad_orientation(
    accel: NDArray[np.float64],
    mag: NDArray[np.float64],
    field: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Body-to-world rotation (3, 3) of an IMU at rest reading specific force ``accel``
    (3,) m/s^2 (up, in the body frame) and magnetic field ``mag`` (3,) T, where the
    world's field is ``field`` (3,) T (TRIAD: gravity exact, the field for heading).

    Without a usable field (zero, or along gravity) the heading is that of the body x
    axis projected on the ground, as good as any: heading is then unobservable."""
    up_b = _unit(accel)
    if up_b is None:
        return np.eye(3)
    up_w = np.array([0.0, 0.0, 1.0])
    north_b = _unit(mag - (mag @ up_b) * up_b)
    north_w = _unit(field - (field @ up_w) * up_w)
    if north_b is None or north_w is None:
        x = np.array([1.0, 0.0, 0.0])
        north_b = _unit(x - (x @ up_b) * up_b)
        if north_b is None:
            north_b = _unit(np.array([0.0, 1.0, 0.0]) - up_b[1] * up_b)
        north_w = np.array([1.0, 0.0, 0.0])
    assert north_b is not None
    body = np.column_stack([up_b, north_b, np.cross(up_b, north_b)])
    world = np.column_stack([up_w, north_w, np.cross(up_w, north_w)])
    return np.asarray(world @ body.T)


def initial_position(
    description: RobotDescription,
    rotation: NDArray[np.float64],
    shape: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Position (3,) m of the body frame that puts the centre of mass of the endcaps at
    ``shape`` (n_nodes, 3, body frame) above the world origin and the lowest endcap's
    centre one endcap radius above the ground (z = 0)."""
    world = shape @ rotation.T
    com = center_of_mass(world, description.node_masses)
    lowest = int(np.argmin(world[:, 2]))
    radius = description.node_radii[lowest]
    return np.array([-com[0], -com[1], radius - world[lowest, 2]])
