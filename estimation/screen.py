"""Screening raw samples before an estimator keeps them.

:class:`PlausibilityScreen` passes on the plausible part of each sample (by the bounds of
:mod:`estimation.plausibility`), counts what it drops by kind, and follows each sensor
stream with a :class:`StreamMonitor`: a stream that has given nothing plausible for a
while is failed, and nothing of it is passed on, plausible or not, until it has given
only plausible samples for as long again. Time is the samples' own (s), compared in
integer nanoseconds so that the verdicts do not depend on where the clock started.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

from estimation.mismatch import ChannelLimits, LimitMismatch, RateMismatch
from estimation.plausibility import Verdict
from tensegrity_gym.model.samples import (
    AhrsSample,
    CableLengthSample,
    EncoderSample,
    ImuSample,
    UwbRangeSample,
    seconds_to_ns,
)

if TYPE_CHECKING:
    from collections.abc import Callable, Sequence

    from numpy.typing import ArrayLike, NDArray

    from estimation.plausibility import PlausibilityBounds
    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.samples import Sample

__all__ = ["PlausibilityScreen", "StreamMonitor"]


class StreamMonitor:
    """Fails a stream that has given only implausible samples for ``window`` seconds, and
    restores it once it has given only plausible ones for ``window`` seconds.

    A sample that agrees with the stream's state (plausible while in use, implausible
    while failed) ends any run toward a change; silence is no evidence either way.
    """

    def __init__(self, window: float) -> None:
        self.window = float(window)
        self._window_ns = seconds_to_ns(self.window)
        self._failed: set[str] = set()
        self._since: dict[str, int] = {}
        """Per stream, the time (ns) of the first sample of the current run that disagrees."""

    def observe(self, stream: str, t: float, plausible: bool) -> bool:
        """Record one sample of ``stream`` at ``t`` (s); True if the stream is in use."""
        failed = stream in self._failed
        if plausible != failed:
            self._since.pop(stream, None)
            return not failed
        t_ns = seconds_to_ns(t)
        start = self._since.setdefault(stream, t_ns)
        if t_ns - start >= self._window_ns:
            del self._since[stream]
            if failed:
                self._failed.discard(stream)
            else:
                self._failed.add(stream)
            failed = not failed
        return not failed

    def observe_many(
        self, stream: str, times: NDArray[np.float64], plausible: NDArray[np.bool_]
    ) -> NDArray[np.bool_]:
        """:meth:`observe` each of (k,) samples in order; (k,) True where in use."""
        if stream not in self._failed and plausible.all():
            self._since.pop(stream, None)  # the common case, at once
            return np.ones(len(times), dtype=bool)
        return np.array(
            [
                self.observe(stream, float(t), bool(p))
                for t, p in zip(times, plausible, strict=True)
            ],
            dtype=bool,
        )

    @property
    def failed(self) -> tuple[str, ...]:
        """The failed streams, sorted."""
        return tuple(sorted(self._failed))


def _vector(values: ArrayLike, width: int) -> NDArray[np.float64]:
    """``values`` as a (width,) vector, or NaN where it is of another size."""
    x = np.asarray(values, dtype=np.float64).reshape(-1)
    return x if x.shape == (width,) else np.full(width, np.nan)


def _stack(rows: Sequence[ArrayLike], width: int) -> NDArray[np.float64]:
    """(k, width): one row a reading, NaN rows for readings of another size."""
    try:
        x = np.asarray(rows, dtype=np.float64)
        if x.shape == (len(rows), width):
            return x
    except ValueError:  # readings of different sizes
        pass
    return np.stack([_vector(r, width) for r in rows])


MAX_STAMP_LEAD = 1.0
"""s: the gap in a batch's stamps beyond which later stamps are a clock glitch. A period
is 0.1 s and its sensors sample many times in it, so a second without a sample before
the last ones is a glitch, not a late period (a stalled link delivers seconds of samples
at once, but with no such gap among them)."""


class PlausibilityScreen:
    """Drops implausible readings and the samples of failed streams.

    Streams: ``"uwb"`` (all ranges); ``"uwb/<node>"`` and ``"uwb/anchor<k>"`` (the ranges
    of one module, judged only in rounds with some plausible range, so that a stream
    failed as a whole is not reported once per module); ``"ahrs/<rod>"`` and
    ``"imu/<rod>"`` by rod name; ``"cable_lengths"``; ``"encoders"``. Other samples
    pass untouched. A UWB round loses its implausible ranges, a cable sample has its
    implausible entries set to NaN (no reading); other samples pass whole or not at all.

    Encoder readings beyond the motor range that read as the description's error, not a
    fault (:mod:`estimation.mismatch`), are kept and counted in
    :attr:`beyond_description`; :attr:`mismatches` says which channels and by how much.

    Args:
        description: the robot (names of rods and nodes, sizes of readings).
        bounds: what is plausible.
        window: seconds of only implausible samples that fail a stream, and of only
            plausible ones that restore it.
        counts: where to count rejected readings by kind (a new dict if None).
    """

    def __init__(
        self,
        description: RobotDescription,
        bounds: PlausibilityBounds,
        window: float,
        counts: dict[str, int] | None = None,
    ) -> None:
        d = description
        self.bounds = bounds
        self.monitor = StreamMonitor(window)
        self.rejected = counts if counts is not None else {}
        self._rods = [r.name for r in d.rods]
        n_anchors = bounds.n_modules - d.n_nodes
        self._modules = [f"uwb/{n.name}" for n in d.nodes]
        self._modules += [f"uwb/anchor{k}" for k in range(n_anchors)]
        self._n_cables = d.n_cables
        self._n_actuated = d.n_actuated
        self.encoder_mismatch = LimitMismatch(ChannelLimits.motors(d))
        rates = {f"imu/{name}": d.sensors.imu.rate for name in self._rods}
        self.rate_mismatch = RateMismatch(rates | {"encoders": d.sensors.encoder.rate})
        self.beyond_description: dict[str, int] = {}
        """Readings kept although beyond the description's limits, by kind."""

    @property
    def failed(self) -> tuple[str, ...]:
        """The failed streams, sorted."""
        return self.monitor.failed

    @property
    def mismatches(self) -> tuple[str, ...]:
        """A line per channel whose readings contradict the description (kept in use):
        beyond its limits, or at another rate."""
        return self.encoder_mismatch.mismatches + self.rate_mismatch.mismatches

    def timely(self, samples: Sequence[Sample]) -> list[Sample]:
        """The samples whose stamps can be believed, in their order: not NaN or inf, and
        not beyond a gap of more than :data:`MAX_STAMP_LEAD` s among the batch's later
        half of stamps (a clock glitch that would otherwise move the estimator's clock
        far ahead, after which every real period would last nothing). A late batch that
        spans seconds without such a gap (a congested link delivering a stall's samples
        at once) is kept whole."""
        if not samples:
            return []
        stamps = [s.t for s in samples]
        if all(math.isfinite(x) for x in stamps) and max(stamps) - min(stamps) <= MAX_STAMP_LEAD:
            return list(samples)  # no gap can exceed the span: the common case, at once
        t = np.array(stamps, dtype=np.float64)
        finite = np.isfinite(t)
        self._count("stamp_not_finite", int(np.count_nonzero(~finite)))
        if not finite.any():
            return []
        ahead = np.zeros_like(finite)
        ordered = np.sort(t[finite])
        gaps = np.flatnonzero(
            (np.diff(ordered) > MAX_STAMP_LEAD) & (ordered[:-1] >= np.median(ordered))
        )
        if len(gaps):
            ahead[finite] = t[finite] > ordered[gaps[0]]
        self._count("stamp_in_future", int(np.count_nonzero(ahead)))
        keep = finite & ~ahead
        return [s for s, k in zip(samples, keep, strict=True) if k]

    def screen(self, samples: Sequence[Sample]) -> list[Sample]:
        """The samples to use, in their order (their stamps already :meth:`timely`)."""
        out: list[Sample | None] = list(samples)
        where: dict[type, list[int]] = {}
        for i, s in enumerate(samples):
            where.setdefault(type(s), []).append(i)
        # IMU, AHRS and encoder readings come many a period: judged as one batch each.
        batched: tuple[tuple[type, Callable[[list[Any]], list[bool]]], ...] = (
            (ImuSample, self._imu),
            (AhrsSample, self._ahrs),
            (EncoderSample, self._encoders),
        )
        for kind, judge in batched:
            if kind in where:
                use = judge([samples[i] for i in where[kind]])
                for i, u in zip(where[kind], use, strict=True):
                    out[i] = samples[i] if u else None
        for i in where.get(UwbRangeSample, []):
            out[i] = self._round(samples[i])  # type: ignore[arg-type]
        for i in where.get(CableLengthSample, []):
            out[i] = self._cables(samples[i])  # type: ignore[arg-type]
        return [s for s in out if s is not None]

    def _count(self, kind: str, n: int) -> None:
        if n:
            self.rejected[kind] = self.rejected.get(kind, 0) + n

    def _count_verdict(self, verdict: Verdict, among: NDArray[np.bool_] | None = None) -> None:
        for kind, mask in verdict.reasons.items():
            self._count(kind, int(np.count_nonzero(mask if among is None else mask & among)))

    def _per_rod(
        self, samples: Sequence[ImuSample | AhrsSample], verdict: Verdict, prefix: str
    ) -> list[bool]:
        """Count and monitor the per-rod streams ``prefix/<rod>``; True for samples to use."""
        rods = np.array([s.rod for s in samples], dtype=np.intp)
        valid = (rods >= 0) & (rods < len(self._rods))
        self._count(f"{prefix}_bad_rod", int(np.count_nonzero(~valid)))
        self._count_verdict(verdict, valid)
        use = verdict.plausible & valid
        times = np.array([s.t for s in samples], dtype=np.float64)
        for rod in sorted({r for r in rods.tolist() if 0 <= r < len(self._rods)}):
            mine = rods == rod
            stream = f"{prefix}/{self._rods[rod]}"
            self.rate_mismatch.accept(stream, times[mine])
            use[mine] &= self.monitor.observe_many(stream, times[mine], verdict.plausible[mine])
        return list(use.tolist())

    def _imu(self, samples: list[ImuSample]) -> list[bool]:
        accel = _stack([s.accel for s in samples], 3)
        gyro = _stack([s.gyro for s in samples], 3)
        return self._per_rod(samples, self.bounds.imu(accel, gyro), "imu")

    def _ahrs(self, samples: list[AhrsSample]) -> list[bool]:
        return self._per_rod(
            samples, self.bounds.ahrs(_stack([s.quaternion for s in samples], 4)), "ahrs"
        )

    def _encoders(self, samples: list[EncoderSample]) -> list[bool]:
        x = _stack([s.rest_lengths for s in samples], self._n_actuated)
        times = np.array([s.t for s in samples], dtype=np.float64)
        verdict = self.bounds.encoders(x)
        self.rate_mismatch.accept("encoders", times)
        if "encoder_out_of_range" in verdict.reasons:
            verdict = self._beyond_description(times, x, verdict)
        self._count_verdict(verdict)
        use = self.monitor.observe_many("encoders", times, verdict.plausible) & verdict.plausible
        self.encoder_mismatch.accept(times[use], x[use])
        return list(use.tolist())

    def _beyond_description(
        self, times: NDArray[np.float64], x: NDArray[np.float64], verdict: Verdict
    ) -> Verdict:
        """``verdict`` with the rows out of range only by a description mismatch made
        plausible (counted in :attr:`beyond_description` under ``"encoder"``)."""
        b = self.bounds
        beyond = (x < b.rest_length_min) | (x > b.rest_length_max)
        mismatch = self.encoder_mismatch.judge(times, x, beyond)
        out = verdict.reasons["encoder_out_of_range"]
        kept = out & ~(beyond & ~mismatch).any(axis=1)
        n = int(np.count_nonzero(kept))
        self.beyond_description["encoder"] = self.beyond_description.get("encoder", 0) + n
        reasons = dict(verdict.reasons, encoder_out_of_range=out & ~kept)
        if not reasons["encoder_out_of_range"].any():
            del reasons["encoder_out_of_range"]
        return Verdict(verdict.plausible | kept, reasons)

    def _cables(self, sample: CableLengthSample) -> CableLengthSample | None:
        x = np.asarray(sample.lengths, dtype=np.float64).reshape(-1)
        if x.shape != (self._n_cables,):
            self._count("cable_wrong_size", 1)
            return None
        verdict = self.bounds.cables(x)
        self._count_verdict(verdict)
        present = ~np.isnan(x)
        if not present.any():
            return sample  # no reading at all: no evidence either way
        ok = verdict.plausible
        if not (self.monitor.observe("cable_lengths", sample.t, bool(ok.any())) and ok.any()):
            return None
        if np.array_equal(ok, present):
            return sample
        return CableLengthSample(sample.t, np.where(ok, x, np.nan))

    def _round(self, sample: UwbRangeSample) -> UwbRangeSample | None:
        pairs = np.asarray(sample.pairs, dtype=np.intp)
        ranges = np.asarray(sample.ranges, dtype=np.float64).reshape(-1)
        times = np.asarray(sample.times, dtype=np.float64).reshape(-1)
        if pairs.size != 2 * ranges.size or times.size != ranges.size:
            self._count("uwb_malformed_round", 1)
            return None
        pairs = pairs.reshape(-1, 2)
        verdict = self.bounds.uwb(pairs, ranges)
        self._count_verdict(verdict)
        ok = verdict.plausible
        if not (self.monitor.observe("uwb", sample.t, bool(ok.any())) and ok.any()):
            return None
        keep = ok & self._modules_in_use(sample.t, pairs, ok)
        if keep.all():
            return sample
        if not keep.any():
            return None
        return UwbRangeSample(sample.t, times[keep], pairs[keep], ranges[keep])

    def _modules_in_use(
        self, t: float, pairs: NDArray[np.intp], plausible: NDArray[np.bool_]
    ) -> NDArray[np.bool_]:
        """Monitor each module of a round; (k,) True where both modules are in use."""
        n = len(self._modules)
        valid = np.asarray(((pairs >= 0) & (pairs < n)).all(axis=1))
        flat = pairs[valid].ravel()
        seen = np.bincount(flat, minlength=n) > 0
        good = np.bincount(flat, weights=np.repeat(plausible[valid], 2), minlength=n) > 0
        in_use = np.ones(n, dtype=bool)
        for m in np.flatnonzero(seen):
            in_use[m] = self.monitor.observe(self._modules[m], t, bool(good[m]))
        safe = np.where(valid[:, None], pairs, 0)
        return np.asarray(valid & in_use[safe].all(axis=1))
