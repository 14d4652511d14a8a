"""Scripted rolling gaits: a face-to-face table driven by the estimated state.

The robot rests on a support face (its three lowest nodes). For each face of its
rolling cycle, a table names the actuated cables to contract fully and whether the
others hold their initial rest length or are let out to their maximum. The gait holds
that command for ``hold_steps``, then returns to the initial lengths for
``settle_steps`` so the robot comes to rest on its next face, and repeats.

The tables were found by ``scripts/find_gait.py``, which searches the transitions
that carry the centre of mass furthest in one direction. Faces are sets of node
indices, fixed to the robot's body, so a table works at any heading; the rolling
direction follows the robot's orientation, not the task's goal.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.tasks.roll import RollTask

__all__ = ["GAIT_TABLES", "FaceGait"]

# face (sorted node ids) -> (actuated cable indices to contract, "hold" | "out")
GaitTable = dict[tuple[int, ...], tuple[tuple[int, ...], str]]

GAIT_TABLES: dict[str, GaitTable] = {
    "three_bar": {
        (1, 2, 5): ((0, 4, 5), "out"),
        (0, 3, 5): ((2, 3, 4), "out"),
        (1, 3, 4): ((1, 3, 5), "out"),
    },
    "superball": {
        (1, 4, 11): ((7, 8), "out"),
        (1, 3, 4): ((5, 6), "hold"),
        (5, 7, 8): ((3,), "hold"),
        (0, 2, 7): ((4, 5), "hold"),
        (2, 6, 10): ((6, 7), "out"),
        (4, 6, 10): ((6, 8), "hold"),
    },
}


class FaceGait:
    """A scripted policy that rolls the robot face to face.

    Call it with observations of a :class:`RollTask`; it returns actions in [-1, 1].
    Keeps a small state (the current face and phase); :meth:`reset` clears it.

    Args:
        description: the robot; its name selects the table unless ``table`` is given.
        task: decodes observations into node positions.
        table: a face-to-action table, overriding the preset's.
        hold_steps, settle_steps: control steps of the contraction and of the rest.
    """

    def __init__(
        self,
        description: RobotDescription,
        task: RollTask,
        *,
        table: GaitTable | None = None,
        hold_steps: int = 25,
        settle_steps: int = 10,
    ) -> None:
        if table is None:
            if description.name not in GAIT_TABLES:
                raise ValueError(
                    f"no gait table for robot {description.name!r}; "
                    f"tables exist for {sorted(GAIT_TABLES)}"
                )
            table = GAIT_TABLES[description.name]
        if hold_steps < 1 or settle_steps < 0:
            raise ValueError("hold_steps must be >= 1 and settle_steps >= 0")
        m = description.n_actuated
        for face, (cables, rest) in table.items():
            if rest not in ("hold", "out") or any(not 0 <= k < m for k in cables):
                raise ValueError(f"bad gait table entry {face}: {(cables, rest)}")
        self.table = table
        self.task = task
        self.hold_steps = hold_steps
        self.settle_steps = settle_steps
        lo, hi, _ = description.motor_limits
        rest_action = 2.0 * (description.rest_lengths[description.actuated] - lo) / (hi - lo) - 1.0
        self.hold_action = rest_action.astype(np.float32)
        self._actions = {}
        for face, (cables, rest) in table.items():
            a = self.hold_action.copy() if rest == "hold" else np.ones(m, dtype=np.float32)
            a[list(cables)] = -1.0
            self._actions[face] = a
        self.reset()

    def reset(self) -> None:
        self._phase = 0

    def support_face(self, observation: NDArray[np.float32]) -> tuple[int, ...]:
        z = self.task.decode(observation).positions[:, 2]
        return tuple(sorted(np.argsort(z, kind="stable")[:3].tolist()))

    def action_for_face(self, face: tuple[int, ...]) -> NDArray[np.float32]:
        """The table's action; for a face off the cycle, that of the most similar face."""
        if face in self._actions:
            return self._actions[face]
        nearest = max(self._actions, key=lambda f: len(set(f) & set(face)))
        return self._actions[nearest]

    def __call__(self, observation: NDArray[np.float32]) -> NDArray[np.float32]:
        period = self.hold_steps + self.settle_steps
        phase = self._phase
        self._phase = (phase + 1) % period
        if phase < self.hold_steps:
            if phase == 0:
                self._command = self.action_for_face(self.support_face(observation))
            return self._command.copy()
        return self.hold_action.copy()
