"""What viewers see (issue 19): /tf and markers in bags, the URDF on /robot_description,
old bags with YAML there, wall-clock stamps, and the live Foxglove view.

Bags are decoded with Foxglove's own libraries (``mcap`` and ``mcap-ros2-support``),
not ours, and compared frame by frame with the recorded states. The live view is
checked with a WebSocket client speaking the Foxglove protocol under either of its
names (``foxglove.websocket.v1``, ``foxglove.sdk.v1``; issue 40). The URDF is loaded
in PyBullet (issue 40: masses and inertia, no defaults).
"""

from __future__ import annotations

import json
import socket
import struct
import subprocess
import sys
import threading
import time
import xml.etree.ElementTree as ET
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.records import Schema
from mcap_ros2.decoder import DecoderFactory
from rosbags.rosbag2 import Reader, StoragePlugin, Writer

import tensegrity_gym  # noqa: F401  (registers the envs)
from agents.cli import main as cli_main
from hardware.bag import BagReader
from hardware.bag import messages as m
from hardware.bag.codec import description_yaml
from hardware.link.process import free_port
from hardware.viewer import INSTALL_HINT, ViewerError
from tensegrity_gym.model.description import PRESETS, dump_robot, load_robot
from tensegrity_gym.model.lie import quat_to_matrix
from tensegrity_gym.model.urdf import robot_urdf

if TYPE_CHECKING:
    from collections.abc import Iterator

ENV = "tensegrity_gym/ThreeBarRoll-v0"
STEPS = 12
PERIOD_NS = 100_000_000  # the env's control period, 0.1 s


@cache
def _recorded(root: str) -> Path:
    """One episode of random actions recorded by the env, markers on (the default)."""
    before = time.time_ns()
    env = gym.make(ENV, record_dir=root, max_episode_steps=STEPS)
    env.reset(seed=1)
    rng = np.random.default_rng(1)
    done = False
    while not done:
        *_, terminated, truncated, _ = env.step(rng.uniform(-1, 1, env.action_space.shape))
        done = terminated or truncated
    env.close()
    (Path(root) / "before_ns").write_text(str(before))
    return Path(root) / "episode_000"


@pytest.fixture(scope="module")
def bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _recorded(str(tmp_path_factory.mktemp("viewer")))


def _decoded(bag: Path) -> Iterator[tuple[str, int, Any]]:
    """(topic, log time ns, message) of every message, decoded by Foxglove's decoder."""
    [mcap] = bag.glob("*.mcap")
    with mcap.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, message, decoded in reader.iter_decoded_messages():
            yield channel.topic, message.log_time, decoded


def _stamp(msg: Any) -> int:
    return int(msg.header.stamp.sec) * 10**9 + int(msg.header.stamp.nanosec)


def _xyz(p: Any) -> list[float]:
    return [p.x, p.y, p.z]


def _xyzw(q: Any) -> list[float]:
    return [q.x, q.y, q.z, q.w]


def test_tf_and_markers_decode_with_foxglove_and_match_the_recorded_states(bag: Path) -> None:
    by_topic: dict[str, list[tuple[int, Any]]] = {}
    for topic, ns, msg in _decoded(bag):
        by_topic.setdefault(topic, []).append((ns, msg))
    poses = {
        tree: {_stamp(msg): msg for _, msg in by_topic[f"/{src}/rod_poses"]}
        for tree, src in (("truth", "ground_truth"), ("estimate", "estimate"))
    }
    states = {_stamp(msg): msg for _, msg in by_topic["/ground_truth/state"]}
    tfs, markers = by_topic[m.TF_TOPIC], by_topic[m.MARKERS_TOPIC]
    assert len(tfs) == len(markers) == STEPS + 1  # the reset's estimate, then one a step
    nis = [msg.data for _, msg in by_topic[m.NIS_TOPIC]]  # the UKF's innovations
    assert len(nis) >= STEPS - 1 and np.all(np.isfinite(nis)) and min(nis) >= 0.0
    assert np.all(np.diff([ns for ns, _ in tfs]) == PERIOD_NS)  # at the control rate
    rods = [r.name for r in load_robot("three_bar").rods]
    for (_, tf), (_, array) in zip(tfs, markers, strict=True):
        frames = {t.child_frame_id: t for t in tf.transforms}
        assert sorted(frames) == sorted(f"{tree}/{r}" for tree in poses for r in rods)
        for tree, recorded in poses.items():
            for k, rod in enumerate(rods):
                t = frames[f"{tree}/{rod}"]
                assert t.header.frame_id == "world"
                pose = recorded[_stamp(t)].poses[k]  # the rod poses of that instant
                assert _xyz(t.transform.translation) == _xyz(pose.position)
                assert _xyzw(t.transform.rotation) == _xyzw(pose.orientation)
        _check_markers(array, frames, states[_stamp(frames[f"truth/{rods[0]}"])], rods)


def _check_markers(array: Any, frames: dict[str, Any], state: Any, rods: list[str]) -> None:
    """One MarkerArray against the TF of its instant and the true state."""
    d = load_robot("three_bar")
    first, *markers = array.markers
    assert first.action == 3  # DELETEALL, then the scene
    by_ns: dict[str, list[Any]] = {}
    for marker in markers:
        assert marker.header.frame_id == "world"
        by_ns.setdefault(marker.ns, []).append(marker)
    assert sorted(by_ns) == sorted(
        [
            f"{tree}/{part}"
            for tree in ("truth", "estimate")
            for part in ("rods", "endcaps", "cables")
        ]
        + ["anchors", "goal"]
    )
    for tree, alpha in (("truth", 1.0), ("estimate", 0.35)):
        for k, cylinder in enumerate(by_ns[f"{tree}/rods"]):
            assert cylinder.type == 3 and cylinder.color.a == pytest.approx(alpha)
            assert _xyz(cylinder.pose.position) == _xyz(
                frames[f"{tree}/{rods[k]}"].transform.translation
            )
            assert cylinder.scale.z == pytest.approx(d.rods[k].length)
            assert [cylinder.color.r, cylinder.color.g, cylinder.color.b] == pytest.approx(
                d.rods[k].color[:3]
            )
        [lines] = by_ns[f"{tree}/cables"]
        assert lines.type == 5 and len(lines.points) == len(lines.colors) == 2 * d.n_cables
    spheres = by_ns["truth/endcaps"]
    assert [_xyz(s.pose.position) for s in spheres] == [_xyz(p) for p in state.node_positions]
    assert len(by_ns["anchors"]) == len(d.anchors)


def test_the_urdf_names_one_link_per_rod_and_is_the_bags_robot_description(bag: Path) -> None:
    for name in PRESETS:
        d = load_robot(name)
        root = ET.fromstring(robot_urdf(d))
        links = [link.get("name") for link in root.iter("link")]
        assert links == ["world", *(r.name for r in d.rods)]
        joints = list(root.iter("joint"))
        assert [j.get("type") for j in joints] == ["floating"] * d.n_rods
        assert [j.find("parent").get("link") for j in joints] == ["world"] * d.n_rods  # type: ignore[union-attr]
        for link, rod in zip(root.iter("link"), (None, *d.rods), strict=False):
            if rod is not None:
                shapes = [v.find("geometry")[0].tag for v in link.iter("visual")]  # type: ignore[index]
                assert shapes == ["cylinder", "sphere", "sphere"]
    text = {t: msg.data for t, _, msg in _decoded(bag) if t in m.HEADER_TOPICS[:2]}
    assert text[m.DESCRIPTION_TOPIC] == robot_urdf(load_robot("three_bar"))
    assert text[m.DESCRIPTION_YAML_TOPIC] == dump_robot(load_robot("three_bar"))


def test_tf_static_holds_the_camera_and_every_endcap_under_its_rod(bag: Path) -> None:
    """/tf_static, decoded by Foxglove's decoder: once, the camera under world at the
    calibration's pose, each endcap under its rod frame at -+length/2 along z; an endcap
    frame composed with its rod's /tf is where the true state puts that node."""
    by_topic: dict[str, list[Any]] = {}
    for topic, _, msg in _decoded(bag):
        by_topic.setdefault(topic, []).append(msg)
    [static] = by_topic[m.TF_STATIC_TOPIC]
    frames = {t.child_frame_id: t for t in static.transforms}
    d = load_robot("three_bar")
    trees = ("truth", "estimate")
    assert sorted(frames) == sorted(["camera", *(f"{t}/{n.name}" for t in trees for n in d.nodes)])
    with BagReader(bag) as reader:
        pose = reader.calibration.camera_pose
    camera = frames["camera"]
    assert camera.header.frame_id == "world"
    assert _xyz(camera.transform.translation) == pytest.approx(pose[:3, 3], abs=1e-12)
    rotation = quat_to_matrix(_xyzw(camera.transform.rotation))
    assert rotation == pytest.approx(pose[:3, :3], abs=1e-12)
    for tree in trees:
        for rod in d.rods:
            for k, z in zip(rod.nodes, (-0.5, 0.5), strict=True):
                t = frames[f"{tree}/{d.nodes[k].name}"]
                assert t.header.frame_id == f"{tree}/{rod.name}"
                assert _xyz(t.transform.translation) == [0.0, 0.0, z * rod.length]
                assert _xyzw(t.transform.rotation) == [0.0, 0.0, 0.0, 1.0]
    tf = {t.child_frame_id: t for t in by_topic[m.TF_TOPIC][0].transforms}
    state = next(s for s in by_topic["/ground_truth/state"]
                 if _stamp(s) == _stamp(tf["truth/red"]))  # fmt: skip
    for i, node in enumerate(d.nodes):
        endcap = frames[f"truth/{node.name}"]
        rod = tf[endcap.header.frame_id].transform
        x = np.array(_xyz(rod.translation)) + quat_to_matrix(_xyzw(rod.rotation)) @ np.array(
            _xyz(endcap.transform.translation)
        )
        assert x == pytest.approx(_xyz(state.node_positions[i]), abs=1e-9)


_LOAD_URDF = """
import json, sys
import pybullet as p
c = p.connect(p.DIRECT)
body = p.loadURDF(sys.argv[1], flags=p.URDF_USE_INERTIA_FROM_FILE, physicsClientId=c)
links = [p.getDynamicsInfo(body, j, physicsClientId=c) for j in range(p.getNumJoints(body))]
with open(sys.argv[2], "w") as out:  # not stdout, where PyBullet's lines run into ours
    json.dump([[info[0], list(info[2])] for info in links], out)
"""


def _load_in_pybullet(urdf: str, tmp_path: Path) -> tuple[str, list[tuple[float, list[float]]]]:
    """PyBullet's output (its C-level warnings: stdout and stderr of a process of its
    own) on loading ``urdf``, and the mass (kg) and inertia diagonal (kg m^2) of each
    link after the root."""
    path, result = tmp_path / "robot.urdf", tmp_path / "links.json"
    path.write_text(urdf)
    done = subprocess.run([sys.executable, "-c", _LOAD_URDF, str(path), str(result)],
                          capture_output=True, text=True, timeout=120, check=True)  # fmt: skip
    links = json.loads(result.read_text())
    return done.stdout + done.stderr, [(mass, inertia) for mass, inertia in links]


def _shapes(link: ET.Element, kind: str) -> list[tuple[dict[str, str], str, dict[str, str]]]:
    """(origin, geometry, size) of each ``kind`` (visual, collision) element of a link."""
    out = []
    for element in link.iter(kind):
        origin, geometry = element.find("origin"), element.find("geometry")
        assert origin is not None and geometry is not None
        out.append((origin.attrib, geometry[0].tag, geometry[0].attrib))
    return out


NO_INERTIAL = "No inertial data for link"
"""PyBullet's warning for a link without <inertial>: it then makes up a mass of 1 kg."""


def test_the_urdf_loads_in_pybullet_with_the_descriptions_masses(tmp_path: Path) -> None:
    """Each rod link has an inertial (the rod's mass, a solid cylinder's inertia of its
    radius and length) and collisions that are its visuals' shapes; PyBullet loads it
    without making up a mass. (A link without inertial is loaded too, to show that the
    warning is caught where there is one.)"""
    bare = '<robot name="bare"><link name="world"/><link name="rod"/>' + (
        '<joint name="j" type="fixed"><parent link="world"/><child link="rod"/></joint></robot>'
    )
    output, _ = _load_in_pybullet(bare, tmp_path)
    assert NO_INERTIAL in output
    for name in PRESETS:
        d = load_robot(name)
        urdf = robot_urdf(d)
        for link in list(ET.fromstring(urdf).iter("link"))[1:]:
            assert _shapes(link, "collision") == _shapes(link, "visual")
            assert len(_shapes(link, "visual")) == 3
        output, links = _load_in_pybullet(urdf, tmp_path)
        assert NO_INERTIAL not in output, output
        assert len(links) == d.n_rods
        for rod, (mass, inertia) in zip(d.rods, links, strict=True):
            assert mass == rod.mass
            across = rod.mass * (3 * rod.radius**2 + rod.length**2) / 12
            assert inertia == pytest.approx([across, across, rod.mass * rod.radius**2 / 2])


def _old_style(src: Path, dst: Path) -> Path:
    """``src`` as bags were written before the URDF: YAML on /robot_description, no
    YAML topic of its own, no /tf or markers."""
    store = m.typestore()
    with Reader(src) as reader, Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP) as out:
        conns: dict[str, Any] = {}
        for conn, ns, raw in reader.messages():
            topic = conn.topic
            if topic in (m.DESCRIPTION_TOPIC, *m.VIEW_TOPICS):
                continue
            if topic == m.DESCRIPTION_YAML_TOPIC:
                topic = m.DESCRIPTION_TOPIC
            if topic not in conns:
                conns[topic] = out.add_connection(topic, conn.msgtype, typestore=store)
            out.write(conns[topic], ns, raw)
    return dst


def test_old_bags_with_yaml_on_robot_description_read_as_before(bag: Path, tmp_path: Path) -> None:
    old = _old_style(bag, tmp_path / "old")
    with BagReader(old) as reader_old, BagReader(bag) as reader_new:
        assert m.DESCRIPTION_YAML_TOPIC not in reader_old.topics
        assert reader_old.description == reader_new.description == load_robot("three_bar")
        a, b = list(reader_old.periods()), list(reader_new.periods())
        assert not reader_old.skipped and not reader_new.skipped  # /tf, markers: no skips
        assert not reader_new.unknown_topics
    assert [len(p.samples) for p in a] == [len(p.samples) for p in b]
    assert all(np.array_equal(p.truth.node_positions, q.truth.node_positions)  # type: ignore[union-attr]
               for p, q in zip(a, b, strict=True))  # fmt: skip


def test_a_simulated_run_is_stamped_from_the_wall_clock(bag: Path) -> None:
    before = int((bag.parent / "before_ns").read_text()) // 10**9 * 10**9
    with BagReader(bag) as reader:
        assert before <= reader.clock_origin_ns <= time.time_ns()
        [start, *_] = reader.periods()
        assert 0.0 <= start.samples[0].t < 1.0  # sample times stay small


def test_record_writes_markers_unless_told_not_to(tmp_path: Path) -> None:
    for flag, expected in (("--markers", True), ("--no-markers", False)):
        out = tmp_path / flag
        args = ["record", "--policy", "random", "--steps", "2", "--out", str(out), flag]
        assert cli_main(args) == 0
        with BagReader(out / "episode_000") as reader:
            assert (m.TF_TOPIC in reader.topics) is expected
            assert (m.MARKERS_TOPIC in reader.topics) is expected
            assert m.DESCRIPTION_TOPIC in reader.topics


def test_the_yaml_is_found_on_its_topic_or_where_older_senders_put_it() -> None:
    """The bag reader's and the robot link's one rule: the YAML's own topic first, else
    YAML (not a URDF) on /robot_description."""
    d = load_robot("three_bar")
    store = m.typestore()

    def string(text: str) -> bytes:
        return bytes(store.serialize_cdr(store.types[m.STRING](data=text), m.STRING))

    yaml_text, urdf = dump_robot(d), robot_urdf(d)
    new = {m.DESCRIPTION_YAML_TOPIC: string(yaml_text), m.DESCRIPTION_TOPIC: string(urdf)}
    assert description_yaml(new, store) == (m.DESCRIPTION_YAML_TOPIC, yaml_text)
    old = {m.DESCRIPTION_TOPIC: string(yaml_text)}
    assert description_yaml(old, store) == (m.DESCRIPTION_TOPIC, yaml_text)
    assert description_yaml({m.DESCRIPTION_TOPIC: string(urdf)}, store) is None
    assert description_yaml({}, store) is None


def test_the_robot_link_takes_the_yaml_from_either_topic() -> None:
    """The driver checks the robot's description on its new topic, and on
    /robot_description where an older robot sends its YAML; a URDF there is not
    mistaken for it."""
    from hardware.link.driver import ZenohDriver
    from hardware.link.wire import LinkError
    from tensegrity_gym.model.protocols import SensorCalibration

    d = load_robot("three_bar")
    n = d.n_nodes + len(d.anchors)
    calibration = SensorCalibration(np.zeros((n, n)), d.anchors, d.sensors.camera.intrinsics,
                                    np.eye(4))  # fmt: skip
    driver = ZenohDriver(d, "zenoh/tcp/127.0.0.1:9")  # never connected
    header = dict(driver.codec.encode_header(calibration, {"control_period": 0.1}, 0.0))
    yaml_raw = header.pop(m.DESCRIPTION_YAML_TOPIC)
    other = load_robot("superball")
    store = m.typestore()
    other_raw = bytes(store.serialize_cdr(store.types[m.STRING](data=dump_robot(other)), m.STRING))
    for description_topics, refused in (
        ({m.DESCRIPTION_YAML_TOPIC: yaml_raw}, False),  # with the URDF: today's robots
        ({m.DESCRIPTION_TOPIC: yaml_raw}, False),  # an older robot: YAML, no URDF
        ({m.DESCRIPTION_TOPIC: other_raw}, True),  # an older robot of another kind
    ):
        driver._header = {**header, **description_topics}
        if refused:
            with pytest.raises(LinkError, match="superball"):
                driver._read_header()
        else:
            driver._read_header()
            assert driver.calibration.anchors.shape == d.anchors.shape


def test_view_streams_an_episode_and_stops() -> None:
    port = free_port()
    args = ["view", "--port", str(port), "--episodes", "1", "--steps", "3", "--speed", "0"]
    assert cli_main([*args, "--policy", "random"]) == 0
    assert _port_is_free(port)


def test_foxglove_render_mode_without_the_sdk_is_a_one_line_error(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setitem(sys.modules, "foxglove", None)  # import foxglove fails
    with pytest.raises(ViewerError, match=r"pip install tensegrity-gym\[viewer\]") as err:
        gym.make(ENV, render_mode="foxglove", viewer_port=free_port())
    assert str(err.value) == INSTALL_HINT


# ---------------------------------------------------------------------- live view


SUBPROTOCOLS = ["foxglove.websocket.v1", "foxglove.sdk.v1"]
"""The protocol's names: foxglove-sdk 0.30's server accepts only the second, whose
messages (serverInfo, advertise, subscribe, messageData) are those of the first; the
live view's relay (hardware/foxglove_relay.py) takes either."""


class _Client:
    """A Foxglove WebSocket client: the server's info and channels, subscriptions,
    and the messages of subscribed channels with their arrival (monotonic) times."""

    def __init__(self, ws: Any) -> None:
        self.ws = ws
        assert ws.subprotocol in SUBPROTOCOLS
        self.channels: dict[str, dict[str, Any]] = {}
        self.info = json.loads(self.ws.recv(timeout=5))
        self._subscribed: dict[int, str] = {}
        self.received: list[tuple[str, int, float, bytes]] = []

    def wait_for(self, topics: set[str], timeout: float = 10.0) -> None:
        deadline = time.monotonic() + timeout
        while not topics <= set(self.channels):
            self._handle(self.ws.recv(timeout=max(0.01, deadline - time.monotonic())))

    def subscribe(self, topics: list[str]) -> None:
        subs = [{"id": k, "channelId": self.channels[t]["id"]} for k, t in enumerate(topics)]
        self._subscribed = dict(enumerate(topics))
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def drain(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            try:
                self._handle(self.ws.recv(timeout=left))
            except TimeoutError:
                return

    def _handle(self, frame: str | bytes) -> None:
        if isinstance(frame, str):
            msg = json.loads(frame)
            if msg["op"] == "advertise":
                self.channels.update({c["topic"]: c for c in msg["channels"]})
            return
        if frame[0] == 1:  # messageData: opcode, subscription id, log time, payload
            sub, ns = struct.unpack_from("<IQ", frame, 1)
            self.received.append((self._subscribed[sub], ns, time.monotonic(), frame[13:]))

    def decoder(self, topic: str) -> Any:
        c = self.channels[topic]
        assert (c["encoding"], c["schemaEncoding"]) == ("cdr", "ros2msg")
        schema = Schema(id=1, name=c["schemaName"], encoding="ros2msg", data=c["schema"].encode())
        return DecoderFactory().decoder_for("cdr", schema)


def _port_is_free(port: int) -> bool:
    """Nothing listens on ``port``: a connection is refused, and a server may bind it
    (SO_REUSEADDR, as servers do: the closed client's connection may be in TIME_WAIT)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        if s.connect_ex(("127.0.0.1", port)) == 0:
            return False
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def test_the_live_view_streams_tf_and_markers_at_the_control_rate_and_stops_with_the_env() -> None:
    from websockets.sync.client import connect

    port = free_port()
    env = gym.make(ENV, render_mode="foxglove", viewer_port=port, max_episode_steps=100)
    try:
        with connect(f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS) as ws:
            client = _Client(ws)
            _watch(env, client)
    finally:
        env.close()
    assert _port_is_free(port)  # the server stopped with the env
    _check_stream(client)


STEPS_LIVE = 15


def _watch(env: gym.Env[Any, Any], client: _Client) -> None:
    """Reset, subscribe to /tf and the markers, and watch :data:`STEPS_LIVE` steps."""
    assert client.info["op"] == "serverInfo"
    env.reset(seed=0)  # the first messages advertise the channels
    client.wait_for({m.TF_TOPIC, m.MARKERS_TOPIC, "/estimate/state", "/uwb/ranges"})
    client.subscribe([m.TF_TOPIC, m.MARKERS_TOPIC])
    client.drain(0.2)
    client.received.clear()
    thread = threading.Thread(
        target=lambda: [env.step(env.action_space.sample()) for _ in range(STEPS_LIVE)]
    )
    thread.start()
    while thread.is_alive():  # however slow the machine, every step's messages
        client.drain(0.2)
    thread.join()
    client.drain(0.5)


def _check_stream(client: _Client) -> None:
    """One TF and one marker message a step, 0.1 s apart in log time and (paced at run
    time) roughly so on the wall clock, each decodable with its advertised schema."""
    tf = [(ns, at, raw) for topic, ns, at, raw in client.received if topic == m.TF_TOPIC]
    markers = [raw for topic, _, _, raw in client.received if topic == m.MARKERS_TOPIC]
    assert len(tf) == len(markers) == STEPS_LIVE
    assert np.all(np.diff([ns for ns, _, _ in tf]) == PERIOD_NS)
    wall = tf[-1][1] - tf[0][1]  # paced: never faster than the run's time
    assert 0.7 * (STEPS_LIVE - 1) * 0.1 < wall < 10.0 * (STEPS_LIVE - 1) * 0.1
    decode_tf, decode_markers = client.decoder(m.TF_TOPIC), client.decoder(m.MARKERS_TOPIC)
    frames = {t.child_frame_id for t in decode_tf(tf[-1][2]).transforms}
    rods = ("red", "green", "blue")
    assert frames == {f"{tree}/{r}" for tree in ("truth", "estimate") for r in rods}
    namespaces = {mk.ns for mk in decode_markers(markers[-1]).markers}
    assert {"truth/rods", "estimate/rods", "truth/cables", "anchors", "goal"} <= namespaces


@pytest.mark.parametrize("subprotocol", SUBPROTOCOLS)
def test_the_live_view_speaks_either_name_of_the_protocol(subprotocol: str) -> None:
    """A client asking for one name (Lichtblick and ws-protocol: the first; Foxglove's
    app: the second) is answered with it, gets serverInfo and the channels, subscribes
    (its messages reach the server through the relay) and receives the URDF and
    /tf_static, which the live view sends again every second of run time."""
    from websockets.sync.client import connect

    port = free_port()
    env = gym.make(ENV, render_mode="foxglove", viewer_port=port, viewer_speed=0,
                   max_episode_steps=100)  # fmt: skip
    try:
        with connect(f"ws://127.0.0.1:{port}", subprotocols=[subprotocol]) as ws:
            assert ws.subprotocol == subprotocol
            client = _Client(ws)
            assert client.info["op"] == "serverInfo" and client.info["name"] == "tensegrity-gym"
            env.reset(seed=0)
            client.wait_for({m.DESCRIPTION_TOPIC, m.TF_STATIC_TOPIC, m.TF_TOPIC})
            client.subscribe([m.DESCRIPTION_TOPIC, m.TF_STATIC_TOPIC])
            client.drain(0.2)
            for _ in range(11):  # past 1 s of run time: the header and /tf_static again
                env.step(env.action_space.sample())
            client.drain(0.5)
    finally:
        env.close()
    assert _port_is_free(port)
    got = {topic: raw for topic, _, _, raw in client.received}
    assert set(got) == {m.DESCRIPTION_TOPIC, m.TF_STATIC_TOPIC}
    urdf = client.decoder(m.DESCRIPTION_TOPIC)(got[m.DESCRIPTION_TOPIC]).data
    assert urdf == robot_urdf(load_robot("three_bar"))
    static = client.decoder(m.TF_STATIC_TOPIC)(got[m.TF_STATIC_TOPIC])
    assert {"camera", "truth/n0", "estimate/n5"} <= {t.child_frame_id for t in static.transforms}


def test_the_relay_rewrites_only_the_subprotocol_header() -> None:
    from hardware.foxglove_relay import LEGACY_SUBPROTOCOL, SDK_SUBPROTOCOL, rewrite_protocol

    def head(*headers: str) -> bytes:
        return "\r\n".join(["GET / HTTP/1.1", "Host: h", *headers, "", ""]).encode()

    old, new = LEGACY_SUBPROTOCOL, SDK_SUBPROTOCOL
    legacy = head("sec-websocket-protocol: x, foxglove.websocket.v1", "Sec-WebSocket-Key: k")
    out, changed = rewrite_protocol(legacy, old, new)
    assert changed and out == head("Sec-WebSocket-Key: k", f"Sec-WebSocket-Protocol: {new}")
    both = head(f"Sec-WebSocket-Protocol: {old}", f"Sec-WebSocket-Protocol: {new}")
    for unchanged in (both, head(), head("Sec-WebSocket-Protocol: other")):
        assert rewrite_protocol(unchanged, old, new) == (unchanged, False)
    response = "HTTP/1.1 101 Switching Protocols\r\nSec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n"
    back, changed = rewrite_protocol(response.encode(), SDK_SUBPROTOCOL, LEGACY_SUBPROTOCOL)
    assert changed and back == response.replace("sdk", "websocket").encode()


def _relay_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "foxglove-relay"]


def test_the_live_view_closes_with_a_client_connected_and_one_mid_handshake() -> None:
    """close() returns at once however its clients behave: one connected (it gets a
    close), one that never finishes its handshake (dropped); the port is free and the
    relay's thread gone."""
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    from hardware.viewer import FoxgloveSink

    sink = FoxgloveSink(free_port(), speed=0)
    stalled = socket.create_connection(("127.0.0.1", sink.port))
    stalled.sendall(b"GET / HTTP/1.1\r\nHost: localhost\r\n")  # and no blank line
    with connect(f"ws://127.0.0.1:{sink.port}", subprotocols=SUBPROTOCOLS[:1]) as ws:
        assert json.loads(ws.recv(timeout=5))["op"] == "serverInfo"
        start = time.monotonic()
        sink.close()
        took = time.monotonic() - start
        with pytest.raises(ConnectionClosed):
            ws.recv(timeout=5)
    with stalled:
        stalled.settimeout(5)
        try:
            assert stalled.recv(1) == b""
        except ConnectionResetError:
            pass  # dropped: as good as closed
    assert took < 2.0 and _port_is_free(sink.port)
    assert not _relay_threads()
    sink.close()  # twice is fine


def test_a_taken_port_is_a_one_line_viewer_error() -> None:
    from hardware.viewer import FoxgloveSink

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(ViewerError, match=f"on 127.0.0.1:{port}: ") as err:
            FoxgloveSink(port)
    assert "\n" not in str(err.value)
    assert not _relay_threads()


def _named_topics(node: Any) -> set[str]:
    """Every topic a Foxglove layout's panels name: plot series (the message path's
    topic), topic settings, image and layer topics."""
    found: set[str] = set()
    if isinstance(node, list):
        for item in node:
            found |= _named_topics(item)
    elif isinstance(node, dict):
        for key, value in node.items():
            if key == "value" and isinstance(value, str) and value.startswith("/"):
                found.add(value.split(".")[0])
            elif key in ("imageTopic", "topic") and isinstance(value, str):
                found.add(value)
            elif key == "topics" and isinstance(value, dict):
                found |= set(value)
            else:
                found |= _named_topics(value)
    return found


def test_the_foxglove_layout_is_built_by_the_sdk_and_names_the_robots_topics(bag: Path) -> None:
    """examples/foxglove_layout.json is what hardware.foxglove_layout builds with
    foxglove-sdk's layout classes, and every topic it names is in the robot's topic
    table (the camera's, where an estimator uses it) or is its script's output."""
    from hardware.foxglove_layout import COM_ERROR_TOPIC, layout_json

    path = Path(__file__).parents[2] / "examples" / "foxglove_layout.json"
    assert path.read_text() == layout_json(), "run: python -m hardware.foxglove_layout " + str(path)
    layout = json.loads(path.read_text())
    with BagReader(bag) as reader:
        topics = set(reader.codec.topics.types)
    [script] = layout["userScripts"].values()
    for name in ("/ground_truth/state", "/estimate/state"):
        assert f'"{name}"' in script["sourceCode"] and name in topics
    named = _named_topics(layout["content"])
    assert named - {COM_ERROR_TOPIC} <= topics, named - topics
    assert {m.MARKERS_TOPIC, m.NIS_TOPIC, m.DESCRIPTION_TOPIC, COM_ERROR_TOPIC} <= named
    panels = json.dumps(layout["content"])
    assert all(f'"panelType": "{p}"' in panels for p in ("ThreeDee", "Plot", "Image"))


@pytest.mark.slow
def test_view_streams_a_robot_on_the_link() -> None:
    """The live view of a robot: the emulator on the network, driven by random actions
    (slow: the emulator's start and the robot's settling, about 15 s)."""
    from agents.recordings.view import view
    from hardware.link.process import EmulatorProcess

    port = free_port()
    with EmulatorProcess("three_bar") as emulator:
        done = view("tensegrity_gym_hardware/ThreeBarRoll-v0", "random", driver=emulator.address,
                    port=port, episodes=1, steps=3)  # fmt: skip
    assert done == 1 and _port_is_free(port)
