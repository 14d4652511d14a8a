"""Robot link security (issue 39): who may speak on the link, and which env the robot
obeys. Security files and their one-line errors; the lab's credentials from
scripts/make_link_certs.py; TLS with mutual authentication and user-password
authentication against the emulator on loopback (the right credentials connect, wrong
or missing ones fail in one line within the connect timeout and the emulator logs the
refusal); the session identity on commands and heartbeats, and a foreign command
publisher that moves no motor while an env drives."""

from __future__ import annotations

import logging
import re
import runpy
import stat
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest

from hardware.link import DriverTimeouts, LinkAddress, LinkError, ZenohDriver
from hardware.link.ownership import MotorOwner, frame_id_of, new_session_id
from hardware.link.process import EmulatorProcess
from hardware.link.security import LinkSecurity, _ZenohLog
from tensegrity_gym.model.description import load_robot
from tensegrity_gym.model.samples import EncoderSample
from tests.fault_matrix import foreign_publisher

if TYPE_CHECKING:
    from collections.abc import Iterator

THREE_BAR = load_robot("three_bar")
NOMINAL = THREE_BAR.rest_lengths[THREE_BAR.actuated]
SCRIPT = Path(__file__).parents[2] / "scripts" / "make_link_certs.py"
CONNECT = 2.0
"""s: the connect timeout of the refused drivers (each waits it out)."""


def make_link_certs(out: Path, **kwargs: Any) -> dict[str, Path]:
    function = runpy.run_path(str(SCRIPT), run_name="make_link_certs")["make_link_certs"]
    return dict(function(out, **kwargs))


@pytest.fixture(scope="module")
def lab(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A lab's credentials (TLS and a user), another lab's, and a users-only pair."""
    root = tmp_path_factory.mktemp("lab")
    files = make_link_certs(root / "ours", user="env")
    other = make_link_certs(root / "theirs", user="env")
    users_only = root / "users_only"
    users_only.mkdir()
    (users_only / "robot.yaml").write_text(f"users_file: {root / 'ours' / 'users.txt'}\n")
    (users_only / "env.yaml").write_text(
        f"user: env\npassword_file: {root / 'ours' / 'env.password'}\n"
    )
    (users_only / "wrong.yaml").write_text("user: env\npassword: not-the-password\n")
    return {
        "robot": files["robot"],
        "env": files["env"],
        "other_env": other["env"],
        "root": root,
        "users_robot": users_only / "robot.yaml",
        "users_env": users_only / "env.yaml",
        "users_wrong": users_only / "wrong.yaml",
    }


# ---------------------------------------------------------------------- files


def _tls_section(folder: Path, ca: str | None = None, key: str | None = None) -> str:
    """A security file's tls section: the env's certificate in ``folder``."""
    ca, key = ca or f"{folder}/ca.pem", key or f"{folder}/env.key"
    return f"tls:\n  ca: {ca}\n  certificate: {folder}/env.pem\n  key: {key}\n"


def test_make_link_certs_writes_a_ca_and_the_two_sides(tmp_path: Path) -> None:
    import zenoh
    from cryptography import x509
    from cryptography.x509.oid import ExtendedKeyUsageOID

    files = make_link_certs(tmp_path, hosts=["robot.local", "192.168.1.20"], user="env")
    ca = x509.load_pem_x509_certificate((tmp_path / "ca.pem").read_bytes())
    robot = x509.load_pem_x509_certificate((tmp_path / "robot.pem").read_bytes())
    env = x509.load_pem_x509_certificate((tmp_path / "env.pem").read_bytes())
    for cert in (robot, env):
        cert.verify_directly_issued_by(ca)
    names = robot.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert names.get_values_for_type(x509.DNSName) == ["robot.local"]
    assert [str(ip) for ip in names.get_values_for_type(x509.IPAddress)] == ["192.168.1.20"]
    usage = env.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
    assert list(usage) == [ExtendedKeyUsageOID.CLIENT_AUTH]
    for secret in ("ca.key", "robot.key", "env.key", "users.txt", "env.password"):
        assert stat.S_IMODE((tmp_path / secret).stat().st_mode) == 0o600, secret
    assert LinkSecurity.load(files["robot"]).users_file == tmp_path / "users.txt"
    zenoh.Config.from_file(str(tmp_path / "robot_zenoh.json5"))  # for a robot not ours
    assert LinkSecurity.load(files["env"]).user == "env"
    # Run again for a second env: the same CA signs it, the robot keeps its certificate.
    robot_pem = (tmp_path / "robot.pem").read_bytes()
    hosts = ["robot.local", "192.168.1.20"]
    second = make_link_certs(tmp_path, hosts=hosts, env_name="env2", user="env2")
    x509.load_pem_x509_certificate((tmp_path / "env2.pem").read_bytes()).verify_directly_issued_by(
        ca
    )
    assert x509.load_pem_x509_certificate((tmp_path / "ca.pem").read_bytes()) == ca
    assert len((tmp_path / "users.txt").read_text().splitlines()) == 2
    assert LinkSecurity.load(second["env"]).certificate == tmp_path / "env2.pem"
    assert (tmp_path / "robot.pem").read_bytes() == robot_pem
    # A third env without a user: the robot still checks the users it has.
    make_link_certs(tmp_path, hosts=hosts, env_name="env3")
    assert LinkSecurity.load(files["robot"]).users_file == tmp_path / "users.txt"
    with pytest.raises(ValueError, match=r"robot\.pem names other hosts .*--reissue-robot"):
        make_link_certs(tmp_path, hosts=["robot.local"], env_name="env4")
    make_link_certs(tmp_path, hosts=["robot.local"], env_name="env4", reissue_robot=True)
    assert (tmp_path / "robot.pem").read_bytes() != robot_pem


def test_security_options_and_files_are_refused_in_one_line(tmp_path: Path) -> None:
    files = make_link_certs(tmp_path / "lab", user="env")
    env = files["env"]
    (tmp_path / "unknown.yaml").write_text("tls:\n  ca: ca.pem\nsecret: 1\n")
    (tmp_path / "no_password.yaml").write_text("user: env\n")
    (tmp_path / "not_pem.pem").write_text("hello\n")
    (tmp_path / "not_pem.yaml").write_text(_tls_section(env.parent, ca="not_pem.pem"))
    (tmp_path / "gone_key.yaml").write_text(_tls_section(env.parent, key="gone.key"))
    (tmp_path / "bad_users.txt").write_text("env secret\n")
    (tmp_path / "bad_users.yaml").write_text("users_file: bad_users.txt\n")
    tls, tcp = "zenoh/tls/127.0.0.1:7447", "zenoh/tcp/127.0.0.1:7447"
    cases = [
        (f"{tls}?security={tmp_path}/none.yaml", r"security file \S+none\.yaml does not exist"),
        (f"{tls}?security={tmp_path}/unknown.yaml", r"unknown key 'secret'"),
        (f"{tcp}?security={tmp_path}/no_password.yaml", r"user 'env' needs one of password"),
        (f"{tls}?security={tmp_path}/not_pem.yaml", r"tls\.ca file \S+not_pem\.pem holds no PEM"),
        (f"{tls}?security={tmp_path}/gone_key.yaml", r"tls\.key file \S+gone\.key does not exist"),
        (f"{tcp}?security={tmp_path}/bad_users.yaml", r"bad_users\.txt, line 1: expected user:"),
        (tls, r"a tls/ endpoint needs security=FILE"),
        (f"{tcp}?security={env}", r"sets up TLS; the endpoint must be tls/HOST:PORT, not tcp/"),
        (f"{tcp}?security=", r"security= needs a file name"),
        (f"{tcp}?secure=1", r"valid options are .*security=FILE"),
    ]
    for address, words in cases:
        with pytest.raises(ValueError, match=words) as caught:
            LinkAddress.parse(address)
        message = str(caught.value)
        assert "\n" not in message and message.startswith(f"robot address {address!r}"), message
    with pytest.raises(ValueError, match="needs security=FILE"):  # refused at make
        ZenohDriver(THREE_BAR, tls)
    good = LinkAddress.parse(f"{tls}?prefix=lab1&security={env}")
    assert good.security is not None and good.security.tls and good.security.user == "env"
    assert str(good) == f"{tls}?prefix=lab1&security={env}"
    assert "password" not in repr(good.security)  # never in a log or a traceback


def test_session_identity_travels_in_the_header_frame_id() -> None:
    from hardware.bag.codec import RobotCodec

    codec = RobotCodec(THREE_BAR)
    session = new_session_id()
    assert re.fullmatch(r"env@[^:]+:\d+/[0-9a-f]{8}", session) and session != new_session_id()
    raw = codec.serialize(codec.header(0.0, session), "std_msgs/msg/Header")
    assert frame_id_of(raw) == session
    _, command = codec.encode_command(1.0, NOMINAL)
    assert frame_id_of(command) == ""  # what a plain ROS controller sends
    assert frame_id_of(b"\x00\x01\x00\x00") is None and frame_id_of(b"junk" * 8) is None


def test_the_first_session_owns_the_motors_until_its_heartbeats_stop(
    caplog: pytest.LogCaptureFixture,
) -> None:
    log = logging.getLogger("test.owner")
    owner = MotorOwner(0.15, log, clock=lambda: 0.0)
    with caplog.at_level(logging.INFO, logger="test.owner"):
        assert owner.may_command("a", 0.0) and not owner.obeys("a", 0.0)  # before its beat
        assert owner.heartbeat("a", 0.01) and owner.obeys("a", 0.02)
        assert not owner.heartbeat("b", 0.05) and not owner.may_command("b", 0.06)
        assert not owner.may_command(None, 0.07) and not owner.may_command("", 0.08)
        assert not owner.heartbeat("", 0.09)
        assert not owner.obeys("b", 0.1) and not owner.obeys(None, 0.1)
        assert not owner.obeys("a", 0.2)  # a's heartbeats stopped: the motors hold
        assert owner.heartbeat("b", 0.3) and owner.obeys("b", 0.31)  # b takes them
        assert not owner.may_command("a", 0.32)
    assert owner.refused == {"heartbeat": 2, "command": 4}
    assert owner.refused_by == {"b": 2, "(none)": 3, "a": 1}
    lines = [r.getMessage() for r in caplog.records]
    assert "session a owns the motors" in lines
    assert "session b owns the motors (a's heartbeats stopped)" in lines
    refusals = [line for line in lines if line.startswith("refused")]
    assert refusals == [  # the first of each kind from each session (the clock stands)
        "refused a heartbeat from b: session a owns the motors (1 refused from it so far)",
        "refused a command from b: session a owns the motors (2 refused from it so far)",
        "refused a command from (none): it names no session (1 refused from it so far)",
        "refused a heartbeat from (none): it names no session (3 refused from it so far)",
        "refused a command from a: session b owns the motors (1 refused from it so far)",
    ]


def test_zenohs_refusals_are_logged_naming_the_peer(caplog: pytest.LogCaptureFixture) -> None:
    sink = _ZenohLog(logging.getLogger("test.zenoh"))
    lines = [
        "2026-12-06T04:02:46.156151Z DEBUG acc-0 ThreadId(05) zenoh_link_tls::unicast: Accepted "
        "TLS connection on 127.0.0.1:17462: 127.0.0.1:34482. Common Name: env.",
        "\x1b[2m2026-12-06T04:02:46.160469Z\x1b[0m \x1b[34mDEBUG\x1b[0m acc-0 ThreadId(05) "
        "\x1b[2mzenoh_transport::unicast::establishment::accept\x1b[0m\x1b[2m:\x1b[0m UsrPwd "
        "extension - Recv OpenSyn. Invalid password. at /root/x/usrpwd.rs:424.",
        "2026-12-06T04:02:52.163890Z  WARN acc-0 ThreadId(05) zenoh_link_tls::unicast: peer sent "
        "no certificates. Hint: increase the system open file limit.",
        "2026-12-06T04:02:52.163890Z  WARN acc-0 ThreadId(05) zenoh_link_tls::unicast: peer sent "
        "no certificates. Hint: increase the system open file limit.",
        "2026-12-06T04:02:55.167242Z  WARN acc-0 ThreadId(05) zenoh_link_tls::unicast: invalid "
        "peer certificate: BadSignature. Hint: increase the system open file limit.",
        "pybullet build time: Jan  1 2026",
    ]
    with caplog.at_level(logging.INFO, logger="test.zenoh"):
        for line in lines:
            sink.line(line)
    assert [r.getMessage() for r in caplog.records] == [
        "refused 127.0.0.1:34482 (certificate env): wrong user or password",
        "refused a peer: it sent no certificate",  # the second within 5 s is counted only
        "refused a peer: its certificate is not the lab CA's (BadSignature)",
        "pybullet build time: Jan  1 2026",
    ]
    assert all(r.levelno == logging.WARNING for r in caplog.records[:3])


# ---------------------------------------------------------------------- on loopback


@pytest.fixture(scope="module")
def tls_robot(lab: dict[str, Path]) -> Iterator[EmulatorProcess]:
    """The emulator with TLS (mutual) and users, logging to ``lab/tls_robot.log``."""
    with EmulatorProcess(
        "three_bar", security=lab["robot"], log=lab["root"] / "tls_robot.log"
    ) as process:
        yield process


def _drive(driver: ZenohDriver, steps: int = 3) -> None:
    try:
        result = driver.reset(np.random.default_rng(0))
        assert result.samples
        for _ in range(steps):
            assert driver.step(NOMINAL).samples
    finally:
        driver.close()


def _log_lines(path: Path, pattern: str, timeout: float = 5.0) -> list[str]:
    """The emulator log's lines that match ``pattern``, waiting for the first."""
    deadline = time.monotonic() + timeout
    while True:
        text = path.read_text() if path.exists() else ""
        found = [line for line in text.splitlines() if re.search(pattern, line)]
        if found or time.monotonic() > deadline:
            return found
        time.sleep(0.1)


def test_the_right_credentials_drive_the_robot_over_mutual_tls(
    tls_robot: EmulatorProcess, lab: dict[str, Path]
) -> None:
    driver = ZenohDriver(THREE_BAR, f"{tls_robot.address}?security={lab['env']}")
    assert tls_robot.address.startswith("zenoh/tls/")
    _drive(driver)
    log = lab["root"] / "tls_robot.log"
    assert _log_lines(log, r"let in 127\.0\.0\.1:\d+ \(certificate env\)")
    assert _log_lines(log, re.escape(f"session {driver.session_id} owns the motors"))


@pytest.mark.parametrize(
    ("credentials", "refusal"),
    [
        ("none", "it does not speak TLS"),  # plain tcp/ to the TLS port
        ("other_env", r"it broke off the TLS handshake|its certificate is not the lab CA's"),
        ("no_user", "no user or password"),
        ("wrong_password", "wrong user or password"),
    ],
)
def test_wrong_or_missing_credentials_fail_in_one_line_within_the_connect_timeout(
    tls_robot: EmulatorProcess, lab: dict[str, Path], credentials: str, refusal: str
) -> None:
    certs = _tls_section(lab["root"] / "ours")
    files = {
        "no_user": certs,
        "wrong_password": certs + "user: env\npassword: not-the-password\n",
    }
    address = tls_robot.address + f"?security={lab['other_env']}"
    if credentials == "none":
        address = tls_robot.address.replace("zenoh/tls/", "zenoh/tcp/")
    elif credentials in files:
        path = lab["root"] / f"{credentials}.yaml"
        path.write_text(files[credentials])
        address = tls_robot.address + f"?security={path}"
    driver = ZenohDriver(THREE_BAR, address, timeouts=DriverTimeouts(connect=CONNECT))
    t = time.monotonic()
    with pytest.raises(LinkError, match=r"could not reach the robot at zenoh/t\w+/127") as caught:
        driver.connect()
    took = time.monotonic() - t
    driver.close()
    assert "\n" not in str(caught.value) and " at /" not in str(caught.value)
    assert took < CONNECT + 1.5, took
    assert _log_lines(lab["root"] / "tls_robot.log", f"WARNING .*refused .*: (?:{refusal})")


def test_user_and_password_alone_let_the_right_env_in(lab: dict[str, Path], tmp_path: Path) -> None:
    log = tmp_path / "robot.log"
    with EmulatorProcess("three_bar", security=lab["users_robot"], log=log) as process:
        assert process.address.startswith("zenoh/tcp/")
        _drive(ZenohDriver(THREE_BAR, f"{process.address}?security={lab['users_env']}"), 1)
        for address in (f"{process.address}?security={lab['users_wrong']}", process.address):
            driver = ZenohDriver(THREE_BAR, address, timeouts=DriverTimeouts(connect=CONNECT))
            with pytest.raises(LinkError, match="could not reach the robot"):
                driver.connect()
            driver.close()
    assert _log_lines(log, r"refused 127\.0\.0\.1:\d+: wrong user or password")
    assert _log_lines(log, r"refused 127\.0\.0\.1:\d+: no user or password")


def test_a_foreign_command_publisher_moves_no_motor_while_the_env_drives(
    tmp_path: Path,
) -> None:
    import zenoh

    from hardware.link.wire import COMMAND_TOPIC, HEARTBEAT_TOPIC, open_session

    log = tmp_path / "robot.log"
    with EmulatorProcess("three_bar", log=log) as process:
        driver = ZenohDriver(THREE_BAR, process.address)
        seen: dict[str, set[str | None]] = {COMMAND_TOPIC: set(), HEARTBEAT_TOPIC: set()}
        listener = open_session(LinkAddress.parse(process.address), listen=False, timeout=5.0)
        subscribers = [
            listener.declare_subscriber(
                topic.lstrip("/"),
                lambda s, t=topic: seen[t].add(frame_id_of(s.payload.to_bytes())),
                allowed_origin=zenoh.Locality.ANY,
            )
            for topic in seen
        ]
        driver.reset(np.random.default_rng(0))
        foreign, stop = foreign_publisher(process.address, "intruder")
        encoders = []
        try:
            for _ in range(15):
                result = driver.step(NOMINAL)
                encoders += [s.rest_lengths for s in result.samples if isinstance(s, EncoderSample)]
            others = driver.link_counts().get("other_controller", 0)  # the env notices it
        finally:
            stop.set()
            driver.close()
            for subscriber in subscribers:
                subscriber.undeclare()
            listener.close()
            foreign.close()
    assert len(encoders) > 100 and others > 20
    # One obeyed tick of the foreign command would move a motor 1.5 mm (0.15 m/s).
    worst = float(np.max(np.abs(np.array(encoders) - NOMINAL)))
    assert worst < 5e-4, f"a motor moved {worst * 1000:.2f} mm off the env's command"
    assert driver.session_id in seen[COMMAND_TOPIC] and driver.session_id in seen[HEARTBEAT_TOPIC]
    assert _log_lines(log, r"WARNING .*refused a command from \(none\): it names no session")
    owner = re.escape(f"session {driver.session_id} owns the motors")
    assert _log_lines(log, rf"WARNING .*refused a heartbeat from intruder: {owner}")
    assert _log_lines(log, rf"WARNING .*refused a command from intruder: {owner}")
    [stats] = _log_lines(log, r"emulator stopped: ")
    refused = int(re.search(r"refused_commands=(\d+)", stats).group(1))  # type: ignore[union-attr]
    assert refused > 20, stats


def test_an_envs_security_file_on_the_robots_side_is_refused(lab: dict[str, Path]) -> None:
    """A users-only env file given to the emulator would listen with no check at all."""
    import zenoh

    security = LinkSecurity.load(lab["users_env"])
    with pytest.raises(ValueError, match=r"the robot's side needs tls or users_file"):
        security.apply(zenoh.Config(), listen=True)
    security.apply(zenoh.Config(), listen=False)  # the env's side takes it
