"""System identification from a recorded run (issue 16): ``tensegrity-gym identify``.

The bag's commands are replayed in a model of the robot from the recorded state, over
many short segments, each restarted from the recorded state (multiple shooting: rolling
is chaotic, and one long open-loop replay would diverge whatever the parameters), and
the chosen physical parameters of the description are fitted so that the simulated
motion matches the recorded one (motion capture where the bag has it, else the UKF's
estimates). Where the bag has IMU readings, the simulator is fitted to those, over one
control period from each of many recorded states (:mod:`agents.identification.imu`): node
positions at the control rate hardly show the cables' damping. The optimiser is CMA-ES
(the ``cma`` package) over log-scales of the description's values; each generation's
candidates are evaluated on the machine's cores, a worker per core, each holding its
own model.

Two models can be fitted: the simulator's (``"sim"``, PyBullet, the default), and the
UKF's spring-mass net (``"ukf"``, its own simpler physics, driven by the encoders as
the filter is). Either way the result is a robot description: the simulator, the UKF
and ``gym.make(robot=...)`` load it.
"""

from __future__ import annotations

import itertools
import logging
import math
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, NamedTuple, Protocol

import numpy as np

from agents.identification.imu import (
    ImuReadings,
    imu_readings,
    imu_term,
    readings_of_replay,
    spin_track,
    window_scores,
)
from tensegrity_gym.model.kinematics import (
    center_of_mass,
    rod_axes,
    rod_centres,
    rod_quaternion_from_axis,
)
from tensegrity_gym.model.samples import EncoderSample

if TYPE_CHECKING:
    from collections.abc import Callable, Sequence

    from numpy.typing import NDArray

    from hardware.recording import RecordedRun
    from tensegrity_gym.model.description import Cable, RobotDescription
    from tensegrity_gym.sim.world import PhysicsWorld

__all__ = [
    "GROUPS",
    "MAX_EVALUATIONS",
    "MODELS",
    "PARAMETERS",
    "PER_PART",
    "Frame",
    "Identification",
    "IdentifyError",
    "Segment",
    "apply_parameters",
    "identify_run",
    "imu_windows",
    "recorded_trajectory",
    "replay_imu",
    "segment_errors",
    "segments_of",
]

logger = logging.getLogger(__name__)


class IdentifyError(ValueError):
    """The recording cannot identify anything; the message (one line) says why."""


# ---------------------------------------------------------------- the parameters


def _scaled_cables(
    d: RobotDescription, field: str, factor: float, which: bool | None, index: int | None = None
) -> RobotDescription:
    """``d``'s cables with ``field`` times ``factor``, for the actuated ones (True), the
    passive ones (False) or all (None); only cable ``index`` where one is given."""
    cables = tuple(
        replace(c, **{field: getattr(c, field) * factor})
        if (which is None or c.actuated == which) and index in (None, k)
        else c
        for k, c in enumerate(d.cables)
    )
    return replace(d, cables=cables)


def _motor_speed(d: RobotDescription, factor: float) -> RobotDescription:
    def scaled(c: Cable) -> Cable:
        if c.motor is None:
            return c
        return replace(c, motor=replace(c.motor, max_speed=c.motor.max_speed * factor))

    return replace(d, cables=tuple(scaled(c) for c in d.cables))


def _friction(d: RobotDescription, factor: float) -> RobotDescription:
    g = d.ground
    return replace(d, ground=replace(
        g, lateral_friction=g.lateral_friction * factor,
        rolling_friction=g.rolling_friction * factor,
        spinning_friction=g.spinning_friction * factor,
    ))  # fmt: skip


def _mass(d: RobotDescription, factor: float) -> RobotDescription:
    return replace(d, rods=tuple(replace(r, mass=r.mass * factor) for r in d.rods))


class Setter(Protocol):
    """Applies one factor to a description."""

    def __call__(self, d: RobotDescription, factor: float, /) -> RobotDescription: ...


PARAMETERS: dict[str, tuple[tuple[str, Setter], ...]] = {
    "stiffness": (
        ("actuated_stiffness", lambda d, f: _scaled_cables(d, "stiffness", f, True)),
        ("passive_stiffness", lambda d, f: _scaled_cables(d, "stiffness", f, False)),
    ),
    "damping": (("damping", lambda d, f: _scaled_cables(d, "damping", f, None)),),
    "rest": (("passive_rest_length", lambda d, f: _scaled_cables(d, "rest_length", f, False)),),
    "friction": (("friction", _friction),),
    "mass": (("mass", _mass),),
    "motor": (("motor_speed", _motor_speed),),
}  # fmt: skip
"""``--params`` groups: each names one or more factors, by which it scales the
description's values (all cables' damping, every rod's mass, ...)."""


def _rod_length(index: int) -> Setter:
    def scaled(d: RobotDescription, factor: float) -> RobotDescription:
        return d.with_rod_length(index, d.rods[index].length * factor)

    return scaled


def _rest_length(index: int) -> Setter:
    def scaled(d: RobotDescription, factor: float) -> RobotDescription:
        return _scaled_cables(d, "rest_length", factor, None, index)

    return scaled


def _geometry_parts(d: RobotDescription) -> list[tuple[str, Setter, float]]:
    """Each rod's length (endcap to endcap) and each passive cable's rest length: the
    factor's name, its setter and the description's value (m)."""
    rods = [(f"rod_length[{rod.name}]", _rod_length(i), rod.length) for i, rod in enumerate(d.rods)]
    rest = [(f"rest_length[{c.name}]", _rest_length(k), c.rest_length)
            for k, c in enumerate(d.cables) if not c.actuated]  # fmt: skip
    return rods + rest


def _geometry(d: RobotDescription) -> list[tuple[str, Setter]]:
    """The ``geometry`` group: a factor per rod length and passive rest length, what a
    tape measure gets a few millimetres wrong, and a motion fitted with the global
    factors cannot absorb."""
    return [(name, setter) for name, setter, _ in _geometry_parts(d)]


PER_PART: dict[str, Callable[[RobotDescription], list[tuple[str, Setter]]]] = {
    "geometry": _geometry,
}
"""``--params`` groups with a factor per rod or cable, named for it (``rod_length[r0]``)."""
GROUPS = (*PARAMETERS, *PER_PART)
"""Every ``--params`` group."""


def _setters(description: RobotDescription) -> dict[str, Setter]:
    """Every factor's setter by name, the per-part ones of ``description``."""
    setters = {name: setter for group in PARAMETERS.values() for name, setter in group}
    for parts in PER_PART.values():
        setters.update(parts(description))
    return setters


_BOUND = {"passive_rest_length": np.log(1.2)}
"""Largest |log factor| searched, per factor; the others: a factor of 2 either way."""
_PART_BOUND = {"rod_length": np.log(1.15), "rest_length": np.log(1.2)}
"""The same, per part (the name before ``[``): a rod within 15 % of its length."""
AT_BOUND_SHARE = 0.95
"""A factor whose |log| ends beyond this share of its bound's has ended at its bound."""


def factor_bounds(names: Sequence[str]) -> NDArray[np.float64]:
    """(p,) the largest |log factor| the search tries for each of ``names``."""
    return np.array([_BOUND.get(n, _PART_BOUND.get(n.split("[")[0], np.log(2.0))) for n in names])


def apply_parameters(
    description: RobotDescription, names: Sequence[str], log_factors: NDArray[np.float64]
) -> RobotDescription:
    """``description`` with each named factor (``PARAMETERS``' inner names, and the
    per-part ones of ``PER_PART`` such as ``rod_length[red]``) applied as
    ``exp(log_factor)``; a name the description has no part for, IdentifyError."""
    setters = _setters(description)
    d = description
    for name, value in zip(names, log_factors, strict=True):
        if name not in setters:
            raise IdentifyError(f"identify: {description.name!r} has no factor {name!r}")
        d = setters[name](d, float(np.exp(value)))
    return d


def parameter_values(description: RobotDescription, name: str) -> float:
    """The description's value behind a factor (the first cable's, rod's...), for reports."""
    actuated = [c for c in description.cables if c.actuated]
    passive = [c for c in description.cables if not c.actuated]
    values: dict[str, Callable[[], float]] = {
        "actuated_stiffness": lambda: actuated[0].stiffness,
        "passive_stiffness": lambda: passive[0].stiffness,
        "damping": lambda: description.cables[0].damping,
        "passive_rest_length": lambda: passive[0].rest_length,
        "friction": lambda: description.ground.lateral_friction,
        "mass": lambda: description.rods[0].mass,
        "motor_speed": lambda: actuated[0].motor.max_speed if actuated[0].motor else np.nan,
    }
    parts = {part: value for part, _, value in _geometry_parts(description)}
    return float(parts[name] if name in parts else values[name]())


def factor_names(groups: Sequence[str], description: RobotDescription) -> list[str]:
    """The factors of the ``--params`` groups; an unknown group refused with the valid
    ones; a group the robot has nothing for (passive cables, motors) left out."""
    unknown = [g for g in groups if g not in GROUPS]
    if unknown:
        raise IdentifyError(
            f"identify: unknown parameter group {unknown[0]!r}; choose from {sorted(GROUPS)}"
        )
    if {"geometry", "rest"} <= set(groups):
        raise IdentifyError(
            "identify: rest scales every passive cable's rest length, geometry each one's: "
            "give one of them"
        )
    if "mass" in groups and ({"stiffness", "damping"} & set(groups)):
        raise IdentifyError(
            "identify: mass cannot be fitted with stiffness or damping: scaling the masses, "
            "stiffnesses and dampings by one factor leaves the motion unchanged (gravity "
            "and friction scale with the mass); weigh the rods, or fit mass alone"
        )
    has_passive = any(not c.actuated for c in description.cables)
    names = [
        name
        for g in groups
        for name, _ in (PARAMETERS[g] if g in PARAMETERS else PER_PART[g](description))
    ]
    return [n for n in names if has_passive or not n.startswith("passive")]


# ---------------------------------------------------------------- the segments


@dataclass(frozen=True)
class Segment:
    """A stretch of the recording to replay open loop from its recorded start."""

    start: int
    """Index of its first control period in the run."""
    t: float
    """Time of its start (s)."""
    nodes: NDArray[np.float64]
    """(n, 3) recorded node positions at the start (m)."""
    velocities: NDArray[np.float64]
    """(n, 3) recorded node velocities at the start (m/s)."""
    encoders: NDArray[np.float64]
    """(K + 1, m) actuated rest lengths the encoders read at the start and at the end of
    each period (m)."""
    commands: NDArray[np.float64]
    """(K, m) rest-length targets sent in each period (m)."""
    recorded: NDArray[np.float64]
    """(K, n, 3) recorded node positions at the end of each period (m)."""
    spin: NDArray[np.float64]
    """(r,) each rod's spin rate about its own axis at the start (rad/s), as its gyro
    read it; 0 without one (the endcaps cannot show it)."""
    imu: ImuReadings | None = None
    """The IMU's readings over the segment's first period, where it is an IMU window
    (:func:`imu_windows`)."""


class Frame(NamedTuple):
    """The trajectory fitted at one period's end."""

    nodes: NDArray[np.float64]
    """(n, 3) node positions (m)."""
    velocities: NDArray[np.float64]
    """(n, 3) node velocities (m/s)."""
    t: float
    """Time (s)."""


def recorded_trajectory(run: RecordedRun) -> tuple[list[Frame | None], str]:
    """The trajectory to fit, per period (the start, then each step): the ground truth
    (motion capture) where the bag has it, else the UKF's estimates of the run; and
    which it is (``"ground truth"``, ``"UKF estimates"``)."""
    steps = [run.start, *run.steps]
    if any(s.truth is not None for s in steps):
        frames: list[Frame | None] = [
            None if s.truth is None
            else Frame(np.asarray(s.truth.node_positions), np.asarray(s.truth.node_velocities),
                       s.truth.t)
            for s in steps
        ]  # fmt: skip
        return frames, "ground truth"
    from agents.recordings.runs import replay
    from estimation.ukf import UkfEstimator
    from estimation.ukf.initialise import InitialisationError

    try:
        estimates = replay(run, UkfEstimator())
    except (InitialisationError, ValueError) as error:
        raise IdentifyError(
            "identify: the bag has no ground truth (motion capture), and the UKF could not "
            f"estimate a trajectory from its samples ({' '.join(str(error).split())})"
        ) from error
    return [
        Frame(e.node_positions, e.node_velocities, e.t) if e.healthy and e.is_finite() else None
        for e in estimates
    ], "UKF estimates"


def segments_of(run: RecordedRun, frames: Sequence[Frame | None], seconds: float) -> list[Segment]:
    """Segments of ``seconds`` of ``run`` back to back, each over periods whose
    trajectory ``frames`` (one per period, the start first) and encoder readings are
    known."""
    K = max(1, round(seconds / run.control_period))
    encoders = _encoder_track(run)
    spins = spin_track(run)
    commands = [s.command for s in run.steps]
    out = []
    for start in range(0, len(frames) - K, K):
        window = frames[start : start + K + 1]
        track = encoders[start : start + K + 1]
        if any(f is None for f in window) or np.isnan(track).any():
            continue
        known = [f for f in window if f is not None]
        out.append(Segment(
            start=start, t=known[0].t, nodes=known[0].nodes, velocities=known[0].velocities,
            encoders=track, commands=np.array(commands[start : start + K]),
            recorded=np.array([f.nodes for f in known[1:]]), spin=spins[start],
        ))  # fmt: skip
    return out


def imu_windows(
    run: RecordedRun, frames: Sequence[Frame | None], time_step: float, most: int = 300
) -> list[Segment]:
    """One-period segments of ``run`` with the IMU's readings over each
    (:attr:`Segment.imu`), every k-th period so that there are at most ``most``: a
    fit's time does not grow with the bag; none where the bag has no IMU topic."""
    periods = segments_of(run, frames, run.control_period)
    out = []
    stride = max(1, -(-len(periods) // max(1, most)))  # ceil(periods / most)
    for seg in periods[::stride]:
        readings = imu_readings(run, seg.start, seg.t, time_step)
        if readings is not None:
            out.append(replace(seg, imu=readings))
    return out


def _encoder_track(run: RecordedRun) -> NDArray[np.float64]:
    """(periods, m): the newest encoder reading at the end of each period, NaN before
    the first."""
    m = len(run.description.actuated)
    out = np.full((len(run.steps) + 1, m), np.nan)
    last = np.full(m, np.nan)
    for k, step in enumerate([run.start, *run.steps]):
        for s in step.samples:
            if isinstance(s, EncoderSample):
                last = np.asarray(s.rest_lengths, dtype=np.float64)
        out[k] = last
    return out


def check_motion(run: RecordedRun, segments: Sequence[Segment]) -> None:
    """IdentifyError where the recording is too short or the robot hardly moved."""
    if len(segments) < 2:
        raise IdentifyError(
            f"identify: {len(segments)} segment(s) with a trajectory and encoder readings in "
            "the bag, 2 needed: record a longer run (with motion capture, or the sensors an "
            "estimator needs)"
        )
    L = run.description.characteristic_length
    moved = max(float(np.abs(s.recorded - s.nodes).max()) for s in segments)
    if moved < 0.02 * L:
        raise IdentifyError(
            f"identify: the robot moved {1e3 * moved:.0f} mm at most in any segment "
            f"(at least {20 * L:.0f} mm needed): too little motion to fit a model to"
        )


# ---------------------------------------------------------------- the models


def _rod_states(d: RobotDescription, seg: Segment) -> tuple[NDArray[np.float64], ...]:
    """Rod centres (r, 3), quaternions (r, 4), linear and angular velocities (r, 3) at
    the segment's start, from its node positions and velocities (n, 3) and the spin
    about each rod's axis its gyro read (the endcaps cannot show it, and a rolling rod
    spins: started still, its endcaps would be dragged over the ground)."""
    rn = d.rod_nodes
    nodes, velocities = seg.nodes, seg.velocities
    a, b = nodes[rn[:, 0]], nodes[rn[:, 1]]
    va, vb = velocities[rn[:, 0]], velocities[rn[:, 1]]
    arm = b - a
    omega = np.cross(arm, vb - va) / np.sum(arm * arm, axis=1, keepdims=True)
    axes = rod_axes(nodes, rn)
    return (
        rod_centres(nodes, rn),
        rod_quaternion_from_axis(axes),
        0.5 * (va + vb),
        omega + seg.spin[:, None] * axes,
    )


PRIME_STEPS = 2
"""Physics steps run from a segment's start before it is set again and replayed."""


def _restart(world: PhysicsWorld, d: RobotDescription, seg: Segment) -> NDArray[np.float64]:
    """Put ``world`` in the segment's recorded start, the actuated cables at the
    encoders' first reading; the rods' centre velocities set (r, 3; m/s).

    PyBullet's contact solver starts each step from the last one's impulses (warm
    starting) and does not converge within a step: a teleported robot would rest on
    the impulses of wherever the world was before (the previous segment's end), or on
    none in a fresh world, and sag or jolt for some steps (IMU readings a hundred
    times the noise). A few steps from the start, and the start set again, give it
    those of this contact, and each replay the same whatever went before."""
    rest = d.rest_lengths.copy()
    rest[d.actuated] = seg.encoders[0]
    states = _rod_states(d, seg)
    for hold in (True, False):
        world.set_rest_lengths(rest)
        world.set_rod_states(*states)
        if hold:
            world.advance(PRIME_STEPS, seg.encoders[0].tolist(), [False] * PRIME_STEPS)
    return states[2]


def replay_sim(
    description: RobotDescription, segments: Sequence[Segment], control_period: float,
    time_step: float,
) -> list[NDArray[np.float64]]:  # fmt: skip
    """Each segment's node positions (K, n, 3) as the simulator replays its commands
    from its recorded start, the actuated cables at the encoders' first reading."""
    from tensegrity_gym.sim.world import PhysicsWorld

    if not segments:
        return []  # a fit on the IMU windows alone: no world to build (46 ms each)
    n_steps = round(control_period / time_step)
    flags = [False] * (n_steps - 1) + [True]
    world = PhysicsWorld(description, time_step)
    out = []
    try:
        for seg in segments:
            _restart(world, description, seg)
            path = [world.advance(n_steps, command.tolist(), flags)[0].node_positions
                    for command in seg.commands]  # fmt: skip
            out.append(np.asarray(path, dtype=np.float64))
    finally:
        world.close()
    return out


def replay_imu(
    description: RobotDescription, windows: Sequence[Segment], control_period: float,
    time_step: float,
) -> list[NDArray[np.float64]]:  # fmt: skip
    """Each IMU window's (:func:`imu_windows`) features (s, q, 3) as the simulator's IMUs
    read them, without noise, over its period replayed from its recorded start."""
    from tensegrity_gym.sim.world import PhysicsWorld

    if not windows:
        return []
    n_steps = round(control_period / time_step)
    world = PhysicsWorld(description, time_step)
    out = []
    try:
        for seg in windows:
            assert seg.imu is not None
            steps = seg.imu.steps.tolist()
            wanted = set(steps) | {j - seg.imu.span for j in steps}
            flags = [j + 1 in wanted for j in range(n_steps)]
            v0 = _restart(world, description, seg)
            snaps = world.advance(n_steps, seg.commands[0].tolist(), flags)
            at = dict(zip([j + 1 for j in range(n_steps) if flags[j]], snaps, strict=True))
            out.append(readings_of_replay(description, seg.imu, v0, at, time_step))
    finally:
        world.close()
    return out


def replay_ukf(
    description: RobotDescription, segments: Sequence[Segment], control_period: float,
    time_step: float,
) -> list[NDArray[np.float64]]:  # fmt: skip
    """Each segment's node positions (K, n, 3) as the UKF's spring-mass model predicts
    them from its recorded start, driven by the encoders as the filter is."""
    from estimation.ukf import SpringMassModel

    model = SpringMassModel(description)
    out = []
    for seg in segments:
        state = np.concatenate([seg.nodes.ravel(), seg.velocities.ravel()])
        path = []
        for k in range(len(seg.commands)):
            state = model.propagate(state, control_period, seg.encoders[k], seg.encoders[k + 1])
            path.append(state[: 3 * description.n_nodes].reshape(-1, 3))
        out.append(np.asarray(path))
    return out


MODELS: dict[str, Callable[..., list[NDArray[np.float64]]]] = {"sim": replay_sim, "ukf": replay_ukf}
"""``--model``: which physics is fitted."""


def segment_errors(
    description: RobotDescription, segments: Sequence[Segment], paths: Sequence[NDArray[np.float64]]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per segment: the open-loop CoM error (m, mean over its periods) and the node RMS
    error (m); a non-finite replay counts as an error of 1e3 m."""
    masses = description.node_masses
    com, nodes = [], []
    for seg, path in zip(segments, paths, strict=True):
        if not np.all(np.isfinite(path)):
            com.append(1e3)
            nodes.append(1e3)
            continue
        delta = center_of_mass(path, masses) - center_of_mass(seg.recorded, masses)
        com.append(float(np.mean(np.linalg.norm(delta, axis=-1))))
        nodes.append(float(np.sqrt(np.mean(np.sum((path - seg.recorded) ** 2, axis=-1)))))
    return np.asarray(com), np.asarray(nodes)


# ---------------------------------------------------------------- the fit


@dataclass(frozen=True)
class _Problem:
    """What a worker needs to score candidates: shipped once to each worker."""

    description: RobotDescription
    names: tuple[str, ...]
    segments: tuple[Segment, ...]
    windows: tuple[Segment, ...]
    """IMU windows (:func:`imu_windows`); none for a bag without IMU, or the UKF model."""
    model: str
    control_period: float
    time_step: float

    def chunks(self, n: int) -> list[tuple[slice, slice]]:
        """``n`` shares of the segments and of the windows, a job each."""

        def cut(total: int) -> list[slice]:
            edges = np.linspace(0, total, n + 1).round().astype(int)
            return [slice(int(a), int(b)) for a, b in itertools.pairwise(edges)]

        return list(zip(cut(len(self.segments)), cut(len(self.windows)), strict=True))

    def errors(
        self, log_factors: NDArray[np.float64], chunk: tuple[slice, slice], fit: bool
    ) -> _Errors:
        """:func:`segment_errors` (CoM, node RMS; m) of each segment in ``chunk``'s
        first slice and the :func:`window_scores` of each window in its second, under
        the candidate; with ``fit``, only what :func:`fit_cost` reads (the segments
        left out where there are IMU windows)."""
        d = apply_parameters(self.description, self.names, log_factors)
        segments, windows = self.segments[chunk[0]], self.windows[chunk[1]]
        if fit and self.windows:
            segments = ()
        paths = MODELS[self.model](d, segments, self.control_period, self.time_step)
        readings = [w.imu for w in windows if w.imu is not None]
        replayed = replay_imu(d, windows, self.control_period, self.time_step)
        return (*segment_errors(d, segments, paths), window_scores(d, readings, replayed))


_Errors = tuple["NDArray[np.float64]", "NDArray[np.float64]", "NDArray[np.float64]"]
"""Per segment its CoM and node RMS errors (m), per IMU window its score."""


def _joined(parts: Sequence[_Errors]) -> _Errors:
    """The chunks' errors of one candidate, in the segments' and windows' order."""
    com, nodes, imu = (np.concatenate([p[i] for p in parts]) for i in range(3))
    return com, nodes, imu


def fit_cost(errors: _Errors) -> float:
    """What CMA-ES minimises: the IMU windows' :func:`imu_term` where there are any,
    else the log of the mean squared node RMS error over the segments.

    Not both: over 2 s the replay of a rolling robot departs from the recording by
    chance as much as by its parameters (where it lands on a face), and that chance
    outweighs what damping changes; CMA-ES, which ranks candidates, then wanders along
    the damping. The IMU windows' one period is too short for it."""
    _, nodes, imu = errors
    if len(imu):
        return imu_term(imu)
    return float(np.log(np.mean(np.minimum(nodes, 1e3) ** 2) + 1e-12))


MAX_EVALUATIONS = 320
"""The search's default budget (:func:`_stages`): a 60 s 3-bar bag in under ten minutes
on two cores."""
COARSE_STRIDE = 4
"""The search's first stage scores candidates on every COARSE_STRIDE-th IMU window ..."""
COARSE_SHARE = 0.5
"""... for this share of its budget; the rest scores them on every window."""
COARSE_LEAST_WINDOWS = 40
"""Fewer IMU windows than this (ten in the coarse share): one stage, on all of them."""


_PROBLEM: _Problem | None = None


def _init_worker(problem: _Problem) -> None:
    global _PROBLEM
    _PROBLEM = problem


def _errors(args: tuple[NDArray[np.float64], tuple[slice, slice], bool]) -> _Errors:
    """The worker's :meth:`_Problem.errors` of (candidate, chunk, fit)."""
    assert _PROBLEM is not None
    return _PROBLEM.errors(*args)


@dataclass(frozen=True)
class Identification:
    """What ``identify`` found."""

    description: RobotDescription
    """The fitted robot."""
    names: tuple[str, ...]
    factors: NDArray[np.float64]
    """(p,) each factor's fitted value (1 = the starting description's)."""
    com_before: NDArray[np.float64]
    """(segments,) open-loop CoM error (m, mean over each segment) with the starting
    description."""
    com_after: NDArray[np.float64]
    nodes_before: NDArray[np.float64]
    """(segments,) node RMS error (m) with the starting description."""
    nodes_after: NDArray[np.float64]
    imu_before: NDArray[np.float64]
    """(windows,) each IMU window's score (:func:`window_scores`; mean squared error in
    units of the sensors' noise) with the starting description; empty without them."""
    imu_after: NDArray[np.float64]
    evaluations: int
    """Candidates scored, on a share of the IMU windows and on all of them together
    (:func:`_stages`: a budget of 320 scores about 800)."""
    seconds: float
    """Wall time of the fit (s)."""
    segments: tuple[Segment, ...]
    trajectory: str
    """What was fitted: ``"ground truth"`` (motion capture) or ``"UKF estimates"``."""
    model: str
    control_period: float
    time_step: float

    @property
    def at_bound(self) -> dict[str, tuple[float, float]]:
        """The factors that ended at a bound of the search (|log| beyond
        :data:`AT_BOUND_SHARE` of the bound's), each with the range searched (low, high):
        the model could not explain the recording with that factor inside it, a sign
        that the model, not the factor, is wrong."""
        bounds = np.exp(factor_bounds(self.names))
        out = {}
        for name, f, b in zip(self.names, self.factors, bounds, strict=True):
            if abs(np.log(f)) >= AT_BOUND_SHARE * np.log(b):
                out[name] = (round(float(1.0 / b), 4), round(float(b), 4))
        return out


def identify_run(
    run: RecordedRun,
    groups: Sequence[str],
    *,
    description: RobotDescription | None = None,
    model: str = "sim",
    segment_seconds: float = 2.0,
    max_evaluations: int = MAX_EVALUATIONS,
    workers: int | None = None,
    seed: int = 0,
    time_step: float = 0.001,
    imu_windows_most: int = 300,
) -> Identification:
    """Fit the factors of the ``groups`` (``GROUPS``) of ``description`` (default:
    the run's own) so that ``model`` (``MODELS``) replays ``run`` as recorded: the
    IMU's readings over one period from each of at most ``imu_windows_most`` recorded
    states, where the model is the simulator's and the bag has an IMU topic (0: never),
    else the node positions over its segments of ``segment_seconds`` (see
    :func:`fit_cost`); both are reported before and after. ``max_evaluations`` is the
    search's budget in candidates scored on every IMU window (:func:`_stages`). IdentifyError
    with one line where it cannot."""
    if model not in MODELS:
        raise IdentifyError(f"identify: unknown model {model!r}; choose from {sorted(MODELS)}")
    if not (math.isfinite(segment_seconds) and segment_seconds >= run.control_period):
        raise IdentifyError(
            f"identify: segment_seconds (--segment-seconds) = {segment_seconds!r} must be a "
            f"finite number of seconds >= the run's control period, {run.control_period:g} s"
        )
    start = description or run.description
    names = tuple(factor_names(groups, start))
    if not names:
        raise IdentifyError("identify: no parameter to fit (--params names none this robot has)")
    frames, trajectory = recorded_trajectory(run)
    segments = tuple(segments_of(run, frames, segment_seconds))
    check_motion(run, segments)
    windows: tuple[Segment, ...] = ()
    if model == "sim" and imu_windows_most > 0:  # the UKF's model has no IMU
        windows = tuple(imu_windows(run, frames, time_step, imu_windows_most))
    problem = _Problem(start, names, segments, windows, model, run.control_period, time_step)
    workers = max(1, min(workers or os.cpu_count() or 1, len(segments)))
    chunks = problem.chunks(workers)
    clock = time.perf_counter()
    with ProcessPoolExecutor(workers, initializer=_init_worker, initargs=(problem,)) as pool:

        def score(x: NDArray[np.float64]) -> _Errors:
            return _joined(list(pool.map(_errors, [(x, c, False) for c in chunks])))

        best, evaluations = _minimise(pool, chunks, names, max_evaluations, seed)
        before, after = score(np.zeros(len(names))), score(best)
    return Identification(
        apply_parameters(start, names, best), names, np.exp(best), before[0], after[0],
        before[1], after[1], before[2], after[2], evaluations, time.perf_counter() - clock,
        segments, trajectory, model, run.control_period, time_step,
    )  # fmt: skip


def _stages(
    chunks: Sequence[tuple[slice, slice]], max_evaluations: int
) -> list[tuple[list[tuple[slice, slice]], int]]:
    """The search's stages: the chunks each scores candidates on, and the evaluation
    count it runs until. ``max_evaluations`` is the budget in candidates scored on every
    window; a coarse stage's COARSE_STRIDE candidates cost one. Each stage ends with
    the generation that reaches its count, so the first may take a few candidates
    from the second.

    The IMU windows' cost is narrow along the damping (off by 7 % the windows' mean
    score is 3 times its least on the 3-bar bench, their median 16 times), and CMA-ES
    needs many generations to learn such a valley: within 400 evaluations on every
    window its mean was still far from it (the damping 11 % off), while a quarter of
    the windows gives four times the generations for the same time, and the last ones,
    on every window, settle the factors. The quarter is every COARSE_STRIDE-th window
    of the bag, whatever the chunks (the worker count); with under COARSE_LEAST_WINDOWS
    windows in all, one stage."""
    if sum(w.stop - w.start for _, w in chunks) < COARSE_LEAST_WINDOWS:
        return [(list(chunks), max_evaluations)]
    coarse = [(segments, slice(w.start + (-w.start) % COARSE_STRIDE, w.stop, COARSE_STRIDE))
              for segments, w in chunks]  # fmt: skip
    share = round(COARSE_SHARE * max_evaluations)
    coarse_until = COARSE_STRIDE * share
    return [(coarse, coarse_until), (list(chunks), coarse_until + max_evaluations - share)]


def _minimise(
    pool: ProcessPoolExecutor, chunks: Sequence[tuple[slice, slice]], names: Sequence[str],
    max_evaluations: int, seed: int,
) -> tuple[NDArray[np.float64], int]:  # fmt: skip
    """CMA-ES over the log-factors of ``names`` within their bounds, each generation's
    candidates scored by :func:`fit_cost` on the pool's workers, a job per chunk (on a
    share of the IMU windows first, :func:`_stages`): the log-factors (p,) it settled
    on and the evaluations made."""
    import cma

    bounds = factor_bounds(names)
    stages = _stages(chunks, max_evaluations)
    options = {"bounds": [list(-bounds), list(bounds)], "seed": seed + 1, "verbose": -9,
               "maxfevals": stages[-1][1], "tolfun": 1e-9, "tolx": 1e-4}  # fmt: skip
    if len(names) == 1:
        # cma 4.5 fails in one dimension when the step outgrows the std it derives from
        # the bounds (a flat cost); the bounds alone hold the search there.
        options["maxstd"] = np.inf
    es = cma.CMAEvolutionStrategy(np.zeros(len(names)), 0.3, options)
    for stage, until in stages:
        # The coarse stage settling (its steps under tolx, say) is not the search's end.
        es.stop().clear()
        n = len(stage)
        while es.countevals < until and not es.stop():
            xs = es.ask()
            parts = list(pool.map(_errors, [(np.asarray(x), c, True) for x in xs for c in stage]))
            costs = [fit_cost(_joined(parts[i * n : (i + 1) * n])) for i in range(len(xs))]
            es.tell(xs, costs)
            logger.info("identify: %d evaluations, best %.4g", es.countevals, min(costs))
    # The distribution's mean, not its best sample: the cost is rough at the scale of
    # the last steps (which contacts a replay makes), the mean averages over it (on
    # the 3-bar bench all factors within 1.1 % of the recording's, the best within 1.9).
    return np.asarray(es.result.xfavorite, dtype=np.float64), int(es.countevals)
