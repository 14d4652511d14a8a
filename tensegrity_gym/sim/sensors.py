"""Sensor models: turn the simulator's true state into the raw samples a robot gives.

Each model has its own rate and draws its noise from the generator it is handed (the
env's ``np_random``), in one vectorised call per control period so that the same seed
gives the same samples bit for bit.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import imufusion
import numpy as np

from tensegrity_gym.model.kinematics import member_lengths, uwb_module_positions
from tensegrity_gym.model.lie import quat_conjugate, quat_rotate
from tensegrity_gym.model.samples import (
    AhrsSample,
    CableLengthSample,
    ContactSample,
    EncoderSample,
    ImuSample,
    RgbdFrame,
    UwbRangeSample,
    ns_to_seconds,
    seconds_to_ns,
)

if TYPE_CHECKING:
    from collections.abc import Sequence

    from numpy.typing import NDArray

    from tensegrity_gym.model.description import (
        CableLengthConfig,
        CameraConfig,
        ContactConfig,
        EncoderConfig,
        ImuConfig,
        RobotDescription,
        UwbConfig,
    )
    from tensegrity_gym.sim.world import Snapshot

__all__ = [
    "CableLengthModel",
    "CameraModel",
    "ContactModel",
    "EncoderModel",
    "ImuModel",
    "SensorSchedule",
    "UwbModel",
]

SPEED_OF_LIGHT = 299_792_458.0
_WXYZ_TO_XYZW = np.array([1, 2, 3, 0])
"""imufusion's quaternion order (w, x, y, z) to the project's (x, y, z, w)."""


class SensorSchedule:
    """Sample times of one sensor at a fixed rate, phase kept across control periods.

    The k-th time is counted from the start in whole nanoseconds (see ``seconds_to_ns``),
    not accumulated, so stamps are exact and a rate like 15 Hz does not drift.
    """

    def __init__(self, rate: float) -> None:
        self.rate = rate
        self.start_ns = 0
        self.count = 0

    def reset(self, t: float) -> None:
        self.start_ns = seconds_to_ns(t)
        self.count = 0

    def due(self, t_end: float) -> list[float]:
        """Sample times up to and including ``t_end``."""
        end = seconds_to_ns(t_end)
        times = []
        while (t_ns := self.start_ns + round(self.count * 1e9 / self.rate)) <= end:
            times.append(ns_to_seconds(t_ns))
            self.count += 1
        return times


class ImuModel:
    """IMU at the centre of each rod that carries one (``description.imu_rods``):
    accelerometer (with gravity), gyro, magnetometer, biases, and the orientation an
    on-board AHRS (imufusion, Madgwick's) computes from them."""

    def __init__(self, config: ImuConfig, description: RobotDescription) -> None:
        self.config = config
        self.gravity = np.array([0.0, 0.0, -description.gravity])
        self.field = np.array(config.magnetic_field)
        self.rods = list(description.imu_rods)
        self._all = self.rods == list(range(description.n_rods))  # no selection to make
        self.n_rods = len(self.rods)
        self.accel_bias = np.zeros((self.n_rods, 3))
        self.gyro_bias = np.zeros((self.n_rods, 3))
        self.ahrs: list[imufusion.Ahrs] = []
        self._last_t = 0.0
        self._last_v = np.zeros((self.n_rods, 3))

    def _new_ahrs(self) -> imufusion.Ahrs:
        settings = imufusion.AhrsSettings()
        settings.convention = imufusion.CONVENTION_NWU  # x north (along the field), z up
        settings.gain = self.config.ahrs_gain
        settings.gyroscope_range = float(np.degrees(self.config.gyro_full_scale))
        settings.acceleration_rejection = 10.0
        settings.magnetic_rejection = 10.0
        settings.sample_rate = round(self.config.rate)
        settings.rejection_timeout = int(5 * self.config.rate)
        ahrs = imufusion.Ahrs()
        ahrs.set_settings(settings)
        return ahrs

    def reset(self, snap: Snapshot, rng: np.random.Generator, warmup: float = 3.0) -> None:
        """Draw the biases and let the AHRS converge while the robot rests for ``warmup`` s,
        as a real robot does after power-up."""
        c = self.config
        self.accel_bias = rng.normal(0.0, c.accel_bias, (self.n_rods, 3))
        self.gyro_bias = rng.normal(0.0, c.gyro_bias, (self.n_rods, 3))
        self.ahrs = [self._new_ahrs() for _ in range(self.n_rods)]
        self._last_t = snap.t
        self._last_v = self._carried(np.asarray(snap.rod_linear_velocities, dtype=np.float64))
        n = int(warmup * c.rate)
        q = self._carried(np.asarray(snap.rod_quaternions, dtype=np.float64))
        still = np.zeros((1, self.n_rods, 3))
        accel, gyro, mag = self._measure(
            q[None], still, still, rng.standard_normal((n, self.n_rods, 9))
        )
        for k in range(n):
            for r, ahrs in enumerate(self.ahrs):
                ahrs.update(np.degrees(gyro[k, r]), accel[k, r] / 9.81, mag[k, r])

    def _carried(self, per_rod: NDArray[np.float64]) -> NDArray[np.float64]:
        """``per_rod`` (..., n_rods, k) reduced to the rods that carry an IMU."""
        return per_rod if self._all else per_rod[..., self.rods, :]

    def _measure(
        self,
        quats: NDArray[np.float64],
        accel_world: NDArray[np.float64],
        omega_world: NDArray[np.float64],
        noise: NDArray[np.float64],
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Body-frame accelerometer, gyro, magnetometer readings, each (k, r, 3)."""
        c = self.config
        inv = quat_conjugate(quats)
        f = quat_rotate(inv, accel_world - self.gravity)
        w = quat_rotate(inv, omega_world)
        m = quat_rotate(inv, np.broadcast_to(self.field, omega_world.shape))
        # A MEMS IMU saturates at its full scale (an impact reads as the full scale).
        a_max, w_max = c.accel_full_scale, c.gyro_full_scale
        accel = np.clip(f + self.accel_bias + c.accel_noise * noise[..., 0:3], -a_max, a_max)
        gyro = np.clip(w + self.gyro_bias + c.gyro_noise * noise[..., 3:6], -w_max, w_max)
        mag = m + c.mag_noise * noise[..., 6:9]
        return accel, gyro, mag

    def sample(
        self, snaps: Sequence[Snapshot], rng: np.random.Generator
    ) -> tuple[list[ImuSample], list[AhrsSample]]:
        if not snaps:
            return [], []
        t = np.array([s.t for s in snaps])
        q = self._carried(np.array([s.rod_quaternions for s in snaps], dtype=np.float64))
        v = self._carried(np.array([s.rod_linear_velocities for s in snaps], dtype=np.float64))
        w = self._carried(np.array([s.rod_angular_velocities for s in snaps], dtype=np.float64))
        # Mean acceleration over each sample interval, as an IMU's anti-alias filter gives.
        prev_v = np.concatenate([self._last_v[None], v[:-1]])
        prev_t = np.concatenate([[self._last_t], t[:-1]])
        dt = np.maximum(t - prev_t, 1e-9)[:, None, None]
        accel_world = (v - prev_v) / dt
        self._last_t, self._last_v = float(t[-1]), v[-1]
        noise = rng.standard_normal((len(snaps), self.n_rods, 9))
        accel, gyro, mag = self._measure(q, accel_world, w, noise)
        gyro_deg = np.degrees(gyro)
        accel_g = accel / 9.81
        wxyz = np.empty((len(snaps), self.n_rods, 4))
        for k in range(len(snaps)):
            for r, ahrs in enumerate(self.ahrs):
                ahrs.update(gyro_deg[k, r], accel_g[k, r], mag[k, r])
                wxyz[k, r] = ahrs.get_quaternion()
        xyzw = wxyz[..., _WXYZ_TO_XYZW]
        times = t.tolist()
        at = [(k, r, rod) for k in range(len(snaps)) for r, rod in enumerate(self.rods)]
        imu = [ImuSample(times[k], rod, accel[k, r], gyro[k, r], mag[k, r]) for k, r, rod in at]
        return imu, [AhrsSample(times[k], rod, xyzw[k, r]) for k, r, rod in at]


class EncoderModel:
    """Motor encoders: actuated cables' rest lengths, quantised."""

    def __init__(self, config: EncoderConfig, description: RobotDescription) -> None:
        self.config = config
        self.actuated = description.actuated
        self.offsets = np.zeros(len(self.actuated))
        """(m,) m by which each cable is longer than its encoder reads (a randomised
        world's zero errors; 0 in the nominal one)."""

    def sample(self, snaps: Sequence[Snapshot]) -> list[EncoderSample]:
        res = self.config.resolution
        out = []
        for s in snaps:
            rest = np.asarray(s.rest_lengths)[self.actuated] - self.offsets
            if res > 0.0:
                rest = np.round(rest / res) * res
            out.append(EncoderSample(s.t, rest))
        return out


class CableLengthModel:
    """Stretch sensors along every cable (Lu et al. 2022): noisy endcap distances, and wrong
    while a cable is slack, when the sensor buckles and reads its own length."""

    def __init__(self, config: CableLengthConfig, description: RobotDescription) -> None:
        self.config = config
        self.pairs = description.cable_nodes

    def sample(
        self, snaps: Sequence[Snapshot], rng: np.random.Generator
    ) -> list[CableLengthSample]:
        if not snaps:
            return []
        nodes = np.array([s.node_positions for s in snaps])
        rest = np.array([s.rest_lengths for s in snaps])
        true = member_lengths(nodes, self.pairs)
        slack = true < rest
        read = np.where(slack, rest + self.config.slack_bias, true)
        read = read + self.config.noise * rng.standard_normal(read.shape)
        return [CableLengthSample(s.t, read[k]) for k, s in enumerate(snaps)]


class ContactModel:
    """Endcap-ground contact flags from the gap between endcap and the flat ground."""

    def __init__(self, config: ContactConfig, description: RobotDescription) -> None:
        self.threshold = config.threshold
        self.radius = description.node_radii

    def sample(self, snaps: Sequence[Snapshot]) -> list[ContactSample]:
        out = []
        for s in snaps:
            z = np.asarray(s.node_positions)[:, 2]
            out.append(ContactSample(s.t, z - self.radius < self.threshold))
        return out


ANCHOR_PLACEMENT_STD = 0.05
"""m, per axis: how far from the description's layout a lab's anchors end up (tripods
put by hand at the marked spots)."""


class UwbModel:
    """DW1000 ranging by timed broadcast, symmetric double-sided two-way (Caluwaerts et al. 2016
    III).

    Each round, every module polls in turn (packets ``packet_spacing`` apart), then each
    responds and sends a final message. Each module computes eq. 5-6 from its six local
    time stamps; local clocks drift, stamps are noisy, and antenna delays add the per-pair
    offset o_ij. Robot module pairs give two measurements a round, anchor-module pairs one.
    A share of packets (drawn per episode) is rejected as non-line-of-sight.

    The module positions are taken at the end of the round: a round lasts a few tens of
    milliseconds, over which the robot moves by millimetres.
    """

    def __init__(self, config: UwbConfig, description: RobotDescription) -> None:
        self.config = config
        self.description = description
        n = description.n_nodes
        anchors = np.asarray(config.anchors, dtype=np.float64).reshape(-1, 3)
        self.anchors = anchors
        self.n_modules = n + len(anchors)
        robot = [(i, j) for i in range(n) for j in range(n) if i != j]
        # Anchors initiate, robot modules compute: one measurement per anchor pair.
        anchor = [(n + a, j) for a in range(len(anchors)) for j in range(n)]
        self.pairs = np.array(robot + anchor, dtype=np.intp).reshape(-1, 2)
        self.offsets = np.zeros((self.n_modules, self.n_modules))
        self.drift = np.zeros(self.n_modules)
        self.reject_fraction = 0.0

    def draw_world(self, rng: np.random.Generator) -> None:
        """What stays fixed for the life of a lab: where the anchors were put (the
        description's layout, each within :data:`ANCHOR_PLACEMENT_STD` per axis), every
        pair's offset o_ij (antenna delays) and every module's clock drift."""
        c = self.config
        nominal = np.asarray(c.anchors, dtype=np.float64).reshape(-1, 3)
        self.anchors = nominal + rng.normal(0.0, ANCHOR_PLACEMENT_STD, nominal.shape)
        o = rng.normal(c.offset_mean, c.offset_std, (self.n_modules, self.n_modules))
        self.offsets = np.triu(o, 1) + np.triu(o, 1).T
        self.drift = rng.uniform(-1.0, 1.0, self.n_modules) * c.clock_drift_ppm * 1e-6

    def reset(self, rng: np.random.Generator) -> None:
        """What changes between runs: the share of packets lost to multipath."""
        self.reject_fraction = float(rng.uniform(*self.config.reject_fraction))

    def module_positions(self, nodes: NDArray[np.float64]) -> NDArray[np.float64]:
        """Positions of all modules (n_modules, 3) for node positions (n, 3)."""
        return np.concatenate([uwb_module_positions(self.description, nodes), self.anchors])

    def sample(self, snaps: Sequence[Snapshot], rng: np.random.Generator) -> list[UwbRangeSample]:
        c = self.config
        out = []
        N = self.n_modules
        s = c.packet_spacing
        i, j = self.pairs[:, 0], self.pairs[:, 1]
        for snap in snaps:
            pos = self.module_positions(np.asarray(snap.node_positions))
            dist = np.linalg.norm(pos[j] - pos[i], axis=1)
            tof = (dist + self.offsets[i, j]) / SPEED_OF_LIGHT
            # Global send times within the round: poll by i, response by j, final by i.
            t_poll = i * s
            t_resp = (N + j) * s
            t_final = (2 * N + i) * s
            stamps = c.timestamp_noise * rng.standard_normal((len(i), 6))
            ei, ej = 1.0 + self.drift[i], 1.0 + self.drift[j]
            t_sp = ei * t_poll + stamps[:, 0]
            t_rp = ej * (t_poll + tof) + stamps[:, 1]
            t_sr = ej * t_resp + stamps[:, 2]
            t_rr = ei * (t_resp + tof) + stamps[:, 3]
            t_sf = ei * t_final + stamps[:, 4]
            t_rf = ej * (t_final + tof) + stamps[:, 5]
            a = t_sf - t_sp  # eq. 1
            b = t_rf - t_rp  # eq. 2
            cc = t_rf - t_sr  # eq. 3
            d = t_sf - t_rr  # eq. 4
            m = 0.5 * SPEED_OF_LIGHT * (cc - d * b / a)  # eq. 6: m_{j,i}
            keep = rng.random(len(i)) >= self.reject_fraction
            # The snapshot closes the round: each measurement is stamped when its final
            # message arrives, so all of a round's times lie within it, none in the future.
            times = np.round((snap.t - 3 * N * s + t_final[keep] + s) * 1e9) / 1e9  # whole ns
            out.append(UwbRangeSample(snap.t, times, self.pairs[keep], m[keep]))
        return out


FLYING_PIXEL_STEP = 0.05
"""m: a depth step between two neighbouring pixels beyond which the nearer lies on a
depth edge, where a real sensor mixes the two surfaces (:attr:`CameraConfig.flying_pixels`)."""


def _no_return(depth: NDArray[np.float32], far: float) -> NDArray[np.bool_]:
    """(H, W) the pixels whose true depth is the far plane: nothing there to return."""
    return np.asarray(depth >= 0.999 * far)


def _deepest_neighbour(depth: NDArray[np.float32], far: float) -> NDArray[np.float32]:
    """(H, W) the largest true depth among each pixel's four neighbours and itself,
    leaving out those with no return (at the far plane): nothing to mix with there."""
    d = np.where(_no_return(depth, far), np.float32(0.0), depth)
    out = d.copy()
    np.maximum(out[1:], d[:-1], out=out[1:])
    np.maximum(out[:-1], d[1:], out=out[:-1])
    np.maximum(out[:, 1:], d[:, :-1], out=out[:, 1:])
    np.maximum(out[:, :-1], d[:, 1:], out=out[:, :-1])
    return out


def _flying_pixels(
    noisy: NDArray[np.float32], depth: NDArray[np.float32], share: float, far: float,
    rng: np.random.Generator,
) -> None:  # fmt: skip
    """Move ``share`` of the pixels on the near side of a depth edge of ``depth`` (H, W)
    (m, true) to a depth drawn uniformly between theirs and their deepest neighbour's,
    in place in ``noisy``: a depth sensor's pixel that sees two surfaces reads between
    them (its colour stays the near surface's)."""
    behind = _deepest_neighbour(depth, far) - depth
    rows, cols = np.nonzero(behind > FLYING_PIXEL_STEP)
    picked = rng.random(len(rows)) < share
    rows, cols = rows[picked], cols[picked]
    mix = rng.random(len(rows)).astype(np.float32)
    noisy[rows, cols] += mix * behind[rows, cols]


class CameraModel:
    """The fixed overhead RGB-D camera: depth noise grows with the square of the range;
    pixels on depth edges may read between the two surfaces (flying pixels)."""

    def __init__(self, config: CameraConfig) -> None:
        self.config = config

    def frame(
        self,
        t: float,
        rgb: NDArray[np.uint8],
        depth: NDArray[np.float32],
        rng: np.random.Generator,
    ) -> RgbdFrame:
        c = self.config
        # In float32 throughout: the frame is float32, and this runs every camera frame.
        sigma = np.float32(c.depth_noise) + np.float32(c.depth_noise_quadratic) * depth * depth
        noisy = depth + sigma * rng.standard_normal(depth.shape, dtype=np.float32)
        if c.flying_pixels > 0.0:  # no draw otherwise: the frames of before, bit for bit
            _flying_pixels(noisy, depth, c.flying_pixels, c.far, rng)
        noisy[_no_return(depth, c.far) | (noisy <= 0.0)] = 0.0
        return RgbdFrame(t, rgb, noisy)
