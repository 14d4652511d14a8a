"""Actions that choose among a steering gait's moves: one action, one gait period.

A steering gait (:class:`~tensegrity_gym.tasks.gaits.FaceGait` with ``gait="steer"``)
lists for each support face several contractions, each with the move it makes, and
chooses by a lookahead over those modelled moves. :class:`MoveChoice` hands that choice
to a policy: its action is the rank of the face's entry to make in the gait's order of
preference (0: the gait's own choice, then the others by their lookahead progress, the
ones that stalled last; modulo the face's count), and one step runs the whole period
(the hold and the settle, 35 control steps on the 3-bar) through the env beneath, the
rewards summed. The policy sees the env's observation (estimated states, the goal) and,
for each entry of the support face in that order, the gait's lookahead progress toward
the goal (m), whether the entry exists, whether it stalled here this episode, and
whether it is the gait's own choice (:func:`move_features`). A policy that always takes
rank 0 is the gait; one that learns which modelled moves do not happen, or pay less
than the model says, from the estimated state can do better. The ranks make the gait a
policy's natural start: a bias on rank 0's logit.

With ``tempos`` the action also sets the period's tempo, its (hold, settle) control
steps: action ``a`` takes rank ``a % ranks`` at tempo ``a // ranks`` of the gait's own
(0) followed by those given; a step is then that period. ``ranks`` (default: the most
entries a face has) limits the choice to the gait's first ranks: 1 leaves the move to
the gait, the policy setting the tempo alone. A flip ends well before the
gait's 35 steps on most faces, and a shorter period changes the flip itself: from a
given state some moves go further, faster, at one tempo, others at another, which the
gait's table (measured at its own tempo, from rest) cannot say. Action 0 is the gait,
at any ``tempos``.

Wrap an env made with absolute actions: ``MoveChoice(gym.make(ID))``. gym.make's time
limit, beneath the wrapper, still counts control steps: the episode lasts as long in
seconds as the id's. ``tensegrity-gym train --moves steer`` trains on it. A policy so
trained drives the env beneath, step by step, through :class:`MovePolicy` (what
``evaluate`` runs): the same choices at the same observations, the same episode.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, SupportsFloat, cast

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from numpy.typing import NDArray

from tensegrity_gym.tasks.gaits import FaceGait

if TYPE_CHECKING:
    from collections.abc import Callable, Sequence

    from tensegrity_gym.envs.tensegrity_env import TensegrityEnv
    from tensegrity_gym.tasks.gaits import PeriodChoice, Tempo

__all__ = [
    "MOVE_FEATURES",
    "MoveChoice",
    "MovePolicy",
    "check_ranks",
    "check_tempos",
    "entry_of_rank",
    "move_features",
    "observe_moves",
    "period_choice",
    "ranked_moves",
]

MOVE_FEATURES = 4
"""Entries per move in the observation: the lookahead progress (m), present, stalled,
the gait's own choice."""

_MOST_PROGRESS = 10.0
"""m: the lookahead progress is clipped to this (a few metres over six periods)."""


def ranked_moves(
    scores: NDArray[np.float64], stalled: NDArray[np.float64], own: NDArray[np.float64]
) -> NDArray[np.intp]:
    """A face's entries (as :meth:`FaceGait.moves` gives them, each (m,)) in the gait's
    order of preference: its own choice first, then the others that have not stalled by
    their lookahead progress, the stalled ones last, (m,) entry indices."""
    return np.lexsort((-scores, stalled, -own)).astype(np.intp)


def entry_of_rank(order: NDArray[np.intp], rank: int) -> int:
    """The face's entry that rank ``rank`` (modulo the face's count) names in ``order``
    (:func:`ranked_moves`)."""
    return int(order[int(rank) % len(order)])


def check_tempos(gait: FaceGait, tempos: Sequence[Sequence[int]] | None) -> tuple[Tempo, ...]:
    """``tempos`` as (hold, settle) pairs of control steps where ``gait`` can run them
    (whole numbers, the hold at least 1 and the ramp's steps, the settle at least 0);
    ValueError in one line naming the first that is not."""
    checked = []
    for tempo in tempos or ():
        pair = tuple(tempo)
        if (
            len(pair) != 2
            or not all(isinstance(k, (int, np.integer)) and not isinstance(k, bool) for k in pair)
            or not gait.runs(*pair)
        ):
            raise ValueError(
                f"tempo {tempo!r}: a tempo is (hold, settle) control steps, whole numbers, "
                f"the hold at least {gait.least_hold} (the gait's ramp), the settle >= 0"
            )
        checked.append((int(pair[0]), int(pair[1])))
    return tuple(checked)


def check_ranks(gait: FaceGait, ranks: int | None) -> int:
    """How many of ``gait``'s ranks a choice picks among: ``ranks``, 1 to the most
    entries a face has, or (None) that most; ValueError in one line otherwise."""
    if ranks is None:
        return gait.most_moves
    if (
        isinstance(ranks, bool)
        or not isinstance(ranks, (int, np.integer))
        or not (1 <= ranks <= gait.most_moves)
    ):
        raise ValueError(f"ranks must be a whole number from 1 to {gait.most_moves} (the most "
                         f"entries a face of the gait has), got {ranks!r}")  # fmt: skip
    return int(ranks)


def period_choice(
    order: NDArray[np.intp], action: int, ranks: int, tempos: Sequence[Tempo]
) -> PeriodChoice:
    """The face's entry and the period's tempo that ``action`` names: rank
    ``action % ranks`` in ``order`` (:func:`ranked_moves`), tempo ``action // ranks`` of
    the gait's own (0, None) followed by ``tempos``."""
    tempo_index, rank = divmod(int(action), ranks)
    return entry_of_rank(order, rank), (None, *tempos)[tempo_index]


def move_features(
    gait: FaceGait, observation: NDArray[np.float32], most: int
) -> tuple[NDArray[np.float32], NDArray[np.intp]]:
    """The move part of :class:`MoveChoice`'s observation, (4 * ``most``,), and the
    support face's entries in the gait's order (:func:`ranked_moves`), (m,). For each
    entry in that order, padded to ``most``: the lookahead progress (m), 1 where the
    entry exists, 1 where it stalled, 1 for the gait's own choice (the first)."""
    scores, stalled, own = gait.moves(observation)
    order = ranked_moves(scores, stalled, own)
    shown = order[:most]
    k = len(shown)
    out = np.zeros((MOVE_FEATURES, most), dtype=np.float32)
    out[0, :k] = np.clip(scores[shown], -_MOST_PROGRESS, _MOST_PROGRESS)
    out[1, :k] = 1.0
    out[2, :k] = stalled[shown]
    out[3, :k] = own[shown]
    return out.ravel(), order


def observe_moves(
    gait: FaceGait, observation: NDArray[np.float32], most: int
) -> tuple[NDArray[np.float32], NDArray[np.intp]]:
    """:class:`MoveChoice`'s observation: the env's ``observation`` (o,) followed by
    :func:`move_features`, (o + 4 * ``most``,); and the face's entries in rank order."""
    moves, order = move_features(gait, observation, most)
    return np.concatenate([observation, moves]).astype(np.float32), order


class MovePolicy:
    """A policy of :class:`MoveChoice`'s observations and actions driving an env with
    absolute actions, one control step at a time: as each gait period begins, ``pick``
    ranks the support face's entries from :func:`observe_moves`'s observation, and the
    gait runs the entry of that rank for the period.

    Args:
        gait: the steering gait the policy was trained on (its own instance: it keeps
            the period under way and the moves stalled).
        pick: the trained policy, (o + 4 * most,) observation to an action of
            :class:`MoveChoice` (a rank, and with ``tempos`` a tempo).
        tempos, ranks: what it was trained with (:class:`MoveChoice`'s).
    """

    def __init__(
        self,
        gait: FaceGait,
        pick: Callable[[NDArray[np.float32]], int],
        tempos: Sequence[Sequence[int]] | None = None,
        ranks: int | None = None,
    ) -> None:
        self.gait, self.pick = gait, pick
        self.most = gait.most_moves
        self.tempos = check_tempos(gait, tempos)
        self.ranks = check_ranks(gait, ranks)
        gait.chooser = self._choose

    def _choose(self, observation: NDArray[np.float32]) -> PeriodChoice:
        seen, order = observe_moves(self.gait, observation, self.most)
        return period_choice(order, self.pick(seen), self.ranks, self.tempos)

    def __call__(self, observation: NDArray[np.float32]) -> NDArray[np.float32]:
        """The command for this control step, (m,) in [-1, 1]."""
        return self.gait(observation)

    def reset(self, _seed: int | None = None) -> None:
        """Before an episode: no period under way, no move stalled."""
        self.gait.reset()


class MoveChoice(
    gym.Wrapper[NDArray[np.float32], np.int64, NDArray[np.float32], NDArray[np.float32]],
    gym.utils.RecordConstructorArgs,
):
    """A policy's action picks the support face's steering-gait entry; a step is a
    whole gait period.

    Args:
        env: a simulated or robot env of this package with absolute actions.
        gait: the robot's steering gait's name (a gait with several entries a face).
        tempos: (hold, settle) control steps a period may also take, beside the gait's
            own (see the module's docstring); None: the gait's own alone.
        ranks: how many of the gait's ranks a choice picks among, 1 to the most any
            face has (the default, None); 1: the gait's own move, the tempo chosen.
    """

    def __init__(
        self,
        env: gym.Env[Any, Any],
        gait: str = "steer",
        tempos: Sequence[Sequence[int]] | None = None,
        ranks: int | None = None,
    ) -> None:
        # gym.make can remake it
        gym.utils.RecordConstructorArgs.__init__(self, gait=gait, tempos=tempos, ranks=ranks)
        gym.Wrapper.__init__(self, env)
        inner: TensegrityEnv = env.unwrapped  # type: ignore[assignment]
        if getattr(inner, "action_base", None) is not None:
            raise ValueError("MoveChoice: the env has residual actions; make it without "
                             "residual_gait (the moves are the gait's own)")  # fmt: skip
        self.gait = FaceGait(inner.backend.description, inner.task, gait=gait)
        if not self.gait.steers:
            raise ValueError(
                f"MoveChoice: the gait {gait!r} of {inner.backend.description.name} has one "
                "entry a face: there is nothing to choose (give a steering gait)"
            )
        self.most = self.gait.most_moves
        self.tempos = check_tempos(self.gait, tempos)
        self.ranks = check_ranks(self.gait, ranks)
        self.action_space = spaces.Discrete(self.ranks * (1 + len(self.tempos)))
        base = env.observation_space
        assert isinstance(base, spaces.Box)
        low = np.concatenate([base.low, np.repeat([-_MOST_PROGRESS, 0, 0, 0], self.most)])
        high = np.concatenate([base.high, np.repeat([_MOST_PROGRESS, 1, 1, 1], self.most)])
        self.observation_space = spaces.Box(low.astype(np.float32), high.astype(np.float32))
        self._last: NDArray[np.float32] | None = None
        self._order: NDArray[np.intp] = np.zeros(0, dtype=np.intp)
        """The last observation's face entries in the gait's order."""

    def _observed(self, observation: NDArray[np.float32]) -> NDArray[np.float32]:
        self._last = observation
        seen, self._order = observe_moves(self.gait, observation, self.most)
        return seen

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[NDArray[np.float32], dict[str, Any]]:
        observation, info = self.env.reset(seed=seed, options=options)
        self.gait.reset()
        return self._observed(observation), info

    def step(
        self, action: np.int64
    ) -> tuple[NDArray[np.float32], SupportsFloat, bool, bool, dict[str, Any]]:
        """Run one gait period with the entry of the support face and the tempo that
        ``action`` names: the last observation, the period's summed reward, and the last
        step's flags and info (``info["period_steps"]``: the control steps run, fewer
        where the episode ended within the period)."""
        if self._last is None:
            raise RuntimeError("MoveChoice: call reset() before step()")
        observation, order = self._last, self._order
        entry, tempo = period_choice(order, int(action), self.ranks, self.tempos)
        self.gait.begin(observation, entry, tempo)
        total, steps = 0.0, 0
        terminated = truncated = False
        info: dict[str, Any] = {}
        beneath = cast("gym.Env[NDArray[np.float32], NDArray[np.float32]]", self.env)
        for _ in range(self.gait.period_steps if tempo is None else sum(tempo)):
            observation, reward, terminated, truncated, info = beneath.step(self.gait(observation))
            total += float(reward)
            steps += 1
            if terminated or truncated:
                break
        info["period_steps"] = steps
        return self._observed(observation), total, terminated, truncated, info
