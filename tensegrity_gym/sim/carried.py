"""A robot carried by hand through a lab's room, ranged by a lab's UWB hardware: the
conditions of a real calibration recording (Caluwaerts et al. 2016 III-C) that the
simulated calibration run does not have.

A lab calibrating its anchors seldom rolls the robot: it carries it about, turning it
every way, at heights a person holds it. Its ranging hardware polls each endcap-anchor
pair about once a second, not in 15 Hz rounds; the robot's modules may not range each
other at all; every pair's offset sits near a common constant of metres (antenna
delays), and multipath adds outliers. :func:`carried_recording` makes such a recording
from the robot's description: the robot keeps its resting shape (its motors hold), and
moves along a smooth random path with a smooth random turn. The IMUs of the rods that
carry one are sampled by the simulator's own :class:`~tensegrity_gym.sim.sensors.ImuModel`.
The truth (anchors, offsets, node positions) comes back beside the samples, for scoring.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from scipy.interpolate import CubicSpline

from tensegrity_gym.model.kinematics import (
    rod_axes,
    rod_centres,
    rod_quaternion_from_axis,
    uwb_module_positions,
)
from tensegrity_gym.model.lie import matrix_to_quat, quat_multiply, so3_exp
from tensegrity_gym.model.samples import UwbRangeSample, ns_to_seconds, seconds_to_ns
from tensegrity_gym.sim.sensors import ImuModel
from tensegrity_gym.sim.world import Snapshot

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.samples import AhrsSample, ImuSample

__all__ = ["LAB_ROOM", "CarriedRecording", "LabRanging", "carried_recording"]

LAB_ROOM: tuple[tuple[float, float, float], ...] = (
    (0.3, 0.4, 4.7), (9.6, 0.6, 4.5), (9.7, 14.5, 4.6), (0.4, 14.6, 4.4),
    (5.1, 0.2, 0.4), (9.8, 7.4, 1.1), (4.8, 14.8, 0.5), (0.2, 7.2, 2.3),
)  # fmt: skip
"""Eight anchors (m) in a 10 x 15 m room: four under the ceiling's corners, four on
the walls, low and at mid height, as a lab puts them."""


@dataclass(frozen=True)
class LabRanging:
    """How a lab's UWB hardware ranges; lengths in metres, rates in Hz."""

    pair_rate: tuple[float, float] = (1.0, 3.0)
    """Each endcap-anchor pair ranges at a rate drawn in this interval (Hz)."""
    robot_ranging: bool = False
    """The robot's modules range each other too (at the same rates)."""
    common_offset: float = 4.0
    """The constant every pair's offset o_ij sits near (m): antenna delays."""
    offset_std: float = 0.05
    """Scatter of the pair offsets about ``common_offset`` (m)."""
    noise: float = 0.03
    """Standard deviation of one range (m)."""
    loss: float = 0.3
    """Share of ranges lost (rejected as non-line-of-sight)."""
    outlier_share: float = 0.01
    """Share of ranges that took a reflected path."""
    outlier_excess: tuple[float, float] = (0.3, 1.5)
    """A reflected range reads long by an amount in this interval (m)."""
    message_period: float = 0.1
    """The ranges are gathered into one message per this many seconds, as a lab's
    ROS node does (Caluwaerts et al. 2016 III-B: 10 Hz)."""


@dataclass(frozen=True)
class CarriedRecording:
    """What :func:`carried_recording` made: the samples a lab records, and the truth."""

    uwb: list[UwbRangeSample]
    """One message per ``message_period``: the ranges that arrived in it."""
    imu: list[ImuSample]
    ahrs: list[AhrsSample]
    anchors: NDArray[np.float64]
    """(A, 3) m, the room's frame: the floor at z = 0."""
    offsets: NDArray[np.float64]
    """(n + A, n + A) m, the true o_ij."""
    times: NDArray[np.float64]
    """(T,) s."""
    nodes: NDArray[np.float64]
    """(T, n, 3) m, the true node positions at ``times``."""
    ranging: LabRanging = field(default_factory=LabRanging)


_STEP = 4.0  # s between the path's waypoints
_TRAVEL = 1.2  # m between waypoints: about 0.3 m/s, a slow walk
_TURN = 0.7  # rad between waypoints' orientations
_REACH = 1.0  # m: how far above its lowest the robot's centre is held
_MARGIN = 1.0  # m: the path keeps this far from the room's walls


def _path(
    rng: np.random.Generator, seconds: float, low: NDArray[np.float64], high: NDArray[np.float64]
) -> tuple[CubicSpline, CubicSpline]:
    """A smooth random walk: centre (m) and rotation vector (rad) splines over time."""
    k = int(np.ceil(seconds / _STEP)) + 2
    centre = np.empty((k, 3))
    centre[0] = rng.uniform(low, high)
    for i in range(1, k):
        step = rng.normal(0.0, 1.0, 3) * np.array([1.0, 1.0, 0.3])
        nxt = centre[i - 1] + _TRAVEL * step / max(float(np.linalg.norm(step)), 1e-9)
        # Reflected off the walls, floor and reach: the walk stays in the room.
        nxt = np.where(nxt < low, 2 * low - nxt, nxt)
        centre[i] = np.clip(np.where(nxt > high, 2 * high - nxt, nxt), low, high)
    turn = np.cumsum(rng.normal(0.0, _TURN / np.sqrt(3.0), (k, 3)), axis=0)
    turn[0] = rng.normal(0.0, np.pi / 2, 3)  # a person picks it up any way round
    turn[1:] += turn[0]
    knots = _STEP * np.arange(k)
    return CubicSpline(knots, centre), CubicSpline(knots, turn)


def _poses(
    description: RobotDescription, centre: CubicSpline, turn: CubicSpline, t: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Node positions (T, n, 3) at times ``t``: the resting shape, turned and moved."""
    rest = description.initial_positions
    shape = rest - rest.mean(axis=0)
    R = so3_exp(turn(t))  # (T, 3, 3)
    return np.asarray(np.einsum("tij,nj->tni", R, shape) + centre(t)[:, None, :])


def _ranges(
    description: RobotDescription,
    anchors: NDArray[np.float64],
    ranging: LabRanging,
    path: tuple[CubicSpline, CubicSpline],
    seconds: float,
    rng: np.random.Generator,
) -> tuple[NDArray[np.float64], NDArray[np.intp], NDArray[np.float64], NDArray[np.float64]]:
    """Every range that arrived: times (k,), pairs (k, 2), ranges (k,), and the true
    offsets (n + A, n + A)."""
    n, A = description.n_nodes, len(anchors)
    pairs = [(n + a, j) for a in range(A) for j in range(n)]
    if ranging.robot_ranging:
        pairs += [(i, j) for i in range(n) for j in range(i + 1, n)]
    pair = np.array(pairs, dtype=np.intp)
    o = rng.normal(ranging.common_offset, ranging.offset_std, (n + A, n + A))
    offsets = np.triu(o, 1) + np.triu(o, 1).T
    rate = rng.uniform(*ranging.pair_rate, len(pair))
    phase = rng.uniform(0.0, 1.0, len(pair)) / rate
    count = np.floor((seconds - phase) * rate).astype(np.intp) + 1
    which = np.repeat(np.arange(len(pair)), count)
    first = np.r_[0, np.cumsum(count)[:-1]]
    t = phase[which] + (np.arange(len(which)) - first[which]) / rate[which]
    t = t + rng.normal(0.0, 0.02, len(t)) / rate[which]  # the polling jitters
    kept = (rng.random(len(t)) >= ranging.loss) & (t >= 0.0) & (t < seconds)
    t, which = t[kept], which[kept]
    order = np.argsort(t, kind="stable")
    t, which = t[order], which[order]
    modules = np.concatenate(
        [uwb_module_positions(description, _poses(description, *path, t)),
         np.broadcast_to(anchors, (len(t), A, 3))], axis=1,
    )  # fmt: skip
    i, j = pair[which, 0], pair[which, 1]
    k = np.arange(len(t))
    dist = np.linalg.norm(modules[k, i] - modules[k, j], axis=1)
    m = dist + offsets[i, j] + rng.normal(0.0, ranging.noise, len(t))
    reflected = rng.random(len(t)) < ranging.outlier_share
    m[reflected] += rng.uniform(*ranging.outlier_excess, int(reflected.sum()))
    return t, pair[which], m, offsets


def _messages(
    t: NDArray[np.float64], pairs: NDArray[np.intp], m: NDArray[np.float64], period: float
) -> list[UwbRangeSample]:
    """The ranges gathered into one message per ``period`` s, stamped at its end."""
    bins = np.floor(t / period).astype(np.intp)
    out = []
    for b in np.unique(bins):
        rows = bins == b
        # Stamps on whole nanoseconds, as a bag keeps them.
        times = np.array([ns_to_seconds(seconds_to_ns(x)) for x in t[rows]])
        stamp = ns_to_seconds(seconds_to_ns((b + 1) * period))
        out.append(UwbRangeSample(stamp, times, pairs[rows].copy(), m[rows].copy()))
    return out


def _imu(
    description: RobotDescription,
    path: tuple[CubicSpline, CubicSpline],
    seconds: float,
    rng: np.random.Generator,
    rate: float,
) -> tuple[list[ImuSample], list[AhrsSample]]:
    """The rods' IMUs along the path at ``rate`` Hz, by the simulator's IMU model."""
    model = ImuModel(description.sensors.imu, description)
    t = np.arange(0.0, seconds, 1.0 / rate)
    nodes = _poses(description, *path, t)
    rn = description.rod_nodes
    rest_axes = rod_axes(description.initial_positions, rn)
    R = so3_exp(path[1](t))  # (T, 3, 3)
    body = quat_multiply(matrix_to_quat(R)[:, None, :], rod_quaternion_from_axis(rest_axes)[None])
    centres = rod_centres(nodes, rn)
    velocity = np.gradient(centres, t, axis=0)
    dR = np.gradient(R, t, axis=0)
    skew = np.einsum("tij,tkj->tik", dR, R)  # dR R^T: the angular rate's hat, world frame
    omega = np.stack([skew[:, 2, 1], skew[:, 0, 2], skew[:, 1, 0]], axis=1)
    snaps = [
        Snapshot(float(tk), centres[k], body[k], velocity[k],
                 np.tile(omega[k], (description.n_rods, 1)).tolist(), nodes[k].tolist(), [])
        for k, tk in enumerate(t)
    ]  # fmt: skip
    model.reset(snaps[0], rng)
    return model.sample(snaps[1:], rng)


def carried_recording(
    description: RobotDescription,
    rng: np.random.Generator,
    *,
    seconds: float = 240.0,
    anchors: NDArray[np.float64] | None = None,
    ranging: LabRanging | None = None,
    imu_rate: float | None = None,
) -> CarriedRecording:
    """The robot carried for ``seconds`` through the room of ``anchors`` (A, 3) m
    (default :data:`LAB_ROOM`), ranged as ``ranging`` says (default
    :class:`LabRanging`: 1-3 Hz pairs, no robot-robot ranging, a 4 m common offset),
    its IMUs sampled at ``imu_rate`` Hz (default: the description's). Every draw comes
    from ``rng``."""
    ranging = ranging or LabRanging()
    anchors = np.asarray(LAB_ROOM if anchors is None else anchors, dtype=np.float64)
    rest = description.initial_positions
    # The centre stays high enough that no endcap, however the robot is turned, is
    # under the floor.
    lowest = float(np.max(np.linalg.norm(rest - rest.mean(axis=0), axis=1))) + 0.05
    low = np.r_[anchors[:, :2].min(axis=0) + _MARGIN, lowest]
    high = np.r_[anchors[:, :2].max(axis=0) - _MARGIN, lowest + _REACH]
    path = _path(rng, seconds, low, high)
    t, pairs, m, offsets = _ranges(description, anchors, ranging, path, seconds, rng)
    imu, ahrs = _imu(description, path, seconds, rng, imu_rate or description.sensors.imu.rate)
    times = np.arange(0.0, seconds, 0.1)
    return CarriedRecording(
        uwb=_messages(t, pairs, m, ranging.message_period), imu=imu, ahrs=ahrs,
        anchors=anchors, offsets=offsets, times=times,
        nodes=_poses(description, *path, times), ranging=ranging,
    )  # fmt: skip
