"""ROS 2 bags: message codecs, bit-for-bit round trips, replay through the env, the
record and estimate commands. (Damaged and hostile bags: tests/hardware/test_bag_robustness.py.)"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import gymnasium as gym
import numpy as np
import pytest

import tensegrity_gym  # noqa: F401
from agents.cli import main as cli_main
from hardware.bag import BagReader, ReplayBackend, read_run
from hardware.bag import messages as m
from hardware.bag.kinds import TopicTable
from hardware.recording import BagSink, MemorySink, RecordingBackend
from tensegrity_gym.model.description import load_robot
from tensegrity_gym.model.protocols import Backend
from tensegrity_gym.model.samples import ns_to_seconds, seconds_to_ns
from tensegrity_gym.sim.backend import SimBackend

if TYPE_CHECKING:
    from hardware.recording import RecordedRun, RecordedStep
    from tensegrity_gym.envs.tensegrity_env import TensegrityEnv

THREE_BAR = "tensegrity_gym/ThreeBarRoll-v0"


# ---------------------------------------------------------------------- codecs


@pytest.mark.parametrize("frame_id", ["", "r", "red", "blue123", "a_long_rod_name"])
def test_fast_imu_codecs_give_the_bytes_and_values_of_rosbags(frame_id: str) -> None:
    store = m.typestore()
    rng = np.random.default_rng(len(frame_id))
    t = 12.345678901
    gyro, accel, quat = rng.normal(size=3), rng.normal(size=3), rng.normal(size=4)
    for raw, kwargs in [
        (m.encode_imu(t, frame_id, gyro=gyro, accel=accel), {"gyro": gyro, "accel": accel}),
        (m.encode_imu(t, frame_id, orientation=quat), {"orientation": quat}),
    ]:
        msg = store.deserialize_cdr(raw, m.IMU)
        assert bytes(store.serialize_cdr(msg, m.IMU)) == raw
        assert msg.header.frame_id == frame_id
        assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (12, 345678901)
        ns, name, q, w, a, provided = m.decode_imu(raw)
        assert (ns, name) == (12_345_678_901, frame_id)
        assert provided == ("orientation" in kwargs, "gyro" in kwargs, "accel" in kwargs)
        if "gyro" in kwargs:
            assert np.array_equal(w, gyro) and np.array_equal(a, accel)
            assert msg.orientation_covariance[0] == -1.0  # REP 145: not provided
        else:
            assert np.array_equal(q, quat)
            assert msg.angular_velocity_covariance[0] == -1.0
    field = rng.normal(size=3) * 1e-5
    raw = m.encode_magnetic_field(t, frame_id, field)
    msg = store.deserialize_cdr(raw, m.MAGNETIC_FIELD)
    assert bytes(store.serialize_cdr(msg, m.MAGNETIC_FIELD)) == raw
    assert np.array_equal(m.decode_magnetic_field(raw)[2], field)


def test_time_stamps_survive_nanoseconds_exactly() -> None:
    rng = np.random.default_rng(0)
    ns = rng.integers(0, 10**15, size=2000)
    for n in ns:
        t = ns_to_seconds(int(n))
        assert seconds_to_ns(t) == n
        assert m.stamp_ns(*m.stamp(t)) == n


def test_every_topic_of_a_robot_has_a_registered_type() -> None:
    d = load_robot("superball")
    table = TopicTable(d)
    store = m.typestore()
    for kind, channels in (("imu", 2), ("ahrs", 1)):
        for channel in range(channels):
            assert len(table.rod_topics(kind, channel)) == d.n_rods
    for topic, msgtype in table.types.items():
        assert topic.startswith("/")
        assert msgtype in store.types, topic
        assert store.generate_msgdef(msgtype, ros_version=2)[0]  # its schema can be embedded
    assert table.topic("ahrs", 0, 2) == f"/{d.rods[2].name}/imu/data"
    assert table.topic("rgbd", 1) == "/camera/depth/image_raw"


# ---------------------------------------------------------------------- round trip


def _record(tmp: Path, robot: str, steps: int, camera: bool, seed: int = 0) -> RecordedRun:
    """A run recorded at once in memory and to a bag (``tmp/rec/episode_000``)."""
    d = load_robot(robot)
    memory = MemorySink()
    sim = SimBackend(d, camera=camera)
    backend = RecordingBackend(RecordingBackend(sim, memory), BagSink(tmp / "rec"))
    rng = np.random.default_rng(seed)
    backend.reset(rng)
    lo, hi, _ = d.motor_limits
    for _ in range(steps):
        backend.step(rng.uniform(lo, hi))
    backend.close()
    return memory.run


def _assert_same_values(a: Any, b: Any, where: str) -> None:
    assert type(a) is type(b), where
    for name in a.__dataclass_fields__:
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and x.shape == y.shape, f"{where}.{name}"
            assert np.array_equal(x, y, equal_nan=True), f"{where}.{name}"
        else:
            assert x == y, f"{where}.{name}"


def _assert_same_step(a: RecordedStep, b: RecordedStep, where: str) -> None:
    assert len(a.samples) == len(b.samples), where
    for k, (x, y) in enumerate(zip(a.samples, b.samples, strict=True)):
        _assert_same_values(x, y, f"{where} sample {k} ({type(x).__name__})")
    assert np.array_equal(a.command, b.command), where
    assert (a.truth is None) == (b.truth is None), where
    if a.truth is not None:
        _assert_same_values(a.truth, b.truth, f"{where} truth")


@pytest.mark.parametrize(
    ("robot", "steps", "camera"), [("three_bar", 12, True), ("superball", 6, False)]
)
def test_record_then_read_reproduces_every_sample_bit_for_bit(
    tmp_path: Path, robot: str, steps: int, camera: bool
) -> None:
    live = _record(tmp_path, robot, steps, camera)
    bag = tmp_path / "rec" / "episode_000"
    assert (bag / "metadata.yaml").exists()
    back = read_run(bag)
    assert back.description == live.description
    for name in ("uwb_offsets", "anchors", "camera_intrinsics", "camera_pose"):
        assert np.array_equal(getattr(back.calibration, name), getattr(live.calibration, name))
    assert back.control_period == live.control_period
    assert len(back.steps) == len(live.steps) == steps
    _assert_same_step(back.start, live.start, "start")
    for k, (x, y) in enumerate(zip(back.steps, live.steps, strict=True)):
        _assert_same_step(x, y, f"step {k}")
    kinds = {type(s).__name__ for step in live.steps for s in step.samples}
    expected = {"ImuSample", "AhrsSample", "EncoderSample", "CableLengthSample", "ContactSample"}
    assert expected | ({"RgbdFrame"} if camera else set()) <= kinds | {"UwbRangeSample"}


def test_a_bag_carries_description_calibration_and_standard_types(tmp_path: Path) -> None:
    _record(tmp_path, "three_bar", 3, camera=False)
    with BagReader(tmp_path / "rec" / "episode_000") as reader:
        topics = reader.topics
        assert topics["/robot_description"] == "std_msgs/msg/String"
        assert topics["/red/imu/data_raw"] == "sensor_msgs/msg/Imu"
        assert topics["/red/imu/mag"] == "sensor_msgs/msg/MagneticField"
        assert topics["/motors/rest_lengths"] == "sensor_msgs/msg/JointState"
        assert topics["/ground_truth/rod_poses"] == "geometry_msgs/msg/PoseArray"
        assert topics["/uwb/ranges"] == "tensegrity_msgs/msg/UwbRangeArray"
        assert reader.run_info["control_period"] == 0.1
        assert reader.command_count == 3
        assert reader.has_truth and not reader.recovered
        assert not reader.skipped
    # Every connection embeds its schema, so a generic tool can decode it.
    from rosbags.rosbag2 import Reader

    with Reader(tmp_path / "rec" / "episode_000") as plain:
        for conn in plain.connections:
            assert conn.msgdef.data, conn.topic
            assert conn.digest.startswith("RIHS01_"), conn.topic


def test_what_is_sent_once_is_recorded_latched(tmp_path: Path) -> None:
    """/robot_description and /tf_static (and the rest of the header) are offered
    transient local, keep last 1, reliable: in metadata.yaml (what ``ros2 bag play``
    reads), in the MCAP channels' metadata and as rosbags reads them back; the streams
    stay without a profile (the player's default)."""
    import yaml
    from mcap.reader import make_reader
    from rosbags.interfaces import QosDurability, QosHistory, QosReliability
    from rosbags.rosbag2 import Reader

    _record(tmp_path, "three_bar", 2, camera=False)
    bag = tmp_path / "rec" / "episode_000"
    latched = {m.DESCRIPTION_TOPIC, m.TF_STATIC_TOPIC}
    assert latched <= m.LATCHED_TOPICS and m.TF_TOPIC not in m.LATCHED_TOPICS
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    profiles = {t["topic_metadata"]["name"]: t["topic_metadata"]["offered_qos_profiles"]
                for t in info["topics_with_message_count"]}  # fmt: skip
    for topic in latched:
        [profile] = profiles[topic]
        assert (profile["durability"], profile["history"], profile["depth"]) == (
            "transient_local", "keep_last", 1)  # fmt: skip
        assert profile["reliability"] == "reliable"
    assert profiles["/ground_truth/state"] == profiles["/red/imu/data_raw"] == []
    [mcap] = bag.glob("*.mcap")
    with mcap.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    channels = {c.topic: c.metadata for c in summary.channels.values()}
    for topic in latched:
        assert yaml.safe_load(channels[topic]["offered_qos_profiles"]) == profiles[topic]
    with Reader(bag) as reader:
        qos = {c.topic: c.ext.offered_qos_profiles for c in reader.connections}  # type: ignore[union-attr]
    for topic in latched:
        [q] = qos[topic]
        assert q.durability == QosDurability.TRANSIENT_LOCAL
        assert (q.history, q.depth, q.reliability) == (QosHistory.KEEP_LAST, 1,
                                                        QosReliability.RELIABLE)  # fmt: skip
    with BagReader(bag) as ours:  # what viewers read, ours passes over, uncounted
        assert m.TF_STATIC_TOPIC in ours.topics and not ours.skipped


# ---------------------------------------------------------------------- replay


@pytest.fixture(scope="module")
def recorded_env_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[Any]]:
    """A UKF episode of ThreeBarRoll recorded through ``record_dir``, and its live outputs."""
    folder = tmp_path_factory.mktemp("bags")
    env = gym.make(THREE_BAR, estimator="ukf", record_dir=folder, max_episode_steps=25)
    env.action_space.seed(3)
    obs, info = env.reset(seed=11)
    live = [(obs, info["com_estimate"], info["com_true"])]
    done = False
    while not done:
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        live.append((obs, info["com_estimate"], info["com_true"], reward))
        done = terminated or truncated
    env.close()
    return folder / "episode_000", live


def test_replayed_bag_gives_the_env_the_same_episode(
    recorded_env_run: tuple[Path, list[Any]], caplog: pytest.LogCaptureFixture
) -> None:
    bag, live = recorded_env_run
    env = gym.make(THREE_BAR, estimator="ukf", driver=f"bag:{bag}")
    obs, info = env.reset(seed=11)  # the same seed: the estimator's belief is the same
    assert np.array_equal(obs, live[0][0])
    assert np.array_equal(info["com_true"], live[0][2])
    zeros = np.zeros(env.action_space.shape, dtype=np.float32)
    with caplog.at_level(logging.WARNING, logger="hardware.bag.replay"):
        for k, (l_obs, l_com, l_true, l_reward) in enumerate(live[1:], 1):
            obs, reward, _, truncated, info = env.step(zeros)  # actions are ignored
            assert np.array_equal(obs, l_obs), k
            assert np.array_equal(info["com_estimate"], l_com), k
            assert np.array_equal(info["com_true"], l_true), k
            assert reward == l_reward, k
            assert truncated == (k == len(live) - 1)  # the bag's end truncates
    assert "actions passed to step() are ignored" in caplog.text
    with pytest.raises(RuntimeError, match="bag ended after 25 steps"):
        env.unwrapped.step(zeros)
    env.close()


def test_replay_backend_follows_the_backend_protocol(recorded_env_run: tuple[Path, Any]) -> None:
    bag, _ = recorded_env_run
    backend = ReplayBackend(bag)
    assert isinstance(backend, Backend)
    assert backend.description.name == "three_bar"
    assert backend.control_period == 0.1
    with pytest.raises(RuntimeError, match="reset"):
        backend.step(np.zeros(6))
    start = backend.reset(np.random.default_rng(0))
    assert start.samples and not start.ended
    assert backend.ground_truth() is not None
    image = backend.render(64, 48)
    assert image.shape == (48, 64, 3) and image.dtype == np.uint8 and image.any()
    steps = 0
    while True:
        command = backend.next_command
        result = backend.step(command)
        assert np.array_equal(result.command, command)
        assert all(s.t > 0.1 * steps - 1e-12 for s in result.samples)
        steps += 1
        if result.ended:
            break
    assert steps == backend.steps_total == 25
    backend.close()


def test_replay_env_passes_check_env(recorded_env_run: tuple[Path, Any]) -> None:
    from gymnasium.utils.env_checker import check_env

    bag, _ = recorded_env_run
    env = gym.make(THREE_BAR, estimator="oracle", driver=f"bag:{bag}")
    check_env(env.unwrapped, skip_render_check=True)
    env.close()


def test_a_bag_of_another_robot_is_refused(recorded_env_run: tuple[Path, Any]) -> None:
    bag, _ = recorded_env_run
    with pytest.raises(ValueError, match=r"runs the robot 'three_bar'.*superball"):
        gym.make("tensegrity_gym/SuperBallRoll-v0", driver=f"bag:{bag}")
    with pytest.raises(ValueError, match="bag:PATH"):
        gym.make(THREE_BAR, driver="zenoh:nowhere")


# ---------------------------------------------------------------------- commands


def test_record_writes_a_randomised_worlds_draws_into_the_bag(tmp_path: Path) -> None:
    out = tmp_path / "bags"
    argv = ["record", "--steps", "2", "--estimator", "oracle", "--out", str(out)]
    assert cli_main([*argv, "--randomization", "description"]) == 0
    with BagReader(out / "episode_000") as reader:
        draws = reader.run_info["randomization"]
    # The description's error: rods drawn off their length, encoders off their zero.
    assert len(draws["rod_length"]) == 3 and any(abs(r - 1.0) > 1e-3 for r in draws["rod_length"])
    assert max(abs(z) for z in draws["encoder_zero_m"]) > 1e-3


def test_record_and_estimate_commands(tmp_path: Path) -> None:
    rc = cli_main(
        [
            "record",
            "--policy",
            "random",
            "--episodes",
            "2",
            "--steps",
            "30",
            "--estimator",
            "oracle",
            "--seed",
            "4",
            "--out",
            str(tmp_path / "bags"),
        ]
    )
    assert rc == 0
    bags = sorted((tmp_path / "bags").iterdir())
    assert [b.name for b in bags] == ["episode_000", "episode_001"]
    with BagReader(bags[1]) as reader:
        assert reader.run_info["policy"] == "random"
        assert reader.run_info["seed"] == 4 and reader.run_info["episode"] == 1
        assert reader.command_count == 30
    out = tmp_path / "est"
    rc = cli_main(
        ["estimate", str(bags[0]), "--estimator", "ukf", "--out", str(out), "--no-progress"]
    )
    assert rc == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["steps"] == 30 and metrics["estimator"] == "ukf"
    assert metrics["finite"] and metrics["reinitialisations"] == 0
    assert 0.0 < metrics["com_rmse_m"] < 0.05
    for key in (
        "ate_rmse_m",
        "rpe_rmse_m",
        "com_final_error_m",
        "com_drift_percent",
        "rods_within_2cm_5deg",
    ):
        assert key in metrics
    for name in ("com_path.png", "error.png", "estimates.npz"):
        assert (out / name).stat().st_size > 0
    # evo reads the trajectories, and agrees on the aligned error
    from evo.core import metrics as evo_metrics
    from evo.core import sync
    from evo.tools import file_interface

    est = file_interface.read_tum_trajectory_file(str(out / "estimate.tum"))
    ref = file_interface.read_tum_trajectory_file(str(out / "truth.tum"))
    assert est.num_poses == ref.num_poses == 31
    ref, est = sync.associate_trajectories(ref, est)
    est.align(ref, correct_scale=False)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    stats = ape.get_all_statistics()
    assert stats["rmse"] == pytest.approx(metrics["ate_rmse_m"], abs=1e-4)


def test_estimate_reports_bad_input_without_a_traceback(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.ERROR):
        assert cli_main(["estimate", str(tmp_path / "none"), "--out", str(tmp_path / "o")]) == 2
    assert "no such file or folder" in caplog.text
    with pytest.raises(SystemExit):
        cli_main(["estimate", str(tmp_path), "--estimator", "kalman", "--out", str(tmp_path)])


def test_interrupted_recording_leaves_a_closed_bag(tmp_path: Path) -> None:
    from agents.recordings import offline

    calls = 0

    def interrupting_policy(obs: np.ndarray) -> np.ndarray:
        nonlocal calls
        calls += 1
        if calls == 15:
            raise KeyboardInterrupt
        return np.zeros(6, dtype=np.float32)

    original = offline.make_policy
    offline.make_policy = lambda name, env, seed: (interrupting_policy, lambda: None)  # type: ignore[assignment]
    try:
        with pytest.raises(KeyboardInterrupt):
            offline.record(THREE_BAR, "random", 1, tmp_path / "bags", steps=50, estimator="oracle")
    finally:
        offline.make_policy = original
    bag = tmp_path / "bags" / "episode_000"
    assert (bag / "metadata.yaml").exists()  # closed properly, not merely recoverable
    with BagReader(bag) as reader:
        assert not reader.recovered
        assert reader.command_count == 14
        assert sum(1 for _ in reader.periods()) == 15


def test_record_rejects_an_unknown_policy(tmp_path: Path) -> None:
    from agents.recordings.offline import record

    with pytest.raises(ValueError, match="not one of \\['scripted', 'random'\\]"):
        record(THREE_BAR, "clever", 1, tmp_path, steps=2, estimator="oracle")


def test_env_record_dir_numbers_episodes_and_keeps_old_ones(tmp_path: Path) -> None:
    env = gym.make(THREE_BAR, estimator="oracle", record_dir=tmp_path, max_episode_steps=3)
    for seed in (0, 1):
        env.reset(seed=seed)
        for _ in range(3):
            env.step(env.action_space.sample())
    env.close()
    env = gym.make(THREE_BAR, estimator="oracle", record_dir=tmp_path, max_episode_steps=3)
    env.reset(seed=2)
    env.close()
    inner = cast("TensegrityEnv", env.unwrapped)
    assert [p.name for p in sorted(tmp_path.iterdir())] == [
        "episode_000",
        "episode_001",
        "episode_002",
    ]
    assert inner.backend.sink.paths[-1].name == "episode_002"  # type: ignore[attr-defined]
    assert len(read_run(tmp_path / "episode_001").steps) == 3


def test_a_bag_written_with_rosbags_alone_runs_through_the_ukf(tmp_path: Path) -> None:
    """The recordings page's promise: a lab's own bag (examples/write_bag_with_rosbags.py) reads."""
    import runpy

    from agents.recordings.offline import estimate_bag
    from tensegrity_gym.model.kinematics import center_of_mass

    example = Path(__file__).parents[2] / "examples" / "write_bag_with_rosbags.py"
    runpy.run_path(str(example), run_name="example")["main"](tmp_path / "lab_bag")
    with BagReader(tmp_path / "lab_bag") as reader:
        assert reader.command_count == 49 and not reader.has_truth
        assert reader.control_period == pytest.approx(0.1)  # inferred from the commands
        periods = list(reader.periods())
        assert not reader.skipped
    assert len(periods) == 50
    kinds = {type(s).__name__ for p in periods for s in p.samples}
    assert kinds == {"AhrsSample", "EncoderSample", "UwbRangeSample"}
    [metrics] = estimate_bag(tmp_path / "lab_bag", "ukf", tmp_path / "out", progress=False)
    assert metrics["finite"] and metrics["steps"] == 49 and "com_rmse_m" not in metrics
    d = load_robot("three_bar")
    com = np.load(tmp_path / "out" / "estimates.npz")["com"]
    nominal = center_of_mass(d.initial_positions, d.node_masses)
    assert np.linalg.norm(com[-1, :2] - nominal[:2]) < 0.05


def test_a_sqlite3_bag_reads_as_its_mcap_twin(tmp_path: Path) -> None:
    """A lab's bag in ROS 2's older default storage (sqlite3, ``.db3``): the same
    messages copied into one with rosbags' own writer read back sample for sample."""
    from rosbags.rosbag2 import Reader, StoragePlugin, Writer

    live = _record(tmp_path, "three_bar", 8, camera=False)
    mcap_bag = tmp_path / "rec" / "episode_000"
    twin = tmp_path / "db3_bag"
    with (
        Reader(mcap_bag) as source,
        Writer(twin, version=9, storage_plugin=StoragePlugin.SQLITE3) as sink,
    ):
        copies = {
            c.id: sink.add_connection(
                c.topic, c.msgtype, msgdef=c.msgdef.data, rihs01=c.digest,
                offered_qos_profiles=c.ext.offered_qos_profiles,
            )
            for c in source.connections
        }  # fmt: skip
        for connection, ns, raw in source.messages():
            sink.write(copies[connection.id], ns, raw)
    assert list(twin.glob("*.db3")) and not list(twin.glob("*.mcap"))
    back = read_run(twin)
    assert back.description == live.description
    assert len(back.steps) == len(live.steps) == 8
    _assert_same_step(back.start, live.start, "start")
    for k, (x, y) in enumerate(zip(back.steps, live.steps, strict=True)):
        _assert_same_step(x, y, f"step {k}")


def test_a_broken_sqlite3_bag_is_one_line(tmp_path: Path) -> None:
    from hardware.bag import BagError

    bag = tmp_path / "broken"
    bag.mkdir()
    (bag / "broken_0.db3").write_bytes(b"not a database at all" * 10)
    with pytest.raises(BagError, match=r"broken: cannot open the sqlite3 bag: ") as caught:
        read_run(bag)
    assert "\n" not in str(caught.value)
