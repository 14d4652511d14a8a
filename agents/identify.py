"""System identification from a recorded run (issue 16): ``tensegrity-gym identify``.

The bag's commands are replayed in a model of the robot from the recorded state, over
many short segments, each restarted from the recorded state (multiple shooting: rolling
is chaotic, and one long open-loop replay would diverge whatever the parameters), and
the chosen physical parameters of the description are fitted so that the simulated
motion matches the recorded one (motion capture where the bag has it, else the UKF's
estimates). The optimiser is CMA-ES (the ``cma`` package) over log-scales of the
description's values; each generation's candidates are evaluated on the machine's
cores, a worker per core, each holding its own model.

Two models can be fitted: the simulator's (``"sim"``, PyBullet, the default), and the
UKF's spring-mass net (``"ukf"``, its own simpler physics, driven by the encoders as
the filter is). Either way the result is a robot description: the simulator, the UKF
and ``gym.make(robot=...)`` load it.
"""

from __future__ import annotations

import itertools
import logging
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

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

__all__ = [
    "MODELS",
    "PARAMETERS",
    "Identification",
    "IdentifyError",
    "Segment",
    "apply_parameters",
    "identify_run",
    "recorded_trajectory",
    "segment_errors",
    "segments_of",
]

logger = logging.getLogger(__name__)


class IdentifyError(ValueError):
    """The recording cannot identify anything; the message (one line) says why."""


# ---------------------------------------------------------------- the parameters


def _scaled_cables(d: RobotDescription, field: str, factor: float, which: bool | None) -> Any:
    """``d``'s cables with ``field`` times ``factor``, for the actuated ones (True), the
    passive ones (False) or all (None)."""
    cables = tuple(
        replace(c, **{field: getattr(c, field) * factor})
        if which is None or c.actuated == which
        else c
        for c in d.cables
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

_BOUND = {"passive_rest_length": np.log(1.2)}
"""Largest |log factor| searched, per factor; the others: a factor of 2 either way."""


def apply_parameters(
    description: RobotDescription, names: Sequence[str], log_factors: NDArray[np.float64]
) -> RobotDescription:
    """``description`` with each named factor (``PARAMETERS``' inner names) applied as
    ``exp(log_factor)``."""
    setters = {name: setter for group in PARAMETERS.values() for name, setter in group}
    d = description
    for name, value in zip(names, log_factors, strict=True):
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
    return float(values[name]())


def factor_names(groups: Sequence[str], description: RobotDescription) -> list[str]:
    """The factors of the ``--params`` groups; an unknown group refused with the valid
    ones; a group the robot has nothing for (passive cables, motors) left out."""
    unknown = [g for g in groups if g not in PARAMETERS]
    if unknown:
        raise IdentifyError(
            f"identify: unknown parameter group {unknown[0]!r}; choose from {sorted(PARAMETERS)}"
        )
    if "mass" in groups and ({"stiffness", "damping"} & set(groups)):
        raise IdentifyError(
            "identify: mass cannot be fitted with stiffness or damping: scaling the masses, "
            "stiffnesses and dampings by one factor leaves the motion unchanged (gravity "
            "and friction scale with the mass); weigh the rods, or fit mass alone"
        )
    has_passive = any(not c.actuated for c in description.cables)
    names = [name for g in groups for name, _ in PARAMETERS[g]]
    return [n for n in names if has_passive or not n.startswith("passive")]


# ---------------------------------------------------------------- the segments


@dataclass(frozen=True)
class Segment:
    """A stretch of the recording to replay open loop from its recorded start."""

    start: int
    """Index of its first control period in the run."""
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


Frame = tuple["NDArray[np.float64]", "NDArray[np.float64]"]
"""Node positions and velocities (n, 3) of one period's end: the trajectory fitted."""


def recorded_trajectory(run: RecordedRun) -> tuple[list[Frame | None], str]:
    """The trajectory to fit, per period (the start, then each step): the ground truth
    (motion capture) where the bag has it, else the UKF's estimates of the run; and
    which it is (``"ground truth"``, ``"UKF estimates"``)."""
    steps = [run.start, *run.steps]
    if any(s.truth is not None for s in steps):
        frames: list[Frame | None] = [
            None if s.truth is None
            else (np.asarray(s.truth.node_positions), np.asarray(s.truth.node_velocities))
            for s in steps
        ]  # fmt: skip
        return frames, "ground truth"
    from agents.runs import replay
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
        (e.node_positions, e.node_velocities) if e.healthy and e.is_finite() else None
        for e in estimates
    ], "UKF estimates"


def segments_of(run: RecordedRun, frames: Sequence[Frame | None], seconds: float) -> list[Segment]:
    """Segments of ``seconds`` of ``run`` back to back, each over periods whose
    trajectory ``frames`` (one per period, the start first) and encoder readings are
    known."""
    K = max(1, round(seconds / run.control_period))
    encoders = _encoder_track(run)
    commands = [s.command for s in run.steps]
    out = []
    for start in range(0, len(frames) - K, K):
        window = frames[start : start + K + 1]
        track = encoders[start : start + K + 1]
        if any(f is None for f in window) or np.isnan(track).any():
            continue
        known = [f for f in window if f is not None]
        out.append(Segment(
            start=start, nodes=known[0][0], velocities=known[0][1], encoders=track,
            commands=np.array(commands[start : start + K]),
            recorded=np.array([f[0] for f in known[1:]]),
        ))  # fmt: skip
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


def _rod_states(
    d: RobotDescription, nodes: NDArray[np.float64], velocities: NDArray[np.float64]
) -> tuple[NDArray[np.float64], ...]:
    """Rod centres (r, 3), quaternions (r, 4), linear and angular velocities (r, 3) from
    node positions and velocities (n, 3); no spin about a rod's own axis (the endcaps
    cannot show it, and a symmetric rod does not feel it)."""
    rn = d.rod_nodes
    a, b = nodes[rn[:, 0]], nodes[rn[:, 1]]
    va, vb = velocities[rn[:, 0]], velocities[rn[:, 1]]
    arm = b - a
    omega = np.cross(arm, vb - va) / np.sum(arm * arm, axis=1, keepdims=True)
    return (
        rod_centres(nodes, rn),
        rod_quaternion_from_axis(rod_axes(nodes, rn)),
        0.5 * (va + vb),
        omega,
    )


def replay_sim(
    description: RobotDescription, segments: Sequence[Segment], control_period: float,
    time_step: float,
) -> list[NDArray[np.float64]]:  # fmt: skip
    """Each segment's node positions (K, n, 3) as the simulator replays its commands
    from its recorded start, the actuated cables at the encoders' first reading."""
    from tensegrity_gym.sim.world import PhysicsWorld

    n_steps = round(control_period / time_step)
    flags = [False] * (n_steps - 1) + [True]
    world = PhysicsWorld(description, time_step)
    rest = description.rest_lengths.copy()
    out = []
    try:
        for seg in segments:
            rest[description.actuated] = seg.encoders[0]
            world.set_rest_lengths(rest)
            world.set_rod_states(*_rod_states(description, seg.nodes, seg.velocities))
            path = [world.advance(n_steps, command.tolist(), flags)[0].node_positions
                    for command in seg.commands]  # fmt: skip
            out.append(np.asarray(path, dtype=np.float64))
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
    model: str
    control_period: float
    time_step: float

    def errors(
        self, log_factors: NDArray[np.float64], chunk: slice
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """:func:`segment_errors` (CoM, node RMS; m) of each segment in ``chunk``
        under the candidate."""
        d = apply_parameters(self.description, self.names, log_factors)
        segments = self.segments[chunk]
        paths = MODELS[self.model](d, segments, self.control_period, self.time_step)
        return segment_errors(d, segments, paths)


_PROBLEM: _Problem | None = None


def _init_worker(problem: _Problem) -> None:
    global _PROBLEM
    _PROBLEM = problem


def _errors(
    args: tuple[NDArray[np.float64], slice],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The worker's :meth:`_Problem.errors` of (candidate, chunk)."""
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
    evaluations: int
    seconds: float
    """Wall time of the fit (s)."""
    segments: tuple[Segment, ...]
    trajectory: str
    """What was fitted: ``"ground truth"`` (motion capture) or ``"UKF estimates"``."""
    model: str
    control_period: float
    time_step: float


def identify_run(
    run: RecordedRun,
    groups: Sequence[str],
    *,
    description: RobotDescription | None = None,
    model: str = "sim",
    segment_seconds: float = 2.0,
    max_evaluations: int = 400,
    workers: int | None = None,
    seed: int = 0,
    time_step: float = 0.001,
) -> Identification:
    """Fit the factors of the ``groups`` (``PARAMETERS``) of ``description`` (default:
    the run's own) so that ``model`` (``MODELS``) replays ``run``'s segments of
    ``segment_seconds`` as recorded. IdentifyError with one line where it cannot."""
    import cma

    if model not in MODELS:
        raise IdentifyError(f"identify: unknown model {model!r}; choose from {sorted(MODELS)}")
    start = description or run.description
    names = tuple(factor_names(groups, start))
    if not names:
        raise IdentifyError("identify: no parameter to fit (--params names none this robot has)")
    frames, trajectory = recorded_trajectory(run)
    segments = tuple(segments_of(run, frames, segment_seconds))
    check_motion(run, segments)
    problem = _Problem(start, names, segments, model, run.control_period, time_step)
    workers = max(1, min(workers or os.cpu_count() or 1, len(segments)))
    edges = np.linspace(0, len(segments), workers + 1).round().astype(int)
    chunks = [slice(int(a), int(b)) for a, b in itertools.pairwise(edges)]
    bounds = np.array([_BOUND.get(n, np.log(2.0)) for n in names])
    clock = time.perf_counter()
    with ProcessPoolExecutor(workers, initializer=_init_worker, initargs=(problem,)) as pool:

        def cost(candidates: list[NDArray[np.float64]]) -> list[float]:
            jobs = [(np.asarray(x), c) for x in candidates for c in chunks]
            scores = [nodes for _, nodes in pool.map(_errors, jobs)]
            per = [np.concatenate(scores[i * len(chunks) : (i + 1) * len(chunks)])
                   for i in range(len(candidates))]  # fmt: skip
            return [float(np.mean(np.minimum(s, 1e3) ** 2)) for s in per]

        es = cma.CMAEvolutionStrategy(
            np.zeros(len(names)), 0.3,
            {"bounds": [list(-bounds), list(bounds)], "seed": seed + 1, "verbose": -9,
             "maxfevals": max_evaluations, "tolfun": 1e-9, "tolx": 1e-4},
        )  # fmt: skip
        while not es.stop():
            xs = es.ask()
            es.tell(xs, cost(xs))
            logger.info("identify: %d evaluations, best %.4g", es.countevals, es.result.fbest)
        best = np.asarray(es.result.xbest, dtype=np.float64)
        before, after = (list(pool.map(_errors, [(x, c) for c in chunks]))
                         for x in (np.zeros(len(names)), best))  # fmt: skip
    fitted = apply_parameters(start, names, best)
    return Identification(
        fitted, names, np.exp(best),
        np.concatenate([b[0] for b in before]), np.concatenate([a[0] for a in after]),
        np.concatenate([b[1] for b in before]), np.concatenate([a[1] for a in after]),
        int(es.countevals), time.perf_counter() - clock, segments, trajectory, model,
        run.control_period, time_step,
    )  # fmt: skip
