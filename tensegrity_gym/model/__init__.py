"""Layer 0: the robot description, sample types, the estimate, protocols, kinematics."""

from tensegrity_gym.model.description import (
    PRESETS,
    DescriptionError,
    RobotDescription,
    load_robot,
)
from tensegrity_gym.model.estimate import Estimate
from tensegrity_gym.model.protocols import Backend, Estimator, SensorCalibration, StepResult
from tensegrity_gym.model.samples import (
    AhrsSample,
    CableLengthSample,
    ContactSample,
    EncoderSample,
    GroundTruth,
    ImuSample,
    RgbdFrame,
    Sample,
    UwbRangeSample,
)

__all__ = [
    "PRESETS",
    "AhrsSample",
    "Backend",
    "CableLengthSample",
    "ContactSample",
    "DescriptionError",
    "EncoderSample",
    "Estimate",
    "Estimator",
    "GroundTruth",
    "ImuSample",
    "RgbdFrame",
    "RobotDescription",
    "Sample",
    "SensorCalibration",
    "StepResult",
    "UwbRangeSample",
    "load_robot",
]
