"""The robot description: presets load with the right shape, malformed files are
rejected at load time with a message that names the file and the field."""

from __future__ import annotations

import copy
import dataclasses
import json
from importlib import resources
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest
import yaml

from tensegrity_gym.model.description import (
    PRESETS,
    DescriptionError,
    RobotDescription,
    dump_robot,
    load_robot,
    loads_robot,
    parse_robot,
    robot_document,
)

if TYPE_CHECKING:
    from collections.abc import Callable
    from pathlib import Path


def _preset_doc(name: str) -> dict[str, Any]:
    text = (resources.files("tensegrity_gym.model") / "assets" / f"{name}.yaml").read_text()
    doc = yaml.safe_load(text)
    assert isinstance(doc, dict)
    return doc


@pytest.fixture(scope="module")
def three_bar_doc() -> dict[str, Any]:
    return _preset_doc("three_bar")


# ------------------------------------------------------------------------------ presets

EXPECTED_COUNTS = {
    # name: (nodes, rods, cables, actuated, anchors)
    "three_bar": (6, 3, 9, 6, 8),
    "three_bar_large": (6, 3, 9, 6, None),
    "superball": (12, 6, 24, 12, 8),
}


def test_presets_are_the_expected_ones() -> None:
    assert set(PRESETS) == set(EXPECTED_COUNTS)


@pytest.mark.parametrize("name", PRESETS)
def test_preset_loads_with_expected_counts(name: str) -> None:
    d = load_robot(name)
    assert isinstance(d, RobotDescription)
    assert d.name == name
    assert d.source.endswith(f"{name}.yaml")
    nodes, rods, cables, actuated, anchors = EXPECTED_COUNTS[name]
    assert (d.n_nodes, d.n_rods, d.n_cables, d.n_actuated) == (nodes, rods, cables, actuated)
    if anchors is not None:
        assert d.anchors.shape == (anchors, 3)
    assert d.actuated.shape == (actuated,)
    assert d.cable_nodes.shape == (cables, 2)
    assert d.rod_nodes.shape == (rods, 2)


@pytest.mark.parametrize("name", PRESETS)
def test_preset_is_consistent(name: str) -> None:
    d = load_robot(name)
    # Every node ends exactly one rod.
    assert sorted(d.rod_nodes.ravel().tolist()) == list(range(d.n_nodes))
    for k, rod in enumerate(d.rods):
        assert d.node_rod[rod.nodes[0]] == k
        assert d.node_rod[rod.nodes[1]] == k
        gap = np.linalg.norm(np.subtract(*d.initial_positions[list(rod.nodes)]))
        assert gap == pytest.approx(rod.length, rel=0.01)
    # Cables join different rods; only actuated cables have motors, within whose range
    # their rest lengths lie.
    for c in d.cables:
        assert d.node_rod[c.nodes[0]] != d.node_rod[c.nodes[1]]
        assert (c.motor is not None) == c.actuated
        if c.motor is not None:
            assert c.motor.min_rest_length <= c.rest_length <= c.motor.max_rest_length
    lo, hi, speed = d.motor_limits
    assert np.all(lo <= d.rest_lengths[d.actuated])
    assert np.all(d.rest_lengths[d.actuated] <= hi)
    assert np.all(speed > 0.0)
    assert d.node_masses.sum() == pytest.approx(d.total_mass)
    assert d.initial_positions.shape == (d.n_nodes, 3)


def test_rod_lengths_of_presets() -> None:
    small = load_robot("three_bar")
    large = load_robot("three_bar_large")
    assert all(r.length == pytest.approx(0.325) for r in small.rods)
    assert all(r.length == pytest.approx(1.45) for r in large.rods)
    superball = load_robot("superball")
    assert sum(c.actuated for c in superball.cables) == 12
    assert sum(not c.actuated for c in superball.cables) == 12


def test_motor_min_tension_is_optional_and_round_trips() -> None:
    # Tong et al. 2024's 1.45 m robot keeps its cables taut by motor torque; the others' motors
    # let their cables go slack, and their documents do not name the field.
    large, small = load_robot("three_bar_large"), load_robot("three_bar")
    stiffness = np.array([large.cables[int(k)].stiffness for k in large.actuated])
    np.testing.assert_allclose(large.motor_min_stretch, 10.0 / stiffness)
    assert np.all(np.isnan(small.motor_min_stretch))
    assert loads_robot(dump_robot(large)) == large
    assert all("min_tension" not in c.get("motor", {}) for c in robot_document(small)["cables"])


def test_the_imu_rods_are_optional_and_named() -> None:
    # Tong et al. 2024's robot carries one IMU, at the centre of its red rod; the others one a rod.
    large, small = load_robot("three_bar_large"), load_robot("three_bar")
    assert large.imu_rods == (0,) and large.rods[0].name == "red"
    assert small.imu_rods == (0, 1, 2) and small.sensors.imu.rods is None
    assert robot_document(large)["sensors"]["imu"]["rods"] == ["red"]
    assert "rods" not in robot_document(small)["sensors"]["imu"]
    assert loads_robot(dump_robot(large)) == large


def test_a_taut_motor_may_read_below_its_range() -> None:
    # A motor that reels in slack winds the cable on below its command range; a command
    # there, or a slack-prone motor's reading, is still one no motor could have.
    large, small = load_robot("three_bar_large"), load_robot("three_bar")
    for d in (large, small):
        short = d.motor_limits[0] - 0.1
        assert d.outside_motor_range(short) == d.n_actuated
    assert large.outside_motor_range(large.motor_limits[0] - 0.1, reading=True) == 0
    assert small.outside_motor_range(small.motor_limits[0] - 0.1, reading=True) == 6
    assert large.outside_motor_range(large.motor_limits[1] + 0.1, reading=True) == 6


def test_preset_by_name_equals_preset_by_path(tmp_path: Path) -> None:
    path = tmp_path / "copy.yaml"
    path.write_text(yaml.safe_dump(_preset_doc("three_bar")))
    by_path = load_robot(path)
    assert by_path == load_robot("three_bar")
    assert by_path.source == str(path)
    assert load_robot(str(path)) == by_path


def test_description_is_hashable_and_frozen() -> None:
    d = load_robot("three_bar")
    assert hash(d) == hash(load_robot("three_bar"))
    with pytest.raises(AttributeError):
        d.name = "other"  # type: ignore[misc]


# ----------------------------------------------------------------------- malformed files


def _del(path: tuple[Any, ...]) -> Callable[[dict[str, Any]], None]:
    def mutate(doc: dict[str, Any]) -> None:
        obj: Any = doc
        for key in path[:-1]:
            obj = obj[key]
        del obj[path[-1]]

    return mutate


def _set(path: tuple[Any, ...], value: Any) -> Callable[[dict[str, Any]], None]:
    def mutate(doc: dict[str, Any]) -> None:
        obj: Any = doc
        for key in path[:-1]:
            obj = obj[key]
        obj[path[-1]] = value

    return mutate


def _move_node(doc: dict[str, Any]) -> None:
    doc["nodes"][0]["position"][2] += 0.1


def _add_loose_node(doc: dict[str, Any]) -> None:
    doc["nodes"].append({"name": "n6", "position": [0.0, 0.0, 0.5]})


def _make_all_passive(doc: dict[str, Any]) -> None:
    for cable in doc["cables"]:
        cable["actuated"] = False
        cable.pop("motor", None)


def _rest_outside_motor_range(doc: dict[str, Any]) -> None:
    doc["cables"][0]["rest_length"] = doc["cables"][0]["motor"]["max_rest_length"] + 0.05


def _motor_without_range(doc: dict[str, Any]) -> None:
    motor = doc["cables"][1]["motor"]
    motor["min_rest_length"] = motor["max_rest_length"] = doc["cables"][1]["rest_length"]


MALFORMED = {
    # id: (mutation, substrings the message must contain besides the file path)
    "missing_stiffness": (_del(("cables", 2, "stiffness")), ["cables[2].stiffness", "missing"]),
    "missing_top_level": (_del(("gravity",)), ["gravity", "missing"]),
    "missing_actuated": (_del(("cables", 4, "actuated")), ["cables[4].actuated", "missing"]),
    "missing_sensor_field": (
        _del(("sensors", "uwb", "anchors")),
        ["sensors.uwb.anchors", "missing"],
    ),
    "negative_length": (_set(("rods", 0, "length"), -0.3), ["rods[0].length", "positive"]),
    "not_a_number": (_set(("cables", 1, "stiffness"), "stiff"), ["cables[1].stiffness"]),
    "bool_is_not_a_number": (_set(("cables", 1, "damping"), True), ["cables[1].damping"]),
    "infinite_number": (_set(("rods", 2, "mass"), float("inf")), ["rods[2].mass", "finite"]),
    "unknown_cable_node": (
        _set(("cables", 0, "nodes", 1), "n99"),
        ["cables[0].nodes[1]", "n99", "unknown node"],
    ),
    "unknown_rod_node": (_set(("rods", 1, "nodes", 0), "x"), ["rods[1].nodes[0]", "'x'"]),
    "cable_within_one_rod": (_set(("cables", 0, "nodes"), ["n0", "n1"]), ["cables[0].nodes"]),
    "cable_same_node_twice": (_set(("cables", 0, "nodes"), ["n0", "n0"]), ["cables[0].nodes"]),
    "node_moved": (_move_node, ["rods[0].length", "rods cannot be assembled"]),
    "node_in_two_rods": (
        _set(("rods", 1, "nodes"), ["n2", "n0"]),
        ["rods[1].nodes[1]", "rods cannot be assembled", "n0", "red"],
    ),
    "node_ends_no_rod": (_add_loose_node, ["rods", "rods cannot be assembled", "n6"]),
    "duplicate_node_name": (_set(("nodes", 5, "name"), "n0"), ["nodes[5].name", "duplicate"]),
    "rest_outside_motor_range": (
        _rest_outside_motor_range,
        ["cables[0].rest_length", "motor's range"],
    ),
    "unknown_field": (_set(("rods", 1, "colour"), [1, 0, 0, 1]), ["rods[1].colour", "unknown"]),
    "unknown_top_level_field": (_set(("version",), 2), ["version", "unknown"]),
    "motor_on_passive_cable": (
        _set(
            ("cables", 6, "motor"),
            {"min_rest_length": 0.1, "max_rest_length": 0.3, "max_speed": 0.1},
        ),
        ["cables[6].motor", "unknown"],
    ),
    "reject_fraction_reversed": (
        _set(("sensors", "uwb", "reject_fraction"), [0.7, 0.3]),
        ["sensors.uwb.reject_fraction"],
    ),
    "wrong_vector_size": (_set(("nodes", 2, "position"), [0.0, 0.1]), ["nodes[2].position"]),
    "camera_width_not_int": (
        _set(("sensors", "camera", "width"), 320.5),
        ["sensors.camera.width"],
    ),
    "camera_far_before_near": (_set(("sensors", "camera", "far"), 0.05), ["sensors.camera.far"]),
    "unsupported_imu_mount": (_set(("sensors", "imu", "mount"), "endcap"), ["sensors.imu.mount"]),
    "rods_not_a_list": (_set(("rods",), {"red": 1}), ["rods", "expected a list"]),
    "no_actuated_cable": (_make_all_passive, ["cables", "no cable is actuated"]),
    "motor_without_range": (
        _motor_without_range,
        ["cables[1].motor.max_rest_length", "must exceed min_rest_length"],
    ),
    "motor_min_tension_negative": (
        _set(("cables", 0, "motor", "min_tension"), -5.0),
        ["cables[0].motor.min_tension", "positive"],
    ),
    "motor_min_tension_not_a_number": (
        _set(("cables", 3, "motor", "min_tension"), "taut"),
        ["cables[3].motor.min_tension", "number"],
    ),
    "imu_on_an_unknown_rod": (
        _set(("sensors", "imu", "rods"), ["red", "purple"]),
        ["sensors.imu.rods[1]", "unknown name 'purple'"],
    ),
    "imu_rod_named_twice": (
        _set(("sensors", "imu", "rods"), ["green", "green"]),
        ["sensors.imu.rods[1]", "named twice"],
    ),
    "imu_on_no_rod": (_set(("sensors", "imu", "rods"), []), ["sensors.imu.rods", "at least 1"]),
    "imu_full_scale_zero": (
        _set(("sensors", "imu", "gyro_full_scale"), 0.0),
        ["sensors.imu.gyro_full_scale", "positive"],
    ),
    "anchor_not_3d": (
        _set(("sensors", "uwb", "anchors", 1), [0.0, 1.0]),
        ["sensors.uwb.anchors[1]", "expected 3 numbers, got 2"],
    ),
    "number_as_text": (
        _set(("cables", 0, "stiffness"), "1e3"),  # YAML 1.1 reads 1e3 as text
        ["cables[0].stiffness", "expected a number, got '1e3'"],
    ),
    "camera_flying_pixels_above_one": (
        _set(("sensors", "camera", "flying_pixels"), 1.5),
        ["sensors.camera.flying_pixels", "1"],
    ),
    "imu_full_scale_misspelt": (
        _set(("sensors", "imu", "accel_fullscale"), 100.0),
        ["sensors.imu.accel_fullscale", "unknown"],
    ),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_description_is_rejected(
    case: str, tmp_path: Path, three_bar_doc: dict[str, Any]
) -> None:
    mutate, needles = MALFORMED[case]
    doc = copy.deepcopy(three_bar_doc)
    mutate(doc)
    path = tmp_path / f"{case}.yaml"
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(DescriptionError) as info:
        load_robot(path)
    message = str(info.value)
    assert str(path) in message
    for needle in needles:
        assert needle in message, f"{needle!r} not in {message!r}"


def test_description_error_is_a_value_error() -> None:
    assert issubclass(DescriptionError, ValueError)


def test_unmutated_copy_loads(tmp_path: Path, three_bar_doc: dict[str, Any]) -> None:
    # The malformed cases above fail because of their mutation, not the round trip.
    path = tmp_path / "ok.yaml"
    path.write_text(yaml.safe_dump(copy.deepcopy(three_bar_doc)))
    assert load_robot(path) == load_robot("three_bar")


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("name: [three_bar\nnodes: {", "not valid YAML"),
        (":\n  - : : [\n\t", "not valid YAML"),
        ("- just\n- a list\n", "expected a mapping"),
        ("", "expected a mapping"),
        ("42\n", "expected a mapping"),
    ],
    ids=["unclosed", "tab", "list", "empty", "scalar"],
)
def test_file_that_is_not_a_description(tmp_path: Path, text: str, needle: str) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(DescriptionError) as info:
        load_robot(path)
    assert str(path) in str(info.value)
    assert needle in str(info.value)


def test_binary_file_is_rejected(tmp_path: Path) -> None:
    path = tmp_path / "image.yaml"
    path.write_bytes(b"\x89PNG\r\n\x1a\n\x00\xff\xfe\x80binary")
    with pytest.raises(DescriptionError) as info:
        load_robot(path)
    assert str(path) in str(info.value)


@pytest.mark.parametrize("as_str", [False, True])
def test_missing_file(tmp_path: Path, as_str: bool) -> None:
    path = tmp_path / "nowhere" / "robot.yaml"
    with pytest.raises(DescriptionError) as info:
        load_robot(str(path) if as_str else path)
    assert str(path) in str(info.value)
    assert "no such file" in str(info.value)


def test_directory_is_not_a_description(tmp_path: Path) -> None:
    with pytest.raises(DescriptionError) as info:
        load_robot(tmp_path)
    assert str(tmp_path) in str(info.value)


def test_unknown_preset_name_is_a_missing_file() -> None:
    with pytest.raises(DescriptionError) as info:
        load_robot("four_bar")
    assert "four_bar" in str(info.value)
    for name in PRESETS:
        assert name in str(info.value)


def test_parse_robot_names_the_given_source(three_bar_doc: dict[str, Any]) -> None:
    doc = copy.deepcopy(three_bar_doc)
    doc["rods"][0]["length"] = -0.3
    with pytest.raises(DescriptionError, match=r"^memory://robot: rods\[0\]\.length: "):
        parse_robot(doc, "memory://robot")
    assert parse_robot(copy.deepcopy(three_bar_doc), "memory://ok").source == "memory://ok"


@pytest.mark.parametrize("preset", PRESETS)
def test_description_round_trips_through_yaml_text(preset: str) -> None:
    """What travels with a recording is the whole description, exactly."""
    d = load_robot(preset)
    text = dump_robot(d)
    again = loads_robot(text, source="recording")
    assert again == d
    assert again.source == "recording"
    assert dump_robot(again) == text


def test_loads_robot_names_its_source() -> None:
    with pytest.raises(DescriptionError, match=r"bag\.mcap: not valid YAML"):
        loads_robot("nodes: [", source="bag.mcap")
    with pytest.raises(DescriptionError, match=r"bag\.mcap.*gravity"):
        loads_robot(
            dump_robot(load_robot("three_bar")).replace("gravity: 9.81", "gravity: x"), "bag.mcap"
        )


def test_imu_full_scale_is_optional_and_read(three_bar_doc: dict[str, Any]) -> None:
    """Old descriptions (and bags) have no full scale: the defaults are 16 g and
    2000 deg/s; a given one is kept through the YAML round trip."""
    d = parse_robot(copy.deepcopy(three_bar_doc), "three_bar")
    assert d.sensors.imu.accel_full_scale == pytest.approx(16 * 9.80665)
    assert d.sensors.imu.gyro_full_scale == pytest.approx(np.radians(2000.0))
    doc = copy.deepcopy(three_bar_doc)
    doc["sensors"]["imu"]["accel_full_scale"] = 78.5
    d = parse_robot(doc, "x")
    assert d.sensors.imu.accel_full_scale == 78.5
    assert loads_robot(dump_robot(d)) == d


# ------------------------------------------------------------------------ the JSON Schema


def test_the_committed_json_schema_is_the_generated_one() -> None:
    from tensegrity_gym.model.schema import description_schema

    file = resources.files("tensegrity_gym.model") / "assets" / "robot_description.schema.json"
    assert json.loads(file.read_text()) == description_schema(), (
        "the schema changed: run python scripts/write_schema.py"
    )


def test_the_presets_keep_to_the_json_schema(three_bar_doc: dict[str, Any]) -> None:
    """What editors check against the JSON Schema is what the loader checks field by
    field: every preset passes, a field out of range does not."""
    import jsonschema

    from tensegrity_gym.model.schema import description_schema

    validator = jsonschema.Draft202012Validator(description_schema())
    for name in PRESETS:
        validator.validate(_preset_doc(name))
    doc = copy.deepcopy(three_bar_doc)
    doc["rods"][0]["length"] = -0.3
    assert not validator.is_valid(doc)


def test_the_schemas_defaults_are_the_dataclasses() -> None:
    from tensegrity_gym.model.description import Gait, ImuConfig
    from tensegrity_gym.model.schema import GaitSection, ImuSection

    for model, cls in ((ImuSection, ImuConfig), (GaitSection, Gait)):
        fields = {f.name: f for f in dataclasses.fields(cls)}
        for key, info in model.model_fields.items():
            if not info.is_required() and key in fields:
                assert info.default == fields[key].default, key
