"""Everything that tunes the UWB self-calibration: :class:`CalibrationConfig`."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["CalibrationConfig"]


@dataclass(frozen=True)
class CalibrationConfig:
    """Settings of :func:`~estimation.uwb_calibration.calibrate_ranges`.

    Lengths are in metres, times in seconds. The defaults suit the presets' DW1000
    model (about 3 cm of range noise, 30-70 % packet loss, 15 Hz rounds).
    """

    min_anchor_ranges: int = 4
    """The indicator alpha of Caluwaerts et al. 2016 eq. 9: a module at a sample counts only with at
    least this many anchors ranged."""
    max_samples: int = 1000
    """Samples the final solve uses at most, drawn spread over the run (the paper used
    about 400; more sharpen the anchors, which the robot's small travel leaves loose,
    at a cost linear in their number)."""
    min_samples: int = 60
    """Fewer usable samples than this (12 s of ranging at the default period) and the
    data cannot decide: CalibrationError."""
    min_pair_ranges: int = 8
    """A robot-anchor pair with fewer ranges in the solve has a doubtful offset."""
    range_sigma: float = 0.03
    """Standard deviation of one UWB range (m): scales the range residuals."""
    bar_sigma: float = 0.003
    """Standard deviation of a bar-length term (m): the rods are rigid."""
    offset_spread: float | None = 0.05
    """Expected scatter (m, standard deviation) of the pair offsets o_ij about their
    common mean, which is solved for: a prior that separates each anchor's distance
    from its offsets (see :mod:`estimation.uwb_calibration.problem`). None: eq. 9
    alone, which needs the robot to travel far compared with the anchor distances."""
    floor_sigma: float = 0.01
    """Standard deviation (m) of an endcap's height on the floor: the robot rests on it,
    which fixes the tilt the anchors' heights leave loose."""
    loss: str = "soft_l1"
    """Robust loss of ``scipy.optimize.least_squares`` for the joint solve."""
    loss_scale: float = 2.0
    """``f_scale`` of the loss, in units of ``range_sigma``: residuals beyond it count
    less than quadratically, so that multipath outliers do not pull the solution."""
    jump_threshold: float = 0.3
    """A range more than this (m) from the median of its pair's neighbouring ranges in
    time is dropped as multipath before the solve (see ``rounds.jump_outliers``)."""
    final_loss: str = "soft_l1"
    """Loss of the final solve, from the grown solution ("cauchy" redescends: an
    outlier left after the jump screen pulls it not at all, but neither do the
    larger honest residuals that fix the anchors' heights)."""
    outlier_sigmas: float = 5.0
    """A range off by more than this many robust standard deviations (and at least
    ``2 * loss_scale * range_sigma``) counts as an outlier in the statistics."""
    n_starts: int = 2
    """Starts of the solve, each from another of the run's first windows."""
    start_samples: int = 120
    """Samples of each growth stage, and of the comparison of the starts."""
    max_iterations: int = 30
    """Levenberg-Marquardt iterations of one joint solve at most."""
    floor_passes: int = 3
    """Joint solves per stage, the floor contacts re-read before each."""
    window: float = 0.4
    """Length (s) of the windows whose ranges are pooled as if the robot stood still:
    for the starting shape, and for the floor and the handedness checks. The least:
    where the data ranges too slowly for each anchor to reach several modules in it,
    it is lengthened (:mod:`~estimation.uwb_calibration.timing`)."""
    sample_period: float = 0.2
    """Samples are the UWB rounds in bins of this many seconds (3 rounds at 15 Hz): with
    30-70 % of packets lost, one round seldom has 4 anchors for a module; a few rounds
    together mostly do, while the robot moves millimetres to centimetres. A period
    shorter than a round keeps one round a sample. The least: where the data's
    ranging rate leaves too few anchors per module in it (a lab's hardware ranging
    each pair about once a second), it is lengthened to what the rate needs."""
    rate_span: float = 1.0
    """Seconds on either side of a range over which its pair's rate of change is
    fitted, to move the range to its sample's time
    (:func:`~estimation.uwb_calibration.rounds.at_sample_times`); lengthened to hold
    about three of the pair's ranges where a pair ranges slowly."""
    first_span: float = 2.0
    """Seconds of the run the solve's first growth stage spans (then 2, 4, 8 times
    that...); lengthened to 10 samples where the samples are long."""
    round_gap: float | None = None
    """Rows closer in time than this (s) belong to one UWB round; None: half the round
    period of the description's ``sensors.uwb.rate``."""
    floor_slab: float = 0.02
    """Half-width (m) of the slab of endcaps taken to touch the floor."""
    flag_ratio: float = 3.0
    """An anchor whose robust residual spread (or median) exceeds this many times the
    anchors' typical one is flagged in the verdict."""
    flag_floor: float = 0.03
    """...and exceeds this (m): a noisy but sound anchor is not flagged."""
    max_residual: float = 0.06
    """Residual spread (m, robust standard deviation) above which the verdict is doubtful."""
    check_ratio: float = 1.8
    """In a check of a calibration against later ranges (left-out residuals), an anchor
    whose residual spread exceeds this many times the others' typical one is flagged."""
    outlier_fraction: float = 0.2
    """Share of an anchor's ranges that are outliers above which it is flagged (and
    above 3 times the anchors' median share)."""
    max_hint_misfit: float = 0.1
    """RMS (m) of a floor hint's anchor heights against the calibrated anchors above
    which the verdict is doubtful."""
    max_anchor_sigma: float = 0.03
    """Predicted anchor standard error (m) above which the verdict is doubtful: the
    robot did not travel far enough across the anchors to fix them better."""

    def __post_init__(self) -> None:
        if self.min_anchor_ranges < 3:
            raise ValueError(f"min_anchor_ranges must be >= 3, got {self.min_anchor_ranges}")
        if self.n_starts < 1 or self.max_samples < 1 or self.min_samples < 1:
            raise ValueError("n_starts, max_samples and min_samples must be >= 1")
        for name in ("range_sigma", "bar_sigma", "loss_scale", "window", "floor_slab",
                     "sample_period", "first_span", "rate_span"):  # fmt: skip
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)!r}")
