"""A recorded bag behind the :class:`Backend` protocol: a run plays back as if it were live.

The env and the estimator see the same samples, at the same times, as when the run was
recorded (less those of a damaged chunk, which are missing from their period; the
period's ``info["bag_lost"]`` says so). The commands are the bag's: the targets the env
passes to :meth:`step` are ignored (a warning says so once), and each
:class:`StepResult` carries the recorded command, which the env hands to the estimator.
The last period has ``ended`` set, which ends the episode (truncated).
Times are seconds from the bag's clock origin (:attr:`ReplayBackend.clock_origin_ns`,
its first log time floored to a whole second), ``info`` times included.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

import numpy as np

from hardware.bag.kinds import sample_kinds_of_topics
from hardware.bag.reader import BagReader
from tensegrity_gym.model.protocols import StepResult
from tensegrity_gym.model.samples import EncoderSample, RgbdFrame

if TYPE_CHECKING:
    from collections.abc import Iterator
    from pathlib import Path

    from numpy.typing import NDArray

    from hardware.bag.reader import BagPeriod
    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.protocols import ReadyCheck, SensorCalibration, UwbCalibration
    from tensegrity_gym.model.samples import GroundTruth

__all__ = ["ReplayBackend"]

log = logging.getLogger(__name__)


class ReplayBackend:
    """Plays a bag back one control period per :meth:`step`.

    Args:
        path: the bag (see :class:`BagReader`).
        description: the robot, for a bag without ``/robot_description``.
        strict: raise on any bad message instead of skipping and counting it.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        description: RobotDescription | None = None,
        strict: bool = False,
    ) -> None:
        self.reader = BagReader(path, description=description, strict=strict)
        try:
            self.reader.require_commands("replaying it")
        except BaseException:
            self.reader.close()
            raise
        self.description = self.reader.description
        self.control_period = self.reader.control_period
        self._periods: Iterator[BagPeriod] | None = None
        self._next: BagPeriod | None = None
        self._truth: GroundTruth | None = None
        self.uwb_calibration: UwbCalibration | None = None
        """Anchors and offsets that replace the bag's (``estimate --calibration``)."""
        self._frame: RgbdFrame | None = None
        self._warned = False
        self.steps_taken = 0
        self.out_of_range: dict[str, int] = {}
        """Recorded commands and encoder readings outside the motors' range, counted
        (they are played as recorded: the robot did get or report them)."""

    @property
    def calibration(self) -> SensorCalibration:
        """The bag's, or :attr:`uwb_calibration`'s anchors and offsets where set (an
        estimator re-run with another calibration)."""
        own = self.reader.calibration
        return own if self.uwb_calibration is None else self.uwb_calibration.applied_to(own)

    @property
    def clock_origin_ns(self) -> int:
        """Robot-clock ns (the bag's log time) of sample time 0: the bag's first log time
        floored to a whole second."""
        return self.reader.clock_origin_ns

    @property
    def next_command(self) -> NDArray[np.float64] | None:
        """The recorded command :meth:`step` will play next (None at the bag's end)."""
        return None if self._next is None else self._next.command

    @property
    def steps_total(self) -> int | None:
        """Control periods after the start, where the bag's index says."""
        return self.reader.command_count

    def _advance(self) -> BagPeriod | None:
        assert self._periods is not None
        return next(self._periods, None)

    def _saw(self, period: BagPeriod) -> None:
        self._truth = period.truth  # None for a period without ground truth: none is known
        if period.command is not None:
            self._count_out_of_range("command", period.command)
        for s in period.samples:
            if isinstance(s, RgbdFrame):
                self._frame = s
            elif isinstance(s, EncoderSample):
                self._count_out_of_range("encoder", s.rest_lengths)

    def _count_out_of_range(self, what: str, rest_lengths: NDArray[np.float64]) -> None:
        outside = self.description.outside_motor_range(rest_lengths, reading=what == "encoder")
        if outside:
            self.out_of_range[what] = self.out_of_range.get(what, 0) + outside

    def reset(self, rng: np.random.Generator, *, ready: ReadyCheck | None = None) -> StepResult:
        """Start again from the beginning of the bag (``rng`` is not used)."""
        self._periods = self.reader.periods()
        self._truth = self._frame = None
        self.steps_taken = 0
        self.out_of_range = {}
        start = self._advance()
        assert start is not None  # periods() always yields the start period
        self._saw(start)
        self._next = self._advance()
        return StepResult(start.samples, info=self._info(start), ended=self._next is None)

    def _info(self, period: BagPeriod) -> dict[str, Any]:
        """``bag_time`` (s): the period's end; ``bag_skipped``: the reader's skip counts
        so far; ``bag_lost``: damaged chunks within the period (their messages are
        simply missing), as :meth:`LostSpan.as_dict` with ``start_s`` and ``end_s`` in
        sample time; ``bag_out_of_range``: commanded and measured rest lengths outside
        the motors' range so far, by kind."""
        seconds = self.reader.codec.seconds
        lost = [
            {**span.as_dict(), "start_s": seconds(span.start_ns), "end_s": seconds(span.end_ns)}
            for span in period.lost
        ]
        return {
            "bag_time": period.t_end,
            "bag_skipped": dict(self.reader.skipped),
            "bag_lost": lost,
            "bag_out_of_range": dict(self.out_of_range),
        }

    def step(self, targets: NDArray[np.float64]) -> StepResult:
        if self._periods is None:
            raise RuntimeError("call reset() before step()")
        period = self._next
        if period is None:
            raise RuntimeError(
                f"{self.reader.path}: the bag ended after {self.steps_taken} steps; call reset()"
            )
        command = period.command
        assert command is not None  # only the start period has none
        asked = np.asarray(targets, dtype=np.float64)
        if not self._warned and (asked.shape != command.shape or not np.allclose(asked, command)):
            log.warning(
                "%s: replaying the bag's recorded commands; the actions passed to step() "
                "are ignored",
                self.reader.path,
            )
            self._warned = True
        self._saw(period)
        self._next = self._advance()
        self.steps_taken += 1
        return StepResult(
            period.samples,
            info=self._info(period),
            command=command,
            ended=self._next is None,
        )

    def sample_kinds(self) -> frozenset[str]:
        """The sample kinds (and ``"ground_truth"``) the bag's topics carry."""
        return sample_kinds_of_topics(self.reader.topics, self.description)

    def ground_truth(self) -> GroundTruth | None:
        return self._truth

    def render(self, width: int, height: int) -> NDArray[np.uint8]:
        """The latest camera frame, or a top view of the true rods, (height, width, 3)."""
        if self._frame is not None:
            rgb = self._frame.rgb
            rows = np.arange(height) * rgb.shape[0] // height
            cols = np.arange(width) * rgb.shape[1] // width
            return np.ascontiguousarray(rgb[rows][:, cols])
        image = np.zeros((height, width, 3), dtype=np.uint8)
        if self._truth is None:
            return image
        x = self._truth.node_positions[:, :2]
        centre = x.mean(axis=0)
        scale = 0.4 * min(width, height) / max(self.description.characteristic_length, 1e-6)
        for k, (i, j) in enumerate(self.description.rod_nodes):
            colour = np.array([(200, 60, 60), (60, 200, 60), (60, 60, 220)][k % 3], np.uint8)
            for s in np.linspace(0.0, 1.0, 200):
                p = (1 - s) * x[i] + s * x[j] - centre
                u = int(width / 2 + scale * p[0])
                v = int(height / 2 - scale * p[1])
                if 0 <= u < width and 0 <= v < height:
                    image[v, u] = colour
        return image

    def stop(self) -> None:
        """Nothing to hold: a log cannot be moved."""

    def close(self) -> None:
        self.reader.close()
