"""UWB self-calibration (Caluwaerts et al. 2016 III-C): anchor positions and pair offsets from the
uncorrected ranges of a robot moving about, without any anchor measured by hand.

:func:`calibrate_ranges` takes ``(t, module_i, module_j, range)`` rows,
:func:`calibrate_samples` ``UwbRangeSample`` rounds; both return a
:class:`CalibrationResult` (anchors in the floor frame, offsets, residual statistics,
a verdict) that :meth:`~CalibrationResult.to_calibration` turns into a
``SensorCalibration``. :func:`check_calibration` tells, from later ranges, whether a
calibration still fits (an anchor moved since). :func:`save_calibration` and
:func:`load_calibration` keep one in YAML; :mod:`~estimation.uwb_calibration.trust`
tells whether a saved one may be used for a scene and its ranges.
"""

from estimation.uwb_calibration.calibrate import calibrate_ranges, calibrate_samples
from estimation.uwb_calibration.check import (
    CalibrationCheck,
    check_calibration,
    check_samples,
    fit_residuals,
)
from estimation.uwb_calibration.config import CalibrationConfig
from estimation.uwb_calibration.files import (
    CalibrationFile,
    CalibrationFileError,
    check_output_path,
    load_calibration,
    save_calibration,
)
from estimation.uwb_calibration.geometry import rigid_alignment_rms
from estimation.uwb_calibration.result import CalibrationError, CalibrationResult, ResidualStats

__all__ = [
    "CalibrationCheck",
    "CalibrationConfig",
    "CalibrationError",
    "CalibrationFile",
    "CalibrationFileError",
    "CalibrationResult",
    "ResidualStats",
    "calibrate_ranges",
    "calibrate_samples",
    "check_calibration",
    "check_output_path",
    "check_samples",
    "fit_residuals",
    "load_calibration",
    "rigid_alignment_rms",
    "save_calibration",
]
