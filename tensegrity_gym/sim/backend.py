"""The simulation backend: a simulated robot (PyBullet or MuJoCo, :mod:`tensegrity_gym.sim.engines`)
and its sensor suite behind :class:`Backend`."""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Mapping
from dataclasses import replace
from functools import lru_cache
from typing import TYPE_CHECKING, Any

import numpy as np

from tensegrity_gym.model.checks import check_number, check_open
from tensegrity_gym.model.kinematics import center_of_mass
from tensegrity_gym.model.lie import quat_multiply, quat_rotate
from tensegrity_gym.model.protocols import SensorCalibration, StepResult, UwbCalibration
from tensegrity_gym.model.samples import GROUND_TRUTH, GroundTruth
from tensegrity_gym.sim.engines import DEFAULT_ENGINE, engine_spec
from tensegrity_gym.sim.sensors import (
    CableLengthModel,
    CameraModel,
    ContactModel,
    EncoderModel,
    ImuModel,
    SensorSchedule,
    UwbModel,
)
from tensegrity_gym.sim.terrain import FixedTerrain, terrain_builder
from tensegrity_gym.sim.world import check_heightfield

if TYPE_CHECKING:
    import os
    from collections.abc import Callable

    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.protocols import ReadyCheck
    from tensegrity_gym.model.randomization import Randomization, WorldDraw
    from tensegrity_gym.model.samples import Sample
    from tensegrity_gym.sim.engines import World
    from tensegrity_gym.sim.terrain import Terrain
    from tensegrity_gym.sim.world import Snapshot

    _Segment = tuple[NDArray[np.float64], NDArray[np.float64], tuple[int, int, int]]

__all__ = ["SettleError", "SimBackend", "check_sensor_rates", "settled_pose"]

_SIMULATED_KINDS = frozenset(
    ["imu", "ahrs", "encoders", "cable_lengths", "uwb", "rgbd", "contacts", GROUND_TRUTH]
)
# The sample kinds each scheduled sensor model gives: one not carried is not scheduled.
_SENSOR_KINDS = {
    "imu": frozenset({"imu", "ahrs"}),
    "encoder": frozenset({"encoders"}),
    "cable_length": frozenset({"cable_lengths"}),
    "contact": frozenset({"contacts"}),
    "uwb": frozenset({"uwb"}),
}

log = logging.getLogger(__name__)

# A state whose nodes move faster than this, or leave this box, has blown up.
_MAX_SPEED = 50.0  # m/s
_MAX_EXTENT = 1.0e3  # m

# Settling goes on past ``settle_time`` until no node moves faster than this over a
# whole window (the robot rocks on its endcaps in a lightly damped mode that a fixed
# settle time can leave at full swing), for at most _MAX_EXTRA_SETTLE seconds more.
_REST_NODE_SPEED = 1.0e-6  # m/s
_REST_WINDOW = 1.0  # s
_REST_SAMPLE = 0.01  # s
_MAX_EXTRA_SETTLE = 60.0  # s

# On uneven ground the settled pose is lifted until no rod sinks in (checked at this
# many points along each rod), then rests this long before the episode's clock starts.
_ROD_POINTS = 9
_TERRAIN_SETTLE = 0.5  # s
READY_WAIT = 5.0
"""s: how long a reset rests, sampling, for what the estimator still lacks (a UWB round
whose packets were lost, say), before it hands over what it has."""


@lru_cache(maxsize=8)
def settled_pose(
    description: RobotDescription,
    time_step: float,
    settle_time: float,
    engine: str = DEFAULT_ENGINE,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Rod positions (r, 3) and quaternions (r, 4) of the robot at rest on the ground,
    reached by letting the nominal shape settle for at least ``settle_time`` seconds and
    then until its nodes are still; centred so the CoM is above the origin.

    Deterministic, so it is computed once per description and ``engine`` and shared.
    """
    world = engine_spec(engine).world(description, time_step)
    try:
        world.set_node_positions(description.initial_positions)
        targets = [description.rest_lengths[k] for k in description.actuated]
        n = round(settle_time / time_step)
        world.advance(n, targets, [False] * n)
        every = max(1, round(_REST_SAMPLE / time_step))
        window = every * max(1, round(_REST_WINDOW / (every * time_step)))
        flags = [(i + 1) % every == 0 for i in range(window)]
        prev = np.array(world.snapshot().node_positions)
        for _ in range(int(np.ceil(_MAX_EXTRA_SETTLE / (window * time_step)))):
            x = np.array([s.node_positions for s in world.advance(window, targets, flags)])
            steps = np.diff(np.concatenate([prev[None], x]), axis=0)
            prev = x[-1]
            if np.linalg.norm(steps, axis=-1).max() < _REST_NODE_SPEED * every * time_step:
                break
            if not np.all(np.isfinite(prev)):
                break  # blown up: no amount of settling brings it back
        pos, orn, _, _ = world.rod_states()
    finally:
        world.close()
    positions = np.array(pos)
    _check_settled(description, time_step, positions, np.array(orn))
    masses = np.array([r.mass for r in description.rods])
    com = (positions * masses[:, None]).sum(axis=0) / masses.sum()
    positions[:, :2] -= com[:2]
    return positions, np.array(orn)


class SettleError(ValueError):
    """The robot's simulation blew up while it settled before the first episode."""


def _check_settled(
    description: RobotDescription,
    time_step: float,
    positions: NDArray[np.float64],
    quaternions: NDArray[np.float64],
) -> None:
    """Raise :class:`SettleError` naming the likely cause if the settled rods, centres
    (r, 3) and quaternions (r, 4), are not finite or not resting near the ground."""
    span = sum(r.length for r in description.rods)
    finite = np.all(np.isfinite(positions)) and np.all(np.isfinite(quaternions))
    centre = positions.mean(axis=0) if finite else np.zeros(3)
    spread = np.linalg.norm(positions - centre, axis=-1).max() if finite else 0.0
    if finite and -span < centre[2] < span and spread < span:
        return
    where = f"{description.source or description.name}: " if description.source else ""
    raise SettleError(
        f"{where}the simulation diverged while the robot settled (time_step={time_step} s): "
        f"{_stiffness_hint(description, time_step)}"
    )


def _stiffness_hint(description: RobotDescription, time_step: float) -> str:
    """Which parameter most likely made the integration unstable: the cable whose
    spring-mass period is the shortest for the time step, or a general pointer."""
    masses = np.array([r.mass for r in description.rods])
    worst, worst_ratio = -1, 0.0
    for k, cable in enumerate(description.cables):
        m1, m2 = masses[description.node_rod[list(cable.nodes)]]
        reduced = m1 * m2 / (m1 + m2)
        # An explicit spring step is stable only for omega * dt < 2 (damping c/m * dt < 2);
        # PyBullet's contacts and rigid rods fail well before that, so the hint names a
        # cable from omega * dt > 0.5 on (seen: 0.79 settles, 1.58 blows up).
        ratio = max(np.sqrt(cable.stiffness / reduced), cable.damping / reduced) * time_step
        if ratio > worst_ratio:
            worst, worst_ratio = k, ratio
    if worst_ratio > 0.5:
        cable = description.cables[worst]
        rods = [description.rods[i] for i in description.node_rod[list(cable.nodes)]]
        return (
            f"cables[{worst}] ({cable.name!r}, stiffness {cable.stiffness:g} N/m, damping "
            f"{cable.damping:g} N s/m) between rods {rods[0].name!r} and {rods[1].name!r} "
            f"({rods[0].mass:g} and {rods[1].mass:g} kg) is too stiff for their masses at "
            f"this time step (omega * time_step = {worst_ratio:.3g}, stable below about 0.5); "
            "lower time_step, or check that cable's stiffness and damping and the rods' masses"
        )
    return "lower time_step, or check the cables' stiffness and damping and the rods' masses"


def _sensor_rates(description: RobotDescription) -> dict[str, float]:
    """Each sensor's rate (Hz), by its field in the description's ``sensors``."""
    s = description.sensors
    return {
        "imu": s.imu.rate,
        "encoder": s.encoder.rate,
        "cable_length": s.cable_length.rate,
        "uwb": s.uwb.rate,
        "contact": s.contact.rate,
        "camera": s.camera.rate,
    }


def _child(rng: np.random.Generator) -> np.random.Generator:
    """An independent generator spawned from ``rng`` without drawing from it; one
    seeded from a draw where ``rng`` has no seed sequence to spawn from."""
    try:
        return rng.spawn(1)[0]
    except (TypeError, ValueError, AttributeError):
        return np.random.default_rng(rng.integers(2**63))


def check_sensor_rates(description: RobotDescription, time_step: float) -> None:
    """Refuse a sensor faster than the physics: its samples would share stamps (and a
    bag or the link would drop them as duplicates)."""
    physics_rate = 1.0 / time_step
    for name, rate in _sensor_rates(description).items():
        if rate > physics_rate * (1.0 + 1e-9):
            where = description.source or description.name
            raise ValueError(
                f"{where}: sensors.{name}.rate={rate:g} Hz is above the physics rate "
                f"{physics_rate:g} Hz (time_step={time_step} s): its samples would repeat "
                "stamps; lower the rate or the time_step"
            )


_GRID_RGB = (110, 110, 100)


def _grid_segments(
    cx: float, cy: float, length: float, terrain: Terrain | None
) -> tuple[list[_Segment], int]:
    """Ground grid lines 0.5 L apart over 16 L around (cx, cy) (m), L = ``length`` (m),
    and the points to draw each with: at z = 0 on flat ground (``terrain`` None), else
    draped over the terrain in pieces 0.5 L long, 0.02 L above it so that the surface
    does not hide them."""
    step = 0.5 * length
    span = 8.0 * length
    gx = np.round(cx / step) * step
    gy = np.round(cy / step) * step
    offsets = np.arange(-span, span + 1e-9, step)
    segments: list[_Segment] = []
    for off in offsets:
        for a, b in (
            ([gx + off, gy - span, 0.0], [gx + off, gy + span, 0.0]),
            ([gx - span, gy + off, 0.0], [gx + span, gy + off, 0.0]),
        ):
            start, end = np.array(a), np.array(b)
            if terrain is None:
                segments.append((start, end, _GRID_RGB))
                continue
            pts = start + (offsets[:, None] + span) / (2.0 * span) * (end - start)
            pts[:, 2] = terrain.height_at(pts[:, 0], pts[:, 1]) + 0.02 * length
            segments += [(p, q, _GRID_RGB) for p, q in itertools.pairwise(pts)]
    return segments, 400 if terrain is None else 40


_SPAWN_KEYS = ("x", "y", "yaw")


def _check_spawn(spawn: object) -> dict[str, float]:
    """``reset(options={"spawn": ...})`` as {key: value}: keys among ``x``, ``y`` (m)
    and ``yaw`` (rad), finite numbers; ValueError naming what is wrong."""
    if spawn is None:
        return {}
    if not isinstance(spawn, Mapping):
        raise ValueError(
            f"reset: spawn={spawn!r} must be a dict with keys among {list(_SPAWN_KEYS)} (m, m, rad)"
        )
    unknown = sorted(str(k) for k in spawn if k not in _SPAWN_KEYS)
    if unknown:
        raise ValueError(f"reset: spawn has unknown keys {unknown}; valid: {list(_SPAWN_KEYS)}")
    return {k: check_number(f"spawn[{k!r}]", v, where="reset") for k, v in spawn.items()}


def _yaw_quaternion(yaw: float) -> NDArray[np.float64]:
    return np.array([0.0, 0.0, np.sin(0.5 * yaw), np.cos(0.5 * yaw)])


class SimBackend:
    """A simulated tensegrity robot producing raw sensor samples.

    Args:
        description: the robot.
        control_period: seconds per :meth:`step` (10 Hz control by default).
        time_step: physics step (s); 1 kHz by default.
        camera: render RGB-D frames for an estimator (costly; off unless asked).
        gui: show PyBullet's window (``render_mode="human"``).
        spawn_radius: the initial CoM is placed uniformly within this radius (m) of the
            origin, at a uniformly random heading.
        settle_time: seconds the nominal shape settles for at least before the first
            episode; settling goes on until the robot is still (see :func:`settled_pose`).
        terrain: the ground (:mod:`tensegrity_gym.sim.terrain`): ``"flat"``, ``"valley"``,
            ``"rough"``, a lab's registered name, a ``.npy``/``.png`` height map or a
            :class:`~tensegrity_gym.sim.terrain.Terrain`; built at each reset from the
            reset's rng. Only the simulation sees it: no estimator is told the map.
        world_seed: draws the lab once, for the life of the backend (a real lab's are
            constants): where the UWB anchors stand, every pair's offset o_ij and the
            modules' clock drift (:meth:`UwbModel.draw_world`). Episodes come from
            :meth:`reset`'s rng.
        uwb_calibration: the anchors and offsets :attr:`calibration` hands the
            estimators (a lab's calibration, e.g. from ``estimation.uwb_calibration``),
            or a callable making them, called at the first :meth:`reset` (a calibration
            run); None: the simulator's own (:attr:`true_calibration`, for ablations).
        randomization: the ranges each :meth:`reset` draws this episode's robot and
            world from (:mod:`tensegrity_gym.model.randomization`); the draws are in the
            reset's ``info["randomization"]``. :attr:`description` stays the nominal one
            (what the estimators get). None: the description, exactly.
        engine: the physics engine's name (:data:`~tensegrity_gym.sim.engines.ENGINES`):
            ``"pybullet"`` or ``"mujoco"``; the sensor models are the same on each.
    """

    def __init__(
        self,
        description: RobotDescription,
        *,
        control_period: float = 0.1,
        time_step: float = 0.001,
        camera: bool = False,
        gui: bool = False,
        spawn_radius: float = 0.0,
        settle_time: float = 5.0,
        terrain: str | os.PathLike[str] | Terrain = "flat",
        world_seed: int = 0,
        uwb_calibration: UwbCalibration | Callable[[], UwbCalibration] | None = None,
        randomization: Randomization | None = None,
        engine: str = DEFAULT_ENGINE,
    ) -> None:
        steps = control_period / time_step
        if steps < 1 or abs(steps - round(steps)) > 1e-9:
            raise ValueError(
                f"control_period={control_period} must be a whole multiple of time_step={time_step}"
            )
        check_sensor_rates(description, time_step)
        self.description = description
        self.control_period = control_period
        self.clock_origin_ns = 0
        """Robot-clock ns of sample time 0: the simulation's clock starts at 0."""
        self.time_step = time_step
        self.camera = camera
        self.gui = gui
        self.spawn_radius = spawn_radius
        self.settle_time = settle_time
        self.terrain_source = terrain
        self._build_terrain = terrain_builder(terrain)
        if isinstance(self._build_terrain, FixedTerrain):
            try:  # at make, not at the first reset
                check_heightfield(self._build_terrain.terrain)
            except ValueError as err:
                raise ValueError(f"make: {err}") from None
        self.terrain: Terrain | None = None
        """This episode's ground, from :meth:`reset` on (for tests and tools)."""
        self._n_steps = round(steps)
        self._engine = engine_spec(engine)
        self._world: World | None = None
        s = description.sensors
        self.imu = ImuModel(s.imu, description)
        self.encoder = EncoderModel(s.encoder, description)
        self.cable_length = CableLengthModel(s.cable_length, description)
        self.contact = ContactModel(s.contact, description)
        self.uwb = UwbModel(s.uwb, description)
        self.world_seed = world_seed
        self.uwb.draw_world(np.random.default_rng(world_seed))
        self.uwb_calibration = uwb_calibration
        self.camera_model = CameraModel(s.camera)
        if randomization is not None and randomization.command_latency[1] >= control_period:
            raise ValueError(
                f"randomization.command_latency={randomization.command_latency} must stay "
                f"below the control period ({control_period} s)"
            )
        self.randomization = randomization
        self.world_draw: WorldDraw | None = None
        """This episode's draw of the randomisation (None without one)."""
        self._offsets = np.zeros(len(description.actuated))  # the encoders' zero errors (m)
        self._latency_steps = 0
        self._previous_targets: list[float] | None = None
        rates = _sensor_rates(description)
        carried = description.sample_kinds
        # Only the sensors the robot carries are sampled; of the IMU's two kinds, one
        # not carried is dropped from what it gives.
        self._schedules = {
            name: SensorSchedule(rates[name])
            for name, kinds in _SENSOR_KINDS.items()
            if kinds & carried
        }
        self._carries_camera = "rgbd" in carried
        self._imu_kinds = _SENSOR_KINDS["imu"] & carried
        self._rng: np.random.Generator | None = None
        self._calibration: SensorCalibration | None = None
        self._diverged = False
        self._truth: GroundTruth | None = None
        self._closed = False

    # Pickling ships the configuration, not the engine's world: a new one is made on
    # the other side (each process owns its client).
    def __getstate__(self) -> dict[str, Any]:
        return {
            "description": self.description,
            "control_period": self.control_period,
            "time_step": self.time_step,
            "camera": self.camera,
            "gui": False,
            "spawn_radius": self.spawn_radius,
            "settle_time": self.settle_time,
            "terrain": self.terrain_source,
            "world_seed": self.world_seed,
            "uwb_calibration": self.uwb_calibration,
            "randomization": self.randomization,
            "engine": self.engine,
        }

    def __setstate__(self, state: dict[str, Any]) -> None:
        description = state.pop("description")
        self.__init__(description, **state)  # type: ignore[misc]

    @property
    def world(self) -> World:
        """The engine's world, built on first use; RuntimeError once :meth:`close` ran."""
        if self._world is None:
            check_open(self._closed, "the simulation")
            self._world = self._engine.world(self.description, self.time_step, gui=self.gui)
        return self._world

    @property
    def engine(self) -> str:
        """The physics engine's name."""
        return self._engine.name

    def render_problem(self) -> str | None:
        """None where this engine renders the RGB-D camera on this machine, else why not."""
        problem = self._engine.render_problem()
        if problem is None:
            return None
        return f"engine {self.engine!r} cannot render on this machine ({problem})"

    @property
    def true_uwb(self) -> UwbCalibration:
        """The world's anchors and offsets as drawn (fixed from construction on)."""
        return UwbCalibration(self.uwb.anchors.copy(), self.uwb.offsets.copy(), source="true")

    @property
    def true_calibration(self) -> SensorCalibration:
        """What the simulator drew: the anchors where they stand, the offsets it adds."""
        if self._calibration is None:
            raise RuntimeError("call reset() before reading the calibration")
        return self._calibration

    @property
    def calibration(self) -> SensorCalibration:
        """What the estimators get: :attr:`uwb_calibration` where set (a lab's, made
        from recorded ranges), else the simulator's own."""
        truth = self.true_calibration
        lab = self.uwb_calibration
        if lab is None:
            return truth
        if callable(lab):  # not made yet: reset makes it
            raise RuntimeError("call reset() before reading the calibration")
        return lab.applied_to(truth)

    def _camera_pose(self) -> NDArray[np.float64]:
        """Camera-to-world transform (4, 4): +z along the view, +x right, +y down."""
        c = self.description.sensors.camera
        eye, target, up = (np.asarray(v, dtype=np.float64) for v in (c.position, c.target, c.up))
        z = target - eye
        z /= np.linalg.norm(z)
        x = np.cross(z, up)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        pose = np.eye(4)
        pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = x, y, z, eye
        return pose

    # ------------------------------------------------------------------ episodes

    reset_options = frozenset({"spawn"})
    """The keys of ``env.reset(options=...)`` that :meth:`reset` takes."""

    def reset(
        self,
        rng: np.random.Generator,
        *,
        ready: ReadyCheck | None = None,
        spawn: Mapping[str, float] | None = None,
    ) -> StepResult:
        """Place the settled robot at a random heading and position; return the first
        samples (one of each sensor, the AHRS having converged while it rested).

        ``spawn`` fixes the CoM's ground position ``x``, ``y`` (m, world frame) and the
        robot's ``yaw`` (rad), any of them; the others are drawn as without it.
        Where ``ready`` says the estimator lacks something, the robot rests on, its motors
        holding, and the periods' samples are added, as a robot's driver waits (at most
        :data:`READY_WAIT` s; then the estimator gets what there is)."""
        check_open(self._closed, "reset")
        pose = _check_spawn(spawn)
        self._rng = rng
        d = self._as_built(self._draw_world(rng))  # the description unless randomised
        positions, quats = settled_pose(d, self.time_step, self.settle_time, self.engine)
        world = self.world
        # Flat ground draws nothing from the rng: episodes stay as they were without it.
        terrain = self.terrain = self._build_terrain(d, rng)
        world.terrain = terrain
        # A fresh simulation each episode: PyBullet keeps contact caches otherwise, and
        # the same seed must give the same episode bit for bit.
        world._build()
        world.time_ns = 0
        self._truth = None
        world.set_rest_lengths(d.rest_lengths)
        self._previous_targets = list(world.targets)  # held until the first command acts
        shift, yaw = self._spawn_pose(rng, pose)
        qz = _yaw_quaternion(yaw)
        c, s = np.cos(yaw), np.sin(yaw)
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        placed, quats = positions @ rot.T + shift, quat_multiply(qz, quats)
        if world.flat_ground:
            world.set_rod_states(placed, quats)
        else:
            self._rest_on(terrain, placed, quats)
        self._diverged = False

        self.uwb.reset(rng)
        if callable(self.uwb_calibration):  # the lab calibrates once, before its first run
            self.uwb_calibration = self.uwb_calibration()
        self._calibration = SensorCalibration(
            uwb_offsets=self.uwb.offsets.copy(),
            anchors=self.uwb.anchors.copy(),
            camera_intrinsics=d.sensors.camera.intrinsics,
            camera_pose=self._camera_pose(),
        )
        snap = world.snapshot()
        self.imu.reset(snap, rng)
        for sched in self._schedules.values():
            sched.reset(0.0)
        for sched in self._schedules.values():
            sched.due(0.0)  # the t = 0 samples are taken below
        samples = self._sample({name: [snap] for name in self._schedules}, rng)
        if ready is not None:
            samples = self._until_ready(samples, ready)
        return StepResult(samples, info=self._episode_info())

    def _until_ready(self, samples: list[Sample], ready: ReadyCheck) -> list[Sample]:
        """``samples`` and those of further periods at rest while ``ready`` names
        something missing, for at most :data:`READY_WAIT` s.

        The wait's sensors draw from a child of the episode's generator (spawning one
        leaves the parent's stream as it was), so that what the episode draws after
        reset (its goal, its sensors' noise) is the same whether this estimator waited
        or another did not."""
        d = self.description
        hold = d.rest_lengths[d.actuated]
        episode_rng = self._rng
        assert episode_rng is not None
        try:
            for period in range(math.ceil(READY_WAIT / self.control_period)):
                missing = ready(samples)
                if missing is None:
                    return samples
                if period == 0:
                    log.info("reset: resting while the estimator lacks %s", missing)
                    self._rng = _child(episode_rng)
                result = self.step(hold)
                if result.diverged:
                    raise SettleError(
                        "the simulation diverged while the robot rested at reset"
                        f"{self._ground_hint()}, waiting for what the estimator lacks "
                        f"({missing})"
                    )
                samples = [*samples, *result.samples]
        finally:
            self._rng = episode_rng
        return samples

    def _ground_hint(self) -> str:
        """`` on terrain NAME (...)`` where the robot rests on a map, else nothing: an
        uneven ground is the first suspect when a robot at rest blows up."""
        terrain = self.terrain
        if terrain is None or terrain.is_flat:
            return ""
        relief = float(np.ptp(terrain.heights))
        return (
            f" on terrain {terrain.name or self.terrain_source!r} (heights span {relief:.3g} m, "
            f"steepest slope {terrain.steepest_slope:.3g} m/m: check its height_scale)"
        )

    def _episode_info(self) -> dict[str, object]:
        """What ``info`` says of this episode alone at reset: a randomised world's draws."""
        if self.world_draw is None:
            return {}
        return {"randomization": self.world_draw.summary(self.description)}

    def _spawn_pose(
        self, rng: np.random.Generator, pose: dict[str, float]
    ) -> tuple[NDArray[np.float64], float]:
        """The CoM's shift from the origin (m, (3,)) and the yaw (rad) of this episode:
        drawn from ``rng`` (always, so that the rest of the episode draws the same), then
        set to ``pose``'s ``x``, ``y`` and ``yaw`` where it has them."""
        yaw = float(rng.uniform(-np.pi, np.pi))
        radius = self.spawn_radius * np.sqrt(rng.uniform())
        heading = rng.uniform(-np.pi, np.pi)
        shift = np.array([radius * np.cos(heading), radius * np.sin(heading), 0.0])
        shift[0], shift[1] = pose.get("x", shift[0]), pose.get("y", shift[1])
        return shift, pose.get("yaw", yaw)

    def _draw_world(self, rng: np.random.Generator) -> RobotDescription:
        """This episode's robot: the description, or one drawn from the randomisation,
        with the world and the sensor models set to it. Draws nothing without one."""
        nominal = self.description
        if self.randomization is None:
            return nominal
        draw = self.world_draw = self.randomization.draw(nominal, rng)
        robot, s = draw.robot, draw.robot.sensors
        self.world.reconfigure(robot, draw.gravity)
        self.imu.config, self.imu.gravity = s.imu, draw.gravity.copy()
        self.uwb.config = s.uwb
        self.camera_model.config = s.camera
        self._offsets = draw.encoder_offsets[nominal.actuated]
        self.encoder.offsets = self._offsets
        self._latency_steps = min(round(draw.command_latency / self.time_step), self._n_steps)
        return robot

    def _as_built(self, robot: RobotDescription) -> RobotDescription:
        """``robot`` with its actuated cables as long as the motors hold them at reset:
        the encoders read the description's rest lengths, the cables are longer by the
        encoders' zero errors, within the motors' own range (which a randomised world
        may shift). The robot settles so: a pose settled with other lengths would snap
        into shape at the first step."""
        lo, hi, _ = robot.motor_limits
        actuated = robot.rest_lengths[robot.actuated]
        rest = np.clip(actuated + self._offsets, lo, hi)
        if np.array_equal(rest, actuated):
            return robot
        held = dict(zip(robot.actuated.tolist(), rest.tolist(), strict=True))
        cables = tuple(
            replace(c, rest_length=held[k]) if k in held else c for k, c in enumerate(robot.cables)
        )
        return replace(robot, cables=cables)

    def _rest_on(
        self, terrain: Terrain, positions: NDArray[np.float64], quaternions: NDArray[np.float64]
    ) -> None:
        """Put the rods, centres (r, 3) and quaternions (r, 4) of a pose settled on the
        plane z = 0, onto ``terrain``: lifted until no rod sinks in, then resting for
        :data:`_TERRAIN_SETTLE` seconds; the clock then starts at 0."""
        world = self.world
        rods = self.description.rods
        half = np.array([[0.0, 0.0, 0.5 * rod.length] for rod in rods])
        arm = quat_rotate(quaternions, half)  # centre to second endcap (r, 3)
        along = np.linspace(-1.0, 1.0, _ROD_POINTS)
        points = positions[:, None, :] + along[None, :, None] * arm[:, None, :]
        radius = np.repeat([rod.endcap_radius for rod in rods], _ROD_POINTS)
        lift = max(terrain.lift(points.reshape(-1, 3), radius), 0.0)
        world.set_rod_states(positions + np.array([0.0, 0.0, lift]), quaternions)
        n = round(_TERRAIN_SETTLE / self.time_step)
        world.advance(n, world.targets, [False] * n)
        world.time_ns = 0

    def sample_kinds(self) -> frozenset[str]:
        """The kinds its sensor models produce for the sensors the robot carries
        (``description.sample_kinds``; RGB-D frames only while :attr:`camera` renders
        them, which ``make`` turns on for an estimator that needs them), and the truth;
        not a kind registered later by a lab for its own robot."""
        kinds = _SIMULATED_KINDS & (self.description.sample_kinds | {GROUND_TRUTH})
        return kinds if self._renders else kinds - {"rgbd"}

    @property
    def _renders(self) -> bool:
        """Whether a period's samples end with an RGB-D frame."""
        return self.camera and self._carries_camera

    def step(self, targets: NDArray[np.float64]) -> StepResult:
        check_open(self._closed, "step")
        if self._rng is None:
            raise RuntimeError("call reset() before step()")
        if self._diverged:
            raise RuntimeError("the simulation diverged; call reset()")
        world = self.world
        t0 = world.time
        t1 = t0 + self._n_steps * self.time_step
        wanted: dict[int, list[str]] = {}
        for name, sched in self._schedules.items():
            for t in sched.due(t1):
                k = min(max(round((t - t0) / self.time_step) - 1, 0), self._n_steps - 1)
                wanted.setdefault(k, []).append(name)
        flags = [False] * self._n_steps
        for k in wanted:
            flags[k] = True
        snaps = self._advance(targets, flags)
        by_sensor: dict[str, list[Snapshot]] = {name: [] for name in self._schedules}
        for k, snap in zip(sorted(wanted), snaps, strict=True):
            for name in wanted[k]:
                by_sensor[name].append(snap)
        last = snaps[-1] if flags[-1] else world.snapshot()
        if not self._finite(last):
            self._diverged = True
            return StepResult((), diverged=True)
        return StepResult(self._sample(by_sensor, self._rng, last))

    def _advance(self, targets: NDArray[np.float64], flags: list[bool]) -> list[Snapshot]:
        """One period toward ``targets`` (the encoders' readings to reach, m): in a
        randomised world the motors act on it only after the command latency (the last
        command until then), and drive cables the encoders' zero errors leave longer."""
        world = self.world
        physical = (np.asarray(targets, dtype=np.float64) + self._offsets).tolist()
        late = self._latency_steps if self._previous_targets is not None else 0
        self._previous_targets, previous = physical, self._previous_targets
        if late == 0 or previous is None:
            return world.advance(self._n_steps, physical, flags)
        first = world.advance(late, previous, flags[:late])
        return first + world.advance(self._n_steps - late, physical, flags[late:])

    def _sample(
        self,
        snaps: dict[str, list[Snapshot]],
        rng: np.random.Generator,
        last: Snapshot | None = None,
    ) -> list[Sample]:
        samples: list[Sample] = []
        if "imu" in snaps:
            imu, ahrs = self.imu.sample(snaps["imu"], rng)
            samples += [*imu] if "imu" in self._imu_kinds else []
            samples += [*ahrs] if "ahrs" in self._imu_kinds else []
        if "encoder" in snaps:
            samples += self.encoder.sample(snaps["encoder"])
        if "cable_length" in snaps:
            samples += self.cable_length.sample(snaps["cable_length"], rng)
        if "contact" in snaps:
            samples += self.contact.sample(self._above_ground(snaps["contact"]))
        if "uwb" in snaps:
            samples += self.uwb.sample(snaps["uwb"], rng)
        if self._renders:
            t = last.t if last is not None else self.world.time
            rgb, depth = self.world.camera_image(self.description.sensors.camera)
            samples.append(self.camera_model.frame(t, rgb, depth, rng))
        samples.sort(key=lambda s: s.t)  # stable: same-time samples keep sensor order
        return samples

    def _above_ground(self, snaps: list[Snapshot]) -> list[Snapshot]:
        """The snapshots with each node's z replaced by its height above the terrain
        along the ground's normal, for the contact model (which measures from z = 0):
        a contact sensor feels the ground it touches. Unchanged on flat ground."""
        terrain = self.terrain
        if terrain is None or terrain.is_flat:
            return snaps
        out = []
        for snap in snaps:
            nodes = np.array(snap.node_positions)
            nodes[:, 2] = terrain.clearance(nodes, 0.0)
            out.append(replace(snap, node_positions=nodes.tolist()))
        return out

    def _finite(self, snap: Snapshot) -> bool:
        pos = np.asarray(snap.rod_positions)
        vel = np.asarray(snap.rod_linear_velocities)
        ang = np.asarray(snap.rod_angular_velocities)
        half = max(r.length for r in self.description.rods) / 2.0
        ok = (
            np.all(np.isfinite(pos))
            and np.all(np.isfinite(vel))
            and np.all(np.isfinite(ang))
            and np.all(np.isfinite(snap.rod_quaternions))
            and np.abs(pos).max() < _MAX_EXTENT
            and np.linalg.norm(vel, axis=1).max() + half * np.linalg.norm(ang, axis=1).max()
            < _MAX_SPEED
        )
        return bool(ok)

    # ------------------------------------------------------------------ truth & views

    def ground_truth(self) -> GroundTruth | None:
        if self._diverged:
            return None
        if self._truth is None or self._truth.t != self.world.time:
            self._truth = self._read_truth()
        return self._truth

    def _read_truth(self) -> GroundTruth:
        world = self.world
        x, v = world.node_states()
        pos, orn, _, _ = world.rod_states()
        return GroundTruth(
            t=world.time,
            node_positions=x,
            node_velocities=v,
            rod_positions=np.array(pos),
            rod_quaternions=np.array(orn),
            com=center_of_mass(x, self.description.node_masses),
            rest_lengths=np.array(world.spool_lengths),  # in effect: as the encoders read
        )

    def render(self, width: int, height: int) -> NDArray[np.uint8]:
        """A chase view of the robot for people, cables and a 0.5 L ground grid drawn in,
        (height, width, 3)."""
        truth = self.ground_truth()
        centre = truth.com if truth is not None else np.zeros(3)
        length = self.description.characteristic_length
        cx, cy, cz = (float(v) for v in centre)
        terrain = self.terrain if self.terrain is not None and not self.terrain.is_flat else None
        below = 0.0 if terrain is None else float(terrain.height_at(cx, cy))
        cam = replace(
            self.description.sensors.camera,
            position=(cx + 0.8 * length, cy - 1.7 * length, cz + 1.1 * length),
            target=(cx, cy, 0.5 * cz if terrain is None else below + 0.5 * (cz - below)),
            near=0.05 * length,
            far=40.0 * length,
        )
        segments = []
        if truth is not None:
            x = truth.node_positions
            for k, (i, j) in enumerate(self.description.cable_nodes):
                colour = (250, 250, 250) if self.description.cables[k].actuated else (40, 40, 40)
                segments.append((x[i], x[j], colour))
        points = [400] * len(segments)
        grid, grid_points = _grid_segments(cx, cy, length, terrain)
        points += [grid_points] * len(grid)
        rgb, _ = self.world.camera_image(cam, width, height, segments + grid, points)
        return rgb

    def stop(self) -> None:
        """Nothing to hold: the simulated motors follow the last targets."""

    def close(self) -> None:
        """Drop the engine's world; later resets and steps raise (closing again is harmless)."""
        self._closed = True
        if self._world is not None:
            self._world.close()
            self._world = None
