"""Scripted rolling gaits: a face-to-face table driven by the estimated state.

The robot rests on a support face (its three lowest nodes). For each face of its
rolling cycle, a table names the actuated cables to contract fully and whether the
others hold their initial rest length or are let out to their maximum. The gait holds
that command for ``hold_steps``, then returns to the initial lengths for
``settle_steps`` so the robot comes to rest on its next face, and repeats. A gait with
``ramp_steps`` moves its commands along a ramp, each across the motors' whole range in
that many control steps: slower than the slowest motor, so that motors faster or slower
than their rating still contract together (a flip is dynamic: with the three cables'
motors ±25 % apart, ThreeBarRoll-v0's robot stops halfway, on the face between two of
the table's, every period). Like the hold and the rest, the ramp is counted in control
steps (the 3-bar's 11 assume its 0.1 s period), and the way back to the initial lengths
is part of the rest.

Each preset's tables live with the robot, in its YAML
(:class:`tensegrity_gym.model.description.Gait`): the ``gait`` section is its default,
``"forward"``, and a ``gaits`` section may add more by name (three_bar_large has
``backward``, ``left`` and ``right``). ``scripts/find_gait.py`` finds them: the
transitions that carry the centre of mass furthest in one direction, or a cycle of them
whose path turns. Faces are sets of node indices, fixed to the robot's body, so a table
works at any heading; the rolling direction follows the robot's orientation, not the
task's goal.

A *steering* gait (``scripts/find_gait.py --steer``; three_bar's and SUPERball's
``steer``) lists, for each face, several contractions with the move each makes (the
CoM's displacement and the turn, in the face's own frame) and the face it leads to.
FaceGait turns every move into the goal frame by the support triangle's yaw there and
takes the contraction whose move, followed by the best ``horizon - 1`` moves after it
(composed from the model), carries the CoM furthest toward the goal: the goal frame's x
axis, which the tasks point at the goal. A move that left the robot on its face is not
chosen there again that episode (until all of the face's have). It rolls toward any
heading and to any goal, which a fixed table cannot.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from tensegrity_gym.model.description import DEFAULT_GAIT, DescriptionError, GaitFace

if TYPE_CHECKING:
    from collections.abc import Callable, Iterable, Iterator

    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.protocols import Task
    from tensegrity_gym.tasks.common import TaskObservation

__all__ = [
    "FaceGait",
    "GaitTable",
    "PeriodChoice",
    "Tempo",
    "face_yaw",
    "gait_table",
    "lowest_face",
    "period_commands",
    "ramp_toward",
    "turned",
]

_YAW_BIN = np.radians(2.0)
"""The yaw's resolution (rad) of a steering gait's memoised lookahead."""

GaitTable = dict[tuple[int, ...], tuple[tuple[int, ...], str]]
"""Face (sorted node indices) -> (actuated cable indices to contract, "hold" | "out")."""

Tempo = tuple[int, int]
"""A gait period's (hold, settle) control steps."""

PeriodChoice = tuple[int, "Tempo | None"]
"""What a :attr:`FaceGait.chooser` picks as a period begins: the support face's entry
(an index, modulo the face's count) and the period's tempo (None: the gait's own)."""


def gait_table(description: RobotDescription, gait: str = DEFAULT_GAIT) -> GaitTable:
    """The robot's gait ``gait`` (a name of its ``gaits``) as a table; for a face with
    several entries (a steering gait), the first.

    Raises:
        ValueError: the robot has no gait by that name; the message lists those it has.
    """
    found = description.gaits.get(gait)
    if found is None:
        raise DescriptionError(
            f"no gait table for robot {description.name!r} named {gait!r}: its description "
            f"({description.source or 'not from a file'}) has "
            + (f"the gaits {sorted(description.gaits)}" if description.gaits else "none")
            + "; find one with scripts/find_gait.py"
        )
    table: GaitTable = {}
    for f in found.faces:  # a steering gait's face: its first entry
        table.setdefault(f.face, (f.contract, f.others))
    return table


def lowest_face(positions: NDArray[np.floating]) -> tuple[int, ...]:
    """The support face: the indices of the three lowest of ``positions`` (n, 3),
    sorted."""
    return tuple(sorted(np.argsort(positions[:, 2], kind="stable")[:3].tolist()))


def face_yaw(positions: NDArray[np.floating], face: tuple[int, ...]) -> float:
    """The support triangle's yaw (rad): from its centre to its first node (the lowest
    index), seen from above; ``positions`` (n, 3) of the nodes in any frame with z up."""
    p = positions[list(face), :2]
    v = p[0] - p.mean(axis=0)
    return float(np.arctan2(v[1], v[0]))


def turned(v: NDArray[np.floating], angle: float) -> NDArray[np.float64]:
    """Planar vectors ``v`` (..., 2) turned counter-clockwise (from above) by ``angle``
    (rad)."""
    c, s = np.cos(angle), np.sin(angle)
    v = np.asarray(v, dtype=np.float64)
    return np.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], axis=-1)


def ramp_toward(
    commanded: NDArray[np.float32], target: NDArray[np.float32], ramp_steps: int
) -> NDArray[np.float32]:
    """The next command, actions (m,) in [-1, 1]: ``target`` where it lies within one
    step of ``commanded``, else one step toward it (a step: 2 / ``ramp_steps``, the
    whole range in ``ramp_steps`` calls); ``ramp_steps`` 0: ``target`` at once."""
    if ramp_steps <= 0:
        return target.astype(commanded.dtype)
    step = np.float32(2.0 / ramp_steps)
    delta = target - commanded
    # Within a step (and float32's rounding of the steps taken): there.
    nxt = np.where(np.abs(delta) <= step + 1e-6, target, commanded + np.sign(delta) * step)
    return nxt.astype(commanded.dtype, copy=False)


def period_commands(
    commanded: NDArray[np.float32],
    action: NDArray[np.float32],
    rest: NDArray[np.float32],
    steps: tuple[int, int, int],
) -> Iterator[NDArray[np.float32]]:
    """The commands (m,) of one gait period, a control step each: ``action`` for the
    hold, then ``rest`` (the initial rest lengths) for the settle, each reached along the
    ramp from ``commanded`` (the last command). ``steps``: (hold, settle, ramp) steps."""
    hold_steps, settle_steps, ramp_steps = steps
    for k in range(hold_steps + settle_steps):
        commanded = ramp_toward(commanded, action if k < hold_steps else rest, ramp_steps)
        yield commanded


@dataclass(frozen=True)
class _Choice:
    """One contraction a gait may make on a face: its action (m,) in [-1, 1], its move
    in the face's frame (3,) (m, m, rad; None: unknown) and the face it leads to."""

    action: NDArray[np.float32]
    move: NDArray[np.float64] | None
    to: tuple[int, ...] | None


class _Move(NamedTuple):
    """A choice's move, as the lookahead reads it: x, y (m), turn (rad), the face next."""

    x: float
    y: float
    turn: float
    to: tuple[int, ...] | None

    @classmethod
    def of(cls, move: NDArray[np.float64], to: tuple[int, ...] | None) -> _Move:
        return cls(float(move[0]), float(move[1]), float(move[2]), to)


def _choices(
    entries: Iterable[GaitFace], hold_action: NDArray[np.float32]
) -> dict[tuple[int, ...], list[_Choice]]:
    """Each face's choices, in the gait's order: the entries' actions (m,) (contracted
    cables at -1, the others at ``hold_action`` or let out to 1) and their moves."""
    out: dict[tuple[int, ...], list[_Choice]] = {}
    for e in entries:
        a = hold_action.copy() if e.others == "hold" else np.ones_like(hold_action)
        a[list(e.contract)] = -1.0
        move = None if e.move is None else np.asarray(e.move, dtype=np.float64)
        out.setdefault(e.face, []).append(_Choice(a, move, e.to))
    return out


class FaceGait:
    """A scripted policy that rolls the robot face to face.

    Call it with observations of a task in the goal frame (:class:`RollTask` or
    :class:`GoToTask`); it returns actions in [-1, 1], (m,). Keeps a small state (the
    period under way, the last command, which the ramp starts from, and a steering
    gait's moves that stalled this episode); :meth:`reset` clears it.

    Args:
        description: the robot; its gait named ``gait`` gives the table unless ``table``
            is given.
        task: decodes observations into node positions (its ``decode``, as the
            tasks of :mod:`tensegrity_gym.tasks.common` have).
        table: a face-to-action table, overriding the robot's.
        gait: the name of one of the robot's gaits (:attr:`RobotDescription.gaits`):
            ``"forward"`` (its YAML's ``gait``), or one of its ``gaits`` such as
            ``"backward"``, ``"left"``, ``"right"``, or ``"steer"`` (a steering gait,
            which chooses its moves by the goal); ValueError naming those it has for
            another.
        hold_steps, settle_steps: control steps of the contraction and of the rest;
            ``None``: the robot's gait's (25 and 10 without one).
        ramp_steps: control steps a command takes to cross the motors' whole range
            (:func:`ramp_toward`; 0: at once, at most ``hold_steps``); ``None``: the
            robot's gait's (0 without one).
        horizon: gait periods a steering gait looks ahead when it chooses (the paths
            are memoised by face and yaw, so a long horizon stays cheap: 1.3 s an
            episode of 300 steps on the 195 moves of SUPERball's first model, at 6).
    """

    def __init__(
        self,
        description: RobotDescription,
        task: Task,
        *,
        gait: str = DEFAULT_GAIT,
        table: GaitTable | None = None,
        hold_steps: int | None = None,
        settle_steps: int | None = None,
        ramp_steps: int | None = None,
        horizon: int = 6,
    ) -> None:
        given = table
        table = gait_table(description, gait) if table is None else table
        spec = description.gaits.get(gait)
        if hold_steps is None:
            hold_steps = spec.hold_steps if spec else 25
        if settle_steps is None:
            settle_steps = spec.settle_steps if spec else 10
        if ramp_steps is None:
            ramp_steps = spec.ramp_steps if spec else 0
        self.gait = gait
        if hold_steps < 1 or settle_steps < 0 or not 0 <= ramp_steps <= hold_steps:
            raise ValueError(
                f"hold_steps must be >= 1 (got {hold_steps}), settle_steps >= 0 (got "
                f"{settle_steps}), ramp_steps from 0 to hold_steps (got {ramp_steps})"
            )
        m = description.n_actuated
        for face, (cables, rest) in table.items():
            if rest not in ("hold", "out") or any(not 0 <= k < m for k in cables):
                raise ValueError(f"bad gait table entry {face}: {(cables, rest)}")
        decode = getattr(task, "decode", None)
        if not callable(decode):
            raise TypeError(
                f"FaceGait reads the robot's nodes from the observation: {type(task).__name__} "
                "has no decode(); use a task in the goal frame (tensegrity_gym.tasks.common)"
            )
        self._decode: Callable[[NDArray[np.float32]], TaskObservation] = decode
        self.table = table
        self.task = task
        self.hold_steps = hold_steps
        self.settle_steps = settle_steps
        self.ramp_steps = ramp_steps
        if not isinstance(horizon, int) or isinstance(horizon, bool) or horizon < 1:
            raise ValueError(f"horizon must be an integer >= 1 (periods), got {horizon!r}")
        self.horizon = horizon
        """Gait periods a steering gait looks ahead (:meth:`score`)."""
        self.chooser: Callable[[NDArray[np.float32]], PeriodChoice] | None = None
        """Picks the support face's entry and the period's tempo as each period begins
        (what :meth:`begin` takes), from the observation; None: the gait chooses."""
        lo, hi, _ = description.motor_limits
        rest_action = 2.0 * (description.rest_lengths[description.actuated] - lo) / (hi - lo) - 1.0
        self.hold_action = rest_action.astype(np.float32)
        entries = (
            spec.faces
            if spec is not None and given is None
            else tuple(GaitFace(f, c, r) for f, (c, r) in table.items())
        )
        self._choices = _choices(entries, self.hold_action)
        # The lookahead's moves as plain floats: it weighs thousands of paths a choice.
        self._moves = {
            face: [_Move.of(c.move, c.to) for c in cs if c.move is not None]
            for face, cs in self._choices.items()
        }
        self.reset()

    def reset(self) -> None:
        self._period: Iterator[NDArray[np.float32]] = iter(())
        self._commanded = self.hold_action.copy()
        self._last: tuple[tuple[int, ...], int] | None = None  # face, choice last period
        self._stalled: set[tuple[tuple[int, ...], int]] = set()

    def support_face(self, observation: NDArray[np.float32]) -> tuple[int, ...]:
        return lowest_face(self._decode(observation).positions)

    @property
    def steers(self) -> bool:
        """Whether the gait chooses among moves by the goal (a steering gait)."""
        return any(len(c) > 1 for c in self._choices.values())

    def action_for_face(
        self, face: tuple[int, ...], positions: NDArray[np.floating] | None = None
    ) -> NDArray[np.float32]:
        """The table's action on ``face``; for a face off the cycle, that of the most
        similar face. Where the face has several (a steering gait) and ``positions``
        (n, 3), the nodes in the goal frame, are given: the one that goes furthest
        toward the goal (:meth:`score`), less those that stalled on it this episode
        (see :meth:`__call__`)."""
        key, index = self._choose(face, positions)
        return self._choices[key][index].action

    def _listed(self, face: tuple[int, ...]) -> tuple[int, ...]:
        """``face`` where the table lists it, else the listed face most like it."""
        if face in self._choices:
            return face
        return max(self._choices, key=lambda f: len(set(f) & set(face)))

    def _choose(
        self, face: tuple[int, ...], positions: NDArray[np.floating] | None
    ) -> tuple[tuple[int, ...], int]:
        """The face whose entries apply (``face``, else the most similar listed) and the
        index of the entry chosen among them."""
        key = self._listed(face)
        choices = self._choices[key]
        if positions is None or len(choices) == 1:
            return key, 0
        yaw = face_yaw(positions, key)  # the moves are in the frame of the face listed
        open_ = [i for i in range(len(choices)) if (key, i) not in self._stalled]
        if not open_:  # every move stalled here once: try them all again
            self._stalled -= {(key, i) for i in range(len(choices))}
            open_ = list(range(len(choices)))
        return key, max(open_, key=lambda i: self.score(choices[i], yaw))

    def score(self, choice: _Choice, yaw: float, periods: int | None = None) -> float:
        """How far (m) toward the goal (the goal frame's x) ``choice`` carries the CoM
        from a support triangle at ``yaw`` (rad, goal frame), followed by the best
        ``periods - 1`` moves after it (the model's moves composed, each from the face
        and yaw the one before leaves): a lookahead, so that a turn or a move sideways
        that opens a fast way counts. ``periods`` None: :attr:`horizon`."""
        periods = self.horizon if periods is None else periods
        if choice.move is None or periods <= 0:
            return 0.0
        return self._path(_Move.of(choice.move, choice.to), yaw, periods, {})

    def _path(self, move: _Move, yaw: float, periods: int, seen: dict[Any, float]) -> float:
        """The progress (m) of ``move`` from a triangle at ``yaw``, then of the best
        ``periods - 1`` moves from the face it leads to (:meth:`_best_from`)."""
        ahead = move.x * math.cos(yaw) - move.y * math.sin(yaw)  # its goal-frame x
        if move.to is not None and periods > 1:
            ahead += self._best_from(move.to, yaw + move.turn, periods - 1, seen)
        return ahead

    def _best_from(
        self, face: tuple[int, ...], yaw: float, periods: int, seen: dict[Any, float]
    ) -> float:
        """The most progress (m) ``periods`` moves make from ``face`` at ``yaw``; the
        paths are memoised by face, periods and yaw to 2 degrees (``seen``), so that a
        long horizon stays cheap (the faces are few)."""
        key = (face, periods, round(yaw / _YAW_BIN))
        if key not in seen:
            paths = [self._path(m, yaw, periods, seen) for m in self._moves.get(face, ())]
            seen[key] = max(paths, default=0.0)  # no move known: none
        return seen[key]

    def __call__(self, observation: NDArray[np.float32]) -> NDArray[np.float32]:
        """The command for this control step. As a period begins, the support face
        chooses its action (:meth:`begin`)."""
        command = next(self._period, None)
        if command is None:
            index, tempo = (None, None) if self.chooser is None else self.chooser(observation)
            self.begin(observation, index, tempo)
            command = next(self._period)
        self._commanded = command
        return command.copy()

    @property
    def least_hold(self) -> int:
        """The shortest hold (control steps) a period can take: one step, and the ramp's
        (a command must reach its target before the settle begins)."""
        return max(1, self.ramp_steps)

    def runs(self, hold: int, settle: int) -> bool:
        """Whether a period of ``hold`` and ``settle`` control steps is one this gait can
        run (:meth:`begin`'s ``tempo``)."""
        return hold >= self.least_hold and settle >= 0

    @property
    def period_steps(self) -> int:
        """Control steps of one period: the hold and the settle."""
        return self.hold_steps + self.settle_steps

    @property
    def most_moves(self) -> int:
        """The most entries any face of the table has."""
        return max(len(c) for c in self._choices.values())

    def begin(
        self, observation: NDArray[np.float32], index: int | None = None, tempo: Tempo | None = None
    ) -> None:
        """Begin a period on the support face of ``observation``: with its entry
        ``index`` (modulo the face's count), or (None) the one the gait chooses; held
        and settled for ``tempo``'s (hold, settle) control steps (hold at least the
        ramp's), or (None) the gait's own. Where
        the period before began on the same face, its move stalled (the model's move did
        not happen from this state), and the gait does not choose that entry again on
        the face this episode, until every one of its entries has stalled."""
        positions = self._decode(observation).positions
        face = lowest_face(positions)
        if self._last is not None and self._last[0] == face:
            self._stalled.add(self._last)
        key, chosen = self._choose(face, positions)
        if index is not None:
            chosen = int(index) % len(self._choices[key])
        self._last = (key, chosen) if key == face else None
        hold, settle = (self.hold_steps, self.settle_steps) if tempo is None else tempo
        if not self.runs(hold, settle):
            raise ValueError(f"a period's tempo needs hold >= {self.least_hold} and "
                             f"settle >= 0, got {tempo}")  # fmt: skip
        steps = (hold, settle, self.ramp_steps)
        action = self._choices[key][chosen].action
        self._period = period_commands(self._commanded, action, self.hold_action, steps)

    def moves(self, observation: NDArray[np.float32]) -> tuple[NDArray[np.float64], ...]:
        """What the support face of ``observation`` offers, entry by entry (m,) for the
        face's m entries: each one's lookahead progress toward the goal (m,
        :meth:`score`; 0 where its move is unknown), whether it stalled on the face this
        episode, and which one the gait would choose (one-hot)."""
        positions = self._decode(observation).positions
        face = lowest_face(positions)
        key = self._listed(face)
        yaw = face_yaw(positions, key)
        choices = self._choices[key]
        scores = np.array([self.score(c, yaw) for c in choices])
        # The period before, begun on this face, stalled (begin records it).
        pending = self._last if self._last is not None and self._last[0] == face else None
        stalled = np.array([float((key, i) in self._stalled or (key, i) == pending)
                            for i in range(len(choices))])  # fmt: skip
        own = np.zeros(len(choices))
        open_ = [i for i in range(len(choices)) if not stalled[i]] or list(range(len(choices)))
        own[max(open_, key=lambda i: scores[i])] = 1.0
        return scores, stalled, own
