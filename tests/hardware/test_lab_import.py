"""A lab's recording in (hardware.lab.importer, ``tensegrity-gym import``): a simulated
recording written out as a lab's CSV logs and ranges file, imported back as a bag, gives
the same samples and the same estimates as the bag it came from."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
import pytest

import tensegrity_gym  # noqa: F401  (registers the envs)
from hardware.bag.reader import BagReader
from hardware.lab import LabFileError, import_recording, load_lab_map, write_logs
from tensegrity_gym.model.samples import RgbdFrame

if TYPE_CHECKING:
    from tensegrity_gym.model.samples import Sample

ENV_ID = "tensegrity_gym/ThreeBarRoll-v0"
pytestmark = pytest.mark.xdist_group("lab_import")  # the recording's fixtures, once


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """40 random steps of the 3-bar robot recorded to a bag."""
    root = tmp_path_factory.mktemp("lab_import")
    env = gym.make(ENV_ID, estimator="oracle", calibration="true", record_dir=root / "runs")
    env.reset(seed=0)
    for _ in range(40):
        env.step(env.action_space.sample())
    env.close()
    return root / "runs" / "episode_000"


def _contents(bag: Path) -> tuple[list[Sample], list[tuple[float, np.ndarray]], BagReader]:
    """A bag's samples (RGB-D left out), its commands with their times, its reader."""
    with BagReader(bag) as reader:
        periods = list(reader.periods())
    samples = [s for p in periods for s in p.samples if not isinstance(s, RgbdFrame)]
    commands = [(periods[k - 1].t_end, p.command) for k, p in enumerate(periods) if k > 0]
    return samples, commands, reader  # type: ignore[return-value]


@pytest.fixture(scope="module")
def exported(recorded: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The recording as a lab's files: CSV logs per kind, a ranges file, a map."""
    samples, commands, reader = _contents(recorded)
    folder = tmp_path_factory.mktemp("logs")
    write_logs(folder, samples, reader.description, clock_origin_ns=reader.clock_origin_ns,
               commands=commands)  # fmt: skip
    return folder


@pytest.fixture(scope="module")
def imported(recorded: Path, exported: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    with BagReader(recorded) as reader:
        d, calibration = reader.description, reader.calibration
    out = tmp_path_factory.mktemp("imported") / "bag"
    summary = import_recording([exported], load_lab_map(exported / "map.yaml"), d, calibration, out)
    assert summary["command_source"] == "recorded" and summary["control_period"] == 0.1
    return out


def test_the_files_round_trip_to_the_same_samples(recorded: Path, imported: Path) -> None:
    before, commands_before, r0 = _contents(recorded)
    after, commands_after, r1 = _contents(imported)
    assert r1.clock_origin_ns == r0.clock_origin_ns
    key = lambda s: (s.t, type(s).__name__, getattr(s, "rod", -1))  # noqa: E731
    before, after = sorted(before, key=key), sorted(after, key=key)
    assert [type(s) for s in after] == [type(s) for s in before]
    for a, b in zip(after, before, strict=True):
        assert repr(a) == repr(b)  # every field, bit for bit
    assert len(commands_after) == len(commands_before)
    for (ta, ca), (tb, cb) in zip(commands_after, commands_before, strict=True):
        assert ta == tb and np.array_equal(ca, cb)


def test_the_imported_bag_estimates_as_the_original(
    recorded: Path, imported: Path, tmp_path: Path
) -> None:
    from agents.recordings.offline import estimate_bag

    estimate_bag(recorded, "ukf", tmp_path / "a", progress=False)
    estimate_bag(imported, "ukf", tmp_path / "b", progress=False)
    a, b = np.load(tmp_path / "a" / "estimates.npz"), np.load(tmp_path / "b" / "estimates.npz")
    assert set(a.files) == set(b.files)
    for name in a.files:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)


def test_without_commands_the_encoders_are_held(
    recorded: Path, exported: Path, tmp_path: Path
) -> None:
    with BagReader(recorded) as reader:
        d, calibration = reader.description, reader.calibration
    lab_map = load_lab_map(exported / "map.yaml")
    files = [exported / name for name in lab_map.files if name != "commands.csv"]
    summary = import_recording(files, lab_map, d, calibration, tmp_path / "bag")
    assert summary["command_source"] == "encoders held"
    samples, commands, _ = _contents(tmp_path / "bag")
    encoders = [s for s in samples if type(s).__name__ == "EncoderSample"]
    t, held = commands[5]
    last = [s for s in encoders if s.t <= t][-1]
    assert np.array_equal(held, last.rest_lengths)


@pytest.mark.parametrize(
    ("doc", "match"),
    [
        ("files: {}\n", r"a lab map is a mapping with 'files'"),
        ("files: {a.csv: {kind: sonar}}\n", r"files\.a\.csv\.kind: 'sonar' is not one of imu"),
        ("files: {a.csv: {kind: imu, unit: {}}}\n", r"files\.a\.csv\.unit: unknown field"),
        ("files: {a.csv: {kind: imu}}\nrobots: x\n", r"robots: unknown field"),
    ],
)  # fmt: skip
def test_bad_lab_maps_are_one_line(tmp_path: Path, doc: str, match: str) -> None:
    (tmp_path / "map.yaml").write_text(doc)
    with pytest.raises(LabFileError, match=match):
        load_lab_map(tmp_path / "map.yaml")


def test_bad_logs_are_one_line(exported: Path, tmp_path: Path, recorded: Path) -> None:
    with BagReader(recorded) as reader:
        d, calibration = reader.description, reader.calibration
    (tmp_path / "imu.csv").write_text("t,rod,ax,ay,az,gx,gy,gz\n1,red,0,0,9.8,0,0,x\n")
    (tmp_path / "map.yaml").write_text("files: {imu.csv: {kind: imu, units: {gyro: rpm}}}\n")
    lab_map = load_lab_map(tmp_path / "map.yaml")
    with pytest.raises(LabFileError, match=r"imu\.csv: units\.gyro: 'rpm' is not one of"):
        import_recording([tmp_path / "imu.csv"], lab_map, d, calibration, tmp_path / "b1")
    (tmp_path / "map.yaml").write_text("files: {imu.csv: {kind: imu}}\n")
    lab_map = load_lab_map(tmp_path / "map.yaml")
    with pytest.raises(LabFileError, match=r"imu\.csv: line 2: gz 'x' is not a number"):
        import_recording([tmp_path / "imu.csv"], lab_map, d, calibration, tmp_path / "b2")
    with pytest.raises(LabFileError, match=r"other\.csv: not one of the files"):
        import_recording([tmp_path / "other.csv"], lab_map, d, calibration, tmp_path / "b3")


def test_import_from_the_command_line(exported: Path, tmp_path: Path) -> None:
    from agents.cli import main

    out = tmp_path / "bag"
    assert main(["import", str(exported), "--out", str(out)]) == 0
    with BagReader(out) as reader:
        assert reader.description.name == "three_bar"
        assert reader.run_info["commands"] == "recorded"
    assert main(["import", str(exported), "--out", str(out)]) == 2  # exists


UWB_MSG = """std_msgs/Header header
uint8[] initiator
uint8[] responder
float64[] distance
{time}[] stamps
"""


def _lab_bag(path: Path, recorded: Path, *, ros2: bool = False) -> None:
    """The recording as a lab's ROS 1 bag (or ROS 2, MCAP): its own topic names,
    standard types (lengths in mm), and a UWB message of its own."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    samples, commands, reader = _contents(recorded)
    d = reader.description
    store = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
    time = "builtin_interfaces/Time" if ros2 else "time"
    store.register(get_types_from_msg(UWB_MSG.format(time=time), "lab_msgs/msg/Ranges"))
    T = store.types
    Time = T["builtin_interfaces/msg/Time"]
    seq = {} if ros2 else {"seq": 0}

    def Header(**fields: object) -> object:  # noqa: N802
        return T["std_msgs/msg/Header"](**seq, **fields)

    V3, Q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
    names = [d.cables[k].name for k in d.actuated]

    def stamp(t: float) -> object:
        ns = round(t * 1e9)
        return Time(sec=ns // 10**9, nanosec=ns % 10**9)

    def imu(t: float, q: np.ndarray, a: np.ndarray, w: np.ndarray) -> object:
        zero = np.zeros(9)
        return T["sensor_msgs/msg/Imu"](
            header=Header(stamp=stamp(t), frame_id=""),
            orientation=Q(x=q[0], y=q[1], z=q[2], w=q[3]), orientation_covariance=zero,
            angular_velocity=V3(x=w[0], y=w[1], z=w[2]), angular_velocity_covariance=zero,
            linear_acceleration=V3(x=a[0], y=a[1], z=a[2]), linear_acceleration_covariance=zero,
        )  # fmt: skip

    def joints(t: float, values: np.ndarray) -> object:
        return T["sensor_msgs/msg/JointState"](
            header=Header(stamp=stamp(t), frame_id=""), name=names[::-1],
            position=1e3 * values[::-1], velocity=np.zeros(0), effort=np.zeros(0),
        )  # the lab's order, not the description's; millimetres  # fmt: skip

    def floats(values: np.ndarray) -> object:
        layout = T["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0)
        return T["std_msgs/msg/Float64MultiArray"](layout=layout, data=values.astype(np.float64))

    out: list[tuple[str, str, int, object]] = []
    for s in samples:
        ns = round(s.t * 1e9)
        kind = type(s).__name__
        if kind == "ImuSample":
            msg = imu(s.t, np.array([0.0, 0, 0, 1]), s.accel, s.gyro)
            out.append((f"/{d.rods[s.rod].name}/imu", "sensor_msgs/msg/Imu", ns, msg))
        elif kind == "AhrsSample":
            msg = imu(s.t, s.quaternion, np.zeros(3), np.zeros(3))
            out.append((f"/{d.rods[s.rod].name}/ahrs", "sensor_msgs/msg/Imu", ns, msg))
        elif kind == "EncoderSample":
            out.append(("/motors", "sensor_msgs/msg/JointState", ns, joints(s.t, s.rest_lengths)))
        elif kind == "CableLengthSample":
            out.append(("/strain", "std_msgs/msg/Float64MultiArray", ns, floats(s.lengths)))
        elif kind == "ContactSample":
            out.append(("/feet", "std_msgs/msg/Float64MultiArray", ns, floats(s.in_contact)))
        elif kind == "UwbRangeSample":
            pairs = np.asarray(s.pairs)
            msg = T["lab_msgs/msg/Ranges"](
                header=Header(stamp=stamp(s.t), frame_id=""),
                initiator=pairs[:, 0].astype(np.uint8), responder=pairs[:, 1].astype(np.uint8),
                distance=np.asarray(s.ranges), stamps=[stamp(x) for x in s.times],
            )  # fmt: skip
            out.append(("/uwb", "lab_msgs/msg/Ranges", ns, msg))
    for t, c in commands:
        out.append(("/motors/target", "sensor_msgs/msg/JointState", round(t * 1e9), joints(t, c)))
    if ros2:
        from rosbags.rosbag2 import StoragePlugin
        from rosbags.rosbag2 import Writer as Ros2Writer

        writer: Any = Ros2Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
        serialize = store.serialize_cdr
    else:
        from rosbags.rosbag1 import Writer as Ros1Writer

        writer, serialize = Ros1Writer(path), store.serialize_ros1
    with writer as bag:
        conns: dict[str, object] = {}
        for topic, msgtype, ns, msg in sorted(out, key=lambda m: m[2]):
            if topic not in conns:
                conns[topic] = bag.add_connection(topic, msgtype, typestore=store)
            bag.write(conns[topic], ns, serialize(msg, msgtype))


TOPIC_MAP = """robot: three_bar
topics:
{rods}
  /motors: {{kind: encoders, values: position, names: name, units: {{length: mm}}}}
  /motors/target: {{kind: commands, values: position, names: name, units: {{length: mm}}}}
  /strain: {{kind: cable_lengths}}
  /feet: {{kind: contacts}}
  /uwb: {{kind: uwb, node: responder, anchor: initiator, range: distance, times: stamps}}
"""


def _topic_map(d: Any) -> str:
    """The lab map of :func:`_lab_bag`'s topics for robot ``d``."""
    rods = "\n".join(
        f"  /{r.name}/imu: {{kind: imu, rod: {r.name}}}\n"
        f"  /{r.name}/ahrs: {{kind: ahrs, rod: {r.name}}}"
        for r in d.rods
    )
    return TOPIC_MAP.format(rods=rods)


@pytest.mark.parametrize("ros", ["ros1", "ros2"])
def test_a_lab_bag_imports_to_the_same_estimates(recorded: Path, tmp_path: Path, ros: str) -> None:
    """A lab's ROS 1 bag, or ROS 2 bag (MCAP), through its topic map."""
    from agents.recordings.offline import estimate_bag

    with BagReader(recorded) as reader:
        d, calibration = reader.description, reader.calibration
    lab = tmp_path / ("lab.bag" if ros == "ros1" else "lab_ros2")
    _lab_bag(lab, recorded, ros2=ros == "ros2")
    (tmp_path / "map.yaml").write_text(_topic_map(d))
    lab_map = load_lab_map(tmp_path / "map.yaml")
    import_recording([lab], lab_map, d, calibration, tmp_path / "bag")
    before, commands_before, _ = _contents(recorded)
    after, commands_after, _ = _contents(tmp_path / "bag")
    key = lambda s: (s.t, type(s).__name__, getattr(s, "rod", -1))  # noqa: E731
    before, after = sorted(before, key=key), sorted(after, key=key)
    assert [type(s) for s in after] == [type(s) for s in before]
    for a, b in zip(after, before, strict=True):
        if type(a).__name__ == "ImuSample":  # sensor_msgs/Imu has no field
            assert (
                a.t == b.t and np.array_equal(a.accel, b.accel) and np.array_equal(a.gyro, b.gyro)
            )
        else:
            assert repr(a) == repr(b)
    assert [c[0] for c in commands_after] == [c[0] for c in commands_before]
    for (_, ca), (_, cb) in zip(commands_after, commands_before, strict=True):
        np.testing.assert_allclose(ca, cb, rtol=1e-15)  # through millimetres: an ulp
    estimate_bag(recorded, "ukf", tmp_path / "a", progress=False)
    estimate_bag(tmp_path / "bag", "ukf", tmp_path / "b", progress=False)
    a, b = np.load(tmp_path / "a" / "estimates.npz"), np.load(tmp_path / "b" / "estimates.npz")
    for name in a.files:  # the same to the rounding of the commands' trip through mm
        np.testing.assert_allclose(a[name], b[name], rtol=1e-9, atol=1e-12, err_msg=name)


def test_a_bag_without_a_mapped_topic_is_one_line(recorded: Path, tmp_path: Path) -> None:
    with BagReader(recorded) as reader:
        d, calibration = reader.description, reader.calibration
    _lab_bag(tmp_path / "lab.bag", recorded)
    (tmp_path / "map.yaml").write_text("topics:\n  /sonar: {kind: imu, rod: red}\n")
    lab_map = load_lab_map(tmp_path / "map.yaml")
    with pytest.raises(LabFileError, match=r"lab\.bag: no topic /sonar \(the bag has /blue/ahrs"):
        import_recording([tmp_path / "lab.bag"], lab_map, d, calibration, tmp_path / "bag")


def test_estimate_reads_a_lab_bag_through_its_map(
    recorded: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``--lab-map``: the lab's bag imported to a temporary bag, estimated, removed."""
    import tempfile

    from agents.cli import main

    _lab_bag(tmp_path / "lab.bag", recorded)
    with BagReader(recorded) as reader:
        (tmp_path / "map.yaml").write_text(_topic_map(reader.description))
    # A temporary folder of this test's own: other workers import at the same time.
    (tmp_path / "tmp").mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    before = set(Path(tempfile.gettempdir()).glob("tensegrity-gym-import-*"))
    assert tempfile.gettempdir() == str(tmp_path / "tmp") and not before
    args = ["estimate", str(tmp_path / "lab.bag"), "--lab-map", str(tmp_path / "map.yaml"),
            "--out", str(tmp_path / "out"), "--no-progress"]  # fmt: skip
    assert main(args) == 0
    assert (tmp_path / "out" / "estimates.npz").is_file()
    assert set(Path(tempfile.gettempdir()).glob("tensegrity-gym-import-*")) == before


def test_identify_runs_on_an_imported_recording(exported: Path, tmp_path: Path) -> None:
    """A lab's recording (no ground truth) imported and identified end to end: fitted to
    the UKF's estimates, a robot written that gym.make loads."""
    from agents.cli import main

    out = tmp_path / "fitted.yaml"
    args = ["identify", str(exported), "--lab-map", str(exported / "map.yaml"),
            "--out", str(out), "--params", "damping", "--max-evaluations", "4",
            "--workers", "1"]  # fmt: skip
    assert main(args) == 0
    report = (tmp_path / "fitted_identify" / "report.md").read_text()
    assert "UKF estimates" in report
    from tensegrity_gym.envs.factory import make_env

    env = make_env(out, estimator="oracle", calibration="true")
    env.reset(seed=0)
    env.close()


def test_an_env_replays_a_lab_bag_as_it_replays_its_own(recorded: Path, tmp_path: Path) -> None:
    """``driver=LabReplay(...)``: the lab's bag imported to a temporary bag and replayed,
    the same observations as ``driver="bag:PATH"`` on the bag it came from; the
    temporary bag goes when the env closes."""
    from hardware.lab import LabReplay

    with BagReader(recorded) as reader:
        d, calibration = reader.description, reader.calibration
    _lab_bag(tmp_path / "lab.bag", recorded)
    (tmp_path / "map.yaml").write_text(_topic_map(d))
    replay = LabReplay([tmp_path / "lab.bag"], load_lab_map(tmp_path / "map.yaml"), d, calibration)
    folder = replay._folder
    observed = []
    for driver in (f"bag:{recorded}", replay):
        env = gym.make(ENV_ID, driver=driver, estimator="ukf")
        obs, _ = env.reset(seed=0)
        run = [obs]
        backend = env.unwrapped.backend  # type: ignore[attr-defined]
        for _ in range(10):
            action = env.unwrapped.targets_to_action(backend.next_command)  # type: ignore[attr-defined]
            obs, *_ = env.step(action)
            run.append(obs)
        env.close()
        observed.append(np.array(run))
    np.testing.assert_allclose(observed[1], observed[0], rtol=1e-6, atol=1e-7)
    assert not folder.exists()
