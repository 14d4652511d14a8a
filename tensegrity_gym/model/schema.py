"""The robot description's YAML, as it is written: pydantic models of its sections.

The models check what one field alone can say (its type, its range, the keys a section
may have) and give the file's JSON Schema (:func:`description_schema`, committed as
``assets/robot_description.schema.json`` for editors). What needs several fields (names
that refer to nodes, rods and cables, rods that assemble, motor ranges that hold the
rest lengths) :mod:`tensegrity_gym.model.description` checks after them, where it builds
its dataclasses. :func:`error_field` turns pydantic's first error into the field's
dotted path and a one-line message, the words the description's errors use.

Units as in the description: SI, world frame z up.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Annotated, Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StrictBool,
    StrictFloat,
    StrictInt,
    StrictStr,
    ValidatorFunctionWrapHandler,
    WrapValidator,
)
from pydantic_core import PydanticCustomError

if TYPE_CHECKING:
    from pydantic_core import ErrorDetails

__all__ = [
    "ACCEL_FULL_SCALE",
    "DISPLAY_NAME_PATTERN",
    "GAIT_NAME_PATTERN",
    "GYRO_FULL_SCALE",
    "CableLengthSection",
    "CableSection",
    "CameraSection",
    "ContactSection",
    "EncoderSection",
    "GaitFaceSection",
    "GaitSection",
    "GroundSection",
    "ImuSection",
    "MotorSection",
    "NodeSection",
    "RobotSection",
    "RodSection",
    "SensorsSection",
    "UwbSection",
    "description_schema",
    "error_field",
]

DISPLAY_NAME_PATTERN = r"^[A-Z][A-Za-z0-9]*$"
GAIT_NAME_PATTERN = r"^[a-z][a-z0-9_-]*$"
_PATTERN_WORDS = {
    DISPLAY_NAME_PATTERN: "a CamelCase word such as 'ThreeBar'",
    GAIT_NAME_PATTERN: "a lower-case word such as 'left'",
}

ACCEL_FULL_SCALE = 16.0 * 9.80665
"""m/s^2: 16 g, the widest range of common MEMS IMUs (``ImuConfig``'s default)."""
GYRO_FULL_SCALE = math.radians(2000.0)
"""rad/s: 2000 deg/s (``ImuConfig``'s default)."""


def _exactly(n: int, what: str) -> WrapValidator:
    """A list of exactly ``n`` entries, or the error "expected n {what}, got k"."""

    def check(value: Any, handler: ValidatorFunctionWrapHandler) -> Any:
        if isinstance(value, (list, tuple)) and len(value) != n:
            raise PydanticCustomError(
                "exact_length",
                "expected {n} {what}, got {actual}",
                {"n": n, "what": what, "actual": len(value)},
            )
        return handler(value)

    return WrapValidator(check)


Number = Annotated[StrictFloat, Field(allow_inf_nan=False)]
Positive = Annotated[StrictFloat, Field(gt=0, allow_inf_nan=False)]
NonNegative = Annotated[StrictFloat, Field(ge=0, allow_inf_nan=False)]
Fraction = Annotated[StrictFloat, Field(ge=0, lt=1, allow_inf_nan=False)]
PositiveInt = Annotated[StrictInt, Field(gt=0)]
Name = Annotated[StrictStr, Field(min_length=1)]
Names = Annotated[tuple[Name, ...], Field(min_length=1)]
"""Distinct names (the description checks that each names something, once)."""
NodePair = Annotated[tuple[Name, ...], Field(min_length=2, max_length=2), _exactly(2, "node names")]
Face = Annotated[tuple[Name, ...], Field(min_length=3, max_length=3), _exactly(3, "node names")]
Vector3 = Annotated[tuple[Number, ...], Field(min_length=3, max_length=3), _exactly(3, "numbers")]
GaitName = Annotated[StrictStr, Field(pattern=GAIT_NAME_PATTERN)]


class _Section(BaseModel):
    """A YAML mapping: no key beyond its fields, immutable once read."""

    model_config = ConfigDict(extra="forbid", frozen=True, use_attribute_docstrings=True)


class GroundSection(_Section):
    """Contact with the ground: friction coefficients, rolling and spinning ones in m."""

    lateral_friction: NonNegative
    rolling_friction: NonNegative
    """Rolling resistance (m): the torque is this times the normal force."""
    spinning_friction: NonNegative
    """Resistance to spinning about the contact normal (m)."""
    restitution: NonNegative


class NodeSection(_Section):
    """A node: an endcap's centre."""

    name: Name
    position: Vector3
    """Position (m) in the resting pose the robot is built in."""


class RodSection(_Section):
    """A rigid rod between two nodes, with an endcap at each."""

    name: Name
    nodes: NodePair
    """The two nodes (endcap centres) it joins, by name."""
    length: Positive
    """Distance between the endcap centres (m)."""
    radius: Positive
    endcap_radius: Positive
    mass: Positive
    color: Annotated[
        tuple[NonNegative, ...], Field(min_length=4, max_length=4), _exactly(4, "numbers")
    ]
    """RGBA."""


class MotorSection(_Section):
    """The motor that sets an actuated cable's rest length (m)."""

    min_rest_length: Positive
    max_rest_length: Positive
    max_speed: Positive
    """Largest rate of change of the rest length (m/s)."""
    min_tension: Positive | None = None
    """N: the tension the motor keeps on its cable, reeling in slack; none: it may go slack."""


class CableSection(_Section):
    """An elastic cable between nodes of two rods."""

    name: Name
    nodes: NodePair
    """The two nodes it joins, on different rods, by name."""
    stiffness: Positive
    """N/m."""
    damping: NonNegative
    """N s/m."""
    rest_length: Positive
    """Initial (and, for a passive cable, fixed) rest length (m)."""
    actuated: StrictBool
    motor: MotorSection | None = None
    """An actuated cable's motor (and only an actuated cable's)."""


class ImuSection(_Section):
    """Each rod's IMU (and AHRS), at its centre; noises are standard deviations."""

    rate: Positive
    mount: Literal["rod_centre"]
    accel_noise: NonNegative
    gyro_noise: NonNegative
    accel_bias: NonNegative
    gyro_bias: NonNegative
    mag_noise: NonNegative
    magnetic_field: Vector3
    """Earth field in the world frame (T)."""
    ahrs_gain: Positive
    accel_full_scale: Positive = ACCEL_FULL_SCALE
    gyro_full_scale: Positive = GYRO_FULL_SCALE
    rods: Names | None = None
    """The rods that carry one, by name; none: every rod."""


class EncoderSection(_Section):
    """The motors' encoders: the rest lengths, quantised (m)."""

    rate: Positive
    resolution: NonNegative


class CableLengthSection(_Section):
    """The cables' length sensors (m)."""

    rate: Positive
    noise: NonNegative
    slack_bias: NonNegative


class UwbSection(_Section):
    """The ultra-wideband ranging modules at the endcaps, and the fixed anchors (m)."""

    rate: Positive
    packet_spacing: Positive
    module_offset: NonNegative
    timestamp_noise: NonNegative
    clock_drift_ppm: NonNegative
    offset_mean: Number
    offset_std: NonNegative
    reject_fraction: Annotated[
        tuple[Fraction, ...], Field(min_length=2, max_length=2), _exactly(2, "numbers")
    ]
    """Low and high share of packets rejected as non-line-of-sight."""
    anchors: tuple[Vector3, ...]


class ContactSection(_Section):
    """The endcaps' ground contact sensors."""

    rate: Positive
    threshold: NonNegative


class CameraSection(_Section):
    """A fixed RGB-D camera watching the robot."""

    position: Vector3
    target: Vector3
    up: Vector3
    width: PositiveInt
    height: PositiveInt
    vertical_fov: Positive
    """Degrees."""
    near: Positive
    far: Positive
    rate: Positive
    depth_noise: NonNegative
    depth_noise_quadratic: NonNegative
    flying_pixels: Annotated[StrictFloat, Field(ge=0, le=1, allow_inf_nan=False)] = 0.0
    """Share of a depth edge's near pixels that read between the near and the far depth."""


class SensorsSection(_Section):
    """What the robot's sensors are and how they err."""

    imu: ImuSection
    encoder: EncoderSection
    cable_length: CableLengthSection
    uwb: UwbSection
    contact: ContactSection
    camera: CameraSection


class GaitFaceSection(_Section):
    """One face of a gait's rolling cycle."""

    face: Face
    """The support face, by node names."""
    contract: Names
    """The actuated cables to contract, by name."""
    others: Literal["hold", "out"]
    move: Vector3 | None = None
    """A steering entry's CoM move (m, m) and turn (rad) over the period."""
    to: Face | None = None
    """A steering entry's face the period leaves the robot on."""


class GaitSection(_Section):
    """A face-to-face rolling gait; steps are control steps."""

    faces: Annotated[tuple[GaitFaceSection, ...], Field(min_length=1)]
    hold_steps: Annotated[StrictInt, Field(ge=1)] = 25
    settle_steps: Annotated[StrictInt, Field(ge=0)] = 10
    ramp_steps: Annotated[StrictInt, Field(ge=0)] = 0


class RobotSection(_Section):
    """A tensegrity robot for tensegrity-gym: its geometry, sensors and gaits."""

    model_config = ConfigDict(title="Robot description")

    name: Name
    display_name: Annotated[StrictStr, Field(pattern=DISPLAY_NAME_PATTERN)] | None = None
    """The name in env ids; none: ``name`` in CamelCase."""
    hardware: StrictBool = False
    gravity: NonNegative
    ground: GroundSection
    nodes: Annotated[tuple[NodeSection, ...], Field(min_length=2)]
    rods: Annotated[tuple[RodSection, ...], Field(min_length=1)]
    cables: Annotated[tuple[CableSection, ...], Field(min_length=1)]
    sensors: SensorsSection
    carries: Names | None = None
    """The sample kinds its sensors give; none: every kind."""
    gait: GaitSection | None = None
    gaits: Annotated[dict[GaitName, GaitSection], Field(min_length=1)] | None = None
    """Further gaits by name."""


def description_schema() -> dict[str, Any]:
    """The JSON Schema (draft 2020-12) of a robot description's YAML."""
    schema = RobotSection.model_json_schema()
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", **schema}


def error_field(error: ErrorDetails) -> tuple[str, str]:
    """A pydantic error as the field's dotted path (``rods[0].length``; ``""``: the
    document) and a one-line message."""
    path = ""
    loc = error["loc"]
    for k, part in enumerate(loc):
        if part == "[key]":
            continue
        # A mapping's key, not a list's index: a gait's name, a key that is no string.
        is_key = loc[k + 1 :] == ("[key]",) or (
            error["type"] == "invalid_key" and k == len(loc) - 1
        )
        if isinstance(part, int) and not is_key:
            path += f"[{part}]"
        else:
            path += f".{part}" if path else str(part)
    return path, _message(error)


def _message(error: ErrorDetails) -> str:
    """The words for pydantic's error ``error``, as the description's errors put them."""
    kind, value = error["type"], error["input"]
    ctx = error.get("ctx", {})
    got = f", got {value!r}"
    fixed = {
        "missing": "missing field",
        "extra_forbidden": "unknown field",
        "invalid_key": "unknown field",
        "model_type": f"expected a mapping, got {type(value).__name__}",
        "dict_type": f"expected a mapping, got {type(value).__name__}",
        "tuple_type": f"expected a list, got {type(value).__name__}",
        "list_type": f"expected a list, got {type(value).__name__}",
        "float_type": "expected a number" + got,
        "finite_number": "must be finite" + got,
        "int_type": "expected an integer" + got,
        "bool_type": "expected true or false" + got,
        "string_type": "expected a non-empty string" + got,
        "string_too_short": "expected a non-empty string" + got,
    }
    if kind in fixed:
        return fixed[kind]
    if kind == "greater_than":
        return ("must be positive" if ctx["gt"] == 0 else f"must exceed {ctx['gt']}") + got
    if kind == "greater_than_equal":
        return ("must not be negative" if ctx["ge"] == 0 else f"must be at least {ctx['ge']}") + got
    if kind == "less_than":
        return f"must be less than {ctx['lt']}" + got
    if kind == "literal_error":
        return f"expected {ctx['expected']}" + got
    if kind == "string_pattern_mismatch":
        pattern = ctx["pattern"]
        return f"expected {_PATTERN_WORDS.get(pattern, f'a match of {pattern}')}" + got
    if kind == "too_short":
        return f"expected at least {ctx['min_length']} entries, got {ctx['actual_length']}"
    if kind == "too_long":
        return f"expected at most {ctx['max_length']} entries, got {ctx['actual_length']}"
    if kind == "exact_length":
        return error["msg"]
    return " ".join(error["msg"].split()) + got
