"""Readings that contradict the robot description, told apart from faulty ones.

A lab's description is never exact: its motors' ranges, its encoders' zeros are set by
hand. Readings of such a robot lie beyond the description's limits, and a screen that
drops them as implausible leaves the estimator blind (a real 3-bar whose motors read
0.067-0.197 m against a description's 0.124-0.237 m lost every encoder reading). Such a
channel is told from a faulty one by how it behaves: a description mismatch is a whole
channel beyond a limit by a bounded amount and smooth in time, moving no faster than its
motor can; a fault jumps, or reads an absurd value (negative, or further beyond a limit
than the channel's own span). :class:`LimitMismatch` judges each reading beyond its
bound so, keeps the mismatched ones in use, and says once per channel, in one line,
which part of the description the data contradicts and by how much.

Time is the samples' own (s), compared in integer nanoseconds so that the verdicts do
not depend on where the clock started.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from tensegrity_gym.model.samples import seconds_to_ns

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription

__all__ = [
    "MISMATCH_EVIDENCE",
    "RATE_EVIDENCE",
    "RATE_TOLERANCE",
    "ChannelLimits",
    "LimitMismatch",
    "RateMismatch",
]

_log = logging.getLogger(__name__)

MISMATCH_EVIDENCE = 1.0
"""s: how long a channel must have read beyond its limit, smoothly, before the mismatch
is said (a moment beyond a limit is overshoot; a second of it is the description)."""

RATE_MARGIN = 3.0
"""How much faster than its motor's top speed a channel may be seen to move between two
readings before the move counts as a jump: a motor that holds a minimum tension reels in
slack faster than it drives (2.2 times on three_bar_large's motors, seen in the
simulator), and stamps jitter."""


@dataclass(frozen=True, eq=False)
class ChannelLimits:
    """What the description says each channel of a stream may read, (m,) each."""

    names: tuple[str, ...]
    """Each channel as a message names it (``"motor 2 (cable 'c2')"``)."""
    low: NDArray[np.float64]
    """The description's lowest reading (m)."""
    high: NDArray[np.float64]
    """The description's highest reading (m)."""
    reach: NDArray[np.float64]
    """m beyond a limit a mismatched channel may read: further is absurd, a fault."""
    rate: NDArray[np.float64]
    """m/s a channel can change by at most (its motor's top speed, with a margin)."""
    tolerance: float
    """m a reading may step by at once whatever the time (resolution, noise)."""
    what: str
    """The part of the description the limits are (``"motor range"``)."""

    @classmethod
    def motors(cls, description: RobotDescription) -> ChannelLimits:
        """The encoders' limits: each actuated cable's motor range."""
        d = description
        lo, hi, speed = d.motor_limits
        names = tuple(
            f"motor {k} (cable {d.cables[int(c)].name!r})" for k, c in enumerate(d.actuated)
        )
        resolution = d.sensors.encoder.resolution
        return cls(names, lo, hi, hi - lo, RATE_MARGIN * speed, 2.0 * resolution, "motor range")


class LimitMismatch:
    """Judges the readings of one stream that lie beyond their plausible bound.

    Each channel's last reading in use is remembered; a reading beyond its bound is a
    mismatch (kept) when it is finite, no more than ``reach`` beyond the description's
    limit, not negative, and no further from that last reading than the channel can
    move in the time between; else it is a fault (dropped). A channel with no reading in
    use yet cannot jump: its first reading is judged by the reach alone.
    """

    def __init__(self, limits: ChannelLimits, evidence: float = MISMATCH_EVIDENCE) -> None:
        self.limits = limits
        m = len(limits.names)
        self._last = np.full(m, np.nan)
        self._last_ns = np.zeros(m, dtype=np.int64)
        self._seen_low = np.full(m, np.inf)
        self._seen_high = np.full(m, -np.inf)
        self._first_ns: dict[int, int] = {}
        """Channel -> stamp (ns) of its first mismatched reading."""
        self._evidence_ns = seconds_to_ns(evidence)
        self._said: dict[int, str] = {}

    @property
    def mismatches(self) -> tuple[str, ...]:
        """A line per channel found to contradict the description (said or not yet),
        with the readings seen so far."""
        return tuple(self._line(k) for k in sorted(self._first_ns))

    def judge(
        self, times: NDArray[np.float64], readings: NDArray[np.float64], beyond: NDArray[np.bool_]
    ) -> NDArray[np.bool_]:
        """(k,) stamps (s), (k, m) readings, (k, m) True where beyond the plausible
        bound: (k, m) True where a reading beyond is a mismatch to keep. Rows in time
        order; the caller marks as in use the rows it keeps (:meth:`accept`)."""
        mismatch = np.zeros_like(beyond)
        if not beyond.any():
            return mismatch
        lim = self.limits
        absurd = ~np.isfinite(readings) | (readings < 0.0)
        absurd |= (readings < lim.low - lim.reach) | (readings > lim.high + lim.reach)
        stamps = [seconds_to_ns(float(t)) for t in times]
        last, last_ns = self._last.copy(), self._last_ns.copy()
        for i, t_ns in enumerate(stamps):
            for k in np.flatnonzero(beyond[i]):
                step = abs(readings[i, k] - last[k])
                reach = lim.rate[k] * max(t_ns - last_ns[k], 0) * 1e-9 + lim.tolerance
                if not absurd[i, k] and (np.isnan(last[k]) or step <= reach):
                    mismatch[i, k] = True
                    last[k] = readings[i, k]
                    self._first_ns.setdefault(int(k), t_ns)
                    self._say(int(k), t_ns)
                # A fault's time counts too: a channel stuck where it jumped to stays a
                # jump away from its last reading in use, however long it stays there.
                last_ns[k] = self._last_ns[k] = max(int(self._last_ns[k]), t_ns)
            inside = ~beyond[i] & np.isfinite(readings[i])
            last[inside], last_ns[inside] = readings[i, inside], t_ns
        return mismatch

    def accept(self, times: NDArray[np.float64], readings: NDArray[np.float64]) -> None:
        """The (k, m) readings at (k,) stamps (s) are in use: each channel's last reading
        in use, and the range of readings seen, follow them."""
        if not len(times):
            return
        self._last[:] = readings[-1]
        self._last_ns[:] = np.maximum(self._last_ns, seconds_to_ns(float(times[-1])))
        self._seen_low = np.fmin(self._seen_low, readings.min(axis=0))
        self._seen_high = np.fmax(self._seen_high, readings.max(axis=0))
        for k in self._first_ns:
            self._say(k, int(self._last_ns[k]))

    def _say(self, k: int, t_ns: int) -> None:
        """Log channel ``k``'s mismatch once, when it has lasted :data:`MISMATCH_EVIDENCE`."""
        if k in self._said or t_ns - self._first_ns[k] < self._evidence_ns:
            return
        self._said[k] = line = self._line(k)
        _log.warning("description mismatch: %s", line)

    def _line(self, k: int) -> str:
        lim = self.limits
        low, high = self._seen_low[k], self._seen_high[k]
        seen = f"{low:.3f}-{high:.3f} m" if np.isfinite(low) else "beyond it"
        return (
            f"{lim.names[k]} reads {seen}, the description's {lim.what} is "
            f"{lim.low[k]:.3f}-{lim.high[k]:.3f} m"
        )


RATE_EVIDENCE = 200
"""Intervals between a stream's readings taken before its rate is judged."""
RATE_TOLERANCE = 0.25
"""Share by which a stream's median interval may differ from the described period."""


class RateMismatch:
    """Streams whose readings come at another rate than the description's.

    Each stream's median interval over its first :data:`RATE_EVIDENCE` intervals (a
    reading lost or a jittered stamp moves a median little) is set against the period
    its description gives; off by more than :data:`RATE_TOLERANCE`, the stream is said
    once, in one line, and kept in :attr:`mismatches` (an IMU at 100 Hz described at
    200 Hz, say: the estimators' noise densities and gap checks read the description).
    The readings stay in use. Intervals are of the samples' own stamps, in integer ns.

    Args:
        rates: Hz by stream name (``"imu/red"``, ``"encoders"``).
    """

    def __init__(self, rates: dict[str, float]) -> None:
        self.rates = dict(rates)
        self._last_ns: dict[str, int] = {}
        self._intervals: dict[str, list[int]] = {}
        self._judged: set[str] = set()
        self._lines: list[str] = []

    @property
    def mismatches(self) -> tuple[str, ...]:
        """A line per stream found at another rate, in the order found."""
        return tuple(self._lines)

    def accept(self, stream: str, times: NDArray[np.float64]) -> None:
        """Readings of ``stream`` stamped ``times`` (k,) s arrived; a stream without a
        described rate, or judged already, is not looked at."""
        if stream in self._judged or stream not in self.rates:
            return
        gaps = self._intervals.setdefault(stream, [])
        last = self._last_ns.get(stream)
        for t in times.tolist():
            t_ns = seconds_to_ns(t)
            if last is not None and t_ns > last:
                gaps.append(t_ns - last)
            if last is None or t_ns > last:
                last = t_ns
        if last is not None:
            self._last_ns[stream] = last
        if len(gaps) >= RATE_EVIDENCE:
            self._judge(stream, gaps)

    def _judge(self, stream: str, gaps: list[int]) -> None:
        self._judged.add(stream)
        del self._intervals[stream]
        median = float(np.median(gaps)) * 1e-9
        rate = self.rates[stream]
        if abs(median * rate - 1.0) > RATE_TOLERANCE:
            line = (
                f"{stream} reads every {median * 1e3:.1f} ms ({1.0 / median:.0f} Hz); the "
                f"description's rate is {rate:g} Hz"
            )
            self._lines.append(line)
            _log.warning("%s", line)
