"""Make a lab's credentials for the robot link: a CA, the robot's certificate, an env's
certificate (TLS with mutual authentication) and, optionally, a user and password.

    python scripts/make_link_certs.py OUT --host robot.local --host 192.168.1.20 \\
        [--env-name env] [--user env] [--days 825]

Writes into the folder OUT (made if missing; private keys readable by their owner only):

- ``ca.pem``, ``ca.key``: the lab's certificate authority. The key signs every other
  certificate: keep it off the robot and the lab's machines once they are issued. An
  OUT that already holds both is reused, so that running the script again with another
  ``--env-name`` issues another env's certificate from the same CA.
- ``robot.pem``, ``robot.key``: the robot's (server) certificate, naming every
  ``--host`` (DNS names and IP addresses, as the env's address writes the robot:
  ``zenoh/tls/robot.local:7447`` needs ``--host robot.local``); default
  ``localhost`` and ``127.0.0.1``.
- ``ENV_NAME.pem``, ``ENV_NAME.key``: an env's (client) certificate.
- ``robot.yaml`` and ``ENV_NAME.yaml``: the two sides' security files, pointing at the
  files beside them. The robot's side::

      tensegrity-gym emulate --listen tls/0.0.0.0:7447 --security OUT/robot.yaml

  and the env's::

      gym.make(ENV_ID, driver="zenoh/tls/robot.local:7447?security=OUT/env.yaml")

- With ``--user NAME``: a random password, added to ``users.txt`` (the robot's list of
  ``user:password`` lines) and written to ``NAME.password`` for the env; both security
  files then name them, and the robot refuses a peer without a listed user.
- ``robot_zenoh.json5``: the same for a robot that is not ours, as a Zenoh
  configuration (``transport/link/tls``, ``transport/auth/usrpwd``): for
  zenoh-bridge-ros2dds (``-c robot_zenoh.json5``) or
  ``examples/robot_node_with_zenoh.py``. Its paths are absolute: edit them where the
  files are copied elsewhere.

Copy ``ca.pem``, ``robot.*`` and ``users.txt`` to the robot, ``ca.pem`` and the env's
files to the machine that runs the env. Needs the ``cryptography`` package.
"""

from __future__ import annotations

import argparse
import datetime
import ipaddress
import json
import logging
import os
import secrets
import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from collections.abc import Sequence

    from cryptography import x509
    from cryptography.hazmat.primitives.asymmetric import ec

log = logging.getLogger(__name__)

DEFAULT_HOSTS = ("localhost", "127.0.0.1")


def _write(path: Path, data: bytes, *, private: bool = False) -> None:
    """Write ``data``; a private file is created readable by its owner only (never
    briefly readable by others: the mode is set at creation)."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC
    fd = os.open(path, flags, 0o600 if private else 0o644)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    if private:
        os.chmod(path, 0o600)  # an existing file keeps its mode through O_CREAT


def _new_key() -> ec.EllipticCurvePrivateKey:
    from cryptography.hazmat.primitives.asymmetric import ec

    return ec.generate_private_key(ec.SECP256R1())


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    from cryptography.hazmat.primitives import serialization

    return key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),  # Zenoh reads unencrypted keys; the file is 0600
    )


def _subject_alt_names(hosts: Sequence[str]) -> list[x509.GeneralName]:
    from cryptography import x509

    names: list[x509.GeneralName] = []
    for host in hosts:
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            names.append(x509.DNSName(host))
    return names


def _certificate(
    name: str,
    key: ec.EllipticCurvePrivateKey,
    issuer: tuple[x509.Certificate, ec.EllipticCurvePrivateKey] | None,
    days: int,
    *,
    hosts: Sequence[str] = (),
    server: bool = False,
) -> x509.Certificate:
    """A certificate for ``name`` signed by ``issuer`` (certificate, key), or the CA's
    own (self-signed) where ``issuer`` is None."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    now = datetime.datetime.now(datetime.timezone.utc)
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)])
    ca = issuer is None
    signer_cert, signer_key = (None, key) if issuer is None else issuer
    builder = (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(subject if signer_cert is None else signer_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))  # clocks a little apart
        .not_valid_after(now + datetime.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=ca, path_length=0 if ca else None), True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), False)
    )
    usage = dict.fromkeys(
        ("content_commitment", "key_encipherment", "data_encipherment", "key_agreement"),
        False,
    )
    builder = builder.add_extension(
        x509.KeyUsage(
            digital_signature=not ca,
            key_cert_sign=ca,
            crl_sign=ca,
            encipher_only=False,
            decipher_only=False,
            **usage,
        ),
        True,
    )
    if signer_cert is not None:
        builder = builder.add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(signer_key.public_key()), False
        )
        purpose = ExtendedKeyUsageOID.SERVER_AUTH if server else ExtendedKeyUsageOID.CLIENT_AUTH
        builder = builder.add_extension(x509.ExtendedKeyUsage([purpose]), False)
    if hosts:
        names = x509.SubjectAlternativeName(_subject_alt_names(hosts))
        builder = builder.add_extension(names, False)
    return builder.sign(signer_key, hashes.SHA256())


def _load_or_make_ca(out: Path, days: int) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import ec

    cert_path, key_path = out / "ca.pem", out / "ca.key"
    if cert_path.exists() and key_path.exists():
        cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
        key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
        if not isinstance(key, ec.EllipticCurvePrivateKey):
            raise ValueError(f"{key_path} is not an EC key made by this script")
        log.info("reusing the CA in %s", cert_path)
        return cert, key
    key = _new_key()
    cert = _certificate("tensegrity-gym lab CA", key, None, days)
    _write(key_path, _key_pem(key), private=True)
    _write(cert_path, _pem(cert))
    return cert, key


def _pem(cert: x509.Certificate) -> bytes:
    from cryptography.hazmat.primitives import serialization

    return cert.public_bytes(serialization.Encoding.PEM)


def _issue(
    out: Path,
    stem: str,
    ca: tuple[x509.Certificate, ec.EllipticCurvePrivateKey],
    days: int,
    hosts: Sequence[str] = (),
    *,
    server: bool,
) -> None:
    key = _new_key()
    cert = _certificate(stem, key, ca, days, hosts=hosts, server=server)
    _write(out / f"{stem}.key", _key_pem(key), private=True)
    _write(out / f"{stem}.pem", _pem(cert))


def _robot_certificate(
    out: Path,
    ca: tuple[x509.Certificate, ec.EllipticCurvePrivateKey],
    days: int,
    hosts: Sequence[str],
    reissue: bool,
) -> None:
    """The robot's certificate: kept where ``out`` has one naming the same ``hosts``
    (the robot already holds it; making an env's files again must not change it), else
    issued; ValueError where one names other hosts and ``reissue`` is not set."""
    from cryptography import x509

    cert_path = out / "robot.pem"
    if reissue or not (cert_path.exists() and (out / "robot.key").exists()):
        _issue(out, "robot", ca, days, hosts, server=True)
        return
    cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
    names = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    if set(names) != set(_subject_alt_names(hosts)):
        raise ValueError(
            f"{cert_path} names other hosts than --host {' '.join(hosts)}: pass "
            "--reissue-robot to replace it (and copy the new one to the robot)"
        )
    log.info("keeping the robot's certificate %s", cert_path)


def _add_user(out: Path, user: str) -> str:
    """A fresh random password for ``user`` in ``users.txt`` (replacing the user's old
    line) and ``USER.password``; the password file's name."""
    password = secrets.token_urlsafe(24)
    users = out / "users.txt"
    lines = users.read_text().splitlines() if users.exists() else []
    lines = [line for line in lines if line.partition(":")[0] != user]
    _write(users, ("\n".join([*lines, f"{user}:{password}"]) + "\n").encode(), private=True)
    _write(out / f"{user}.password", (password + "\n").encode(), private=True)
    return f"{user}.password"


def make_link_certs(
    out: str | Path,
    hosts: Sequence[str] = DEFAULT_HOSTS,
    *,
    env_name: str = "env",
    user: str | None = None,
    days: int = 825,
    reissue_robot: bool = False,
) -> dict[str, Path]:
    """Write the files of the module docstring into ``out``; returns the two security
    files: ``{"robot": .../robot.yaml, "env": .../ENV_NAME.yaml}``. Run again for
    another env, it keeps the CA, the robot's certificate (unless ``reissue_robot``)
    and the users already made."""
    if not hosts:
        raise ValueError("at least one --host is needed: the names the env reaches the robot by")
    if env_name == "robot" or not env_name.replace("-", "").replace("_", "").isalnum():
        raise ValueError(f"--env-name {env_name!r}: letters, digits, '-' and '_', not 'robot'")
    if days <= 0:
        raise ValueError(f"--days {days} must be positive")
    if user is not None and (not user or ":" in user or any(c.isspace() for c in user)):
        raise ValueError(f"--user {user!r} must be a non-empty name without ':' or spaces")
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    ca = _load_or_make_ca(folder, max(days, 3650))
    _robot_certificate(folder, ca, days, hosts, reissue_robot)
    _issue(folder, env_name, ca, days, server=False)
    robot = ["tls:", "  ca: ca.pem", "  certificate: robot.pem", "  key: robot.key"]
    env = ["tls:", "  ca: ca.pem", f"  certificate: {env_name}.pem", f"  key: {env_name}.key"]
    if user is not None:
        password_file = _add_user(folder, user)
        env += [f"user: {user}", f"password_file: {password_file}"]
    users = (folder / "users.txt").exists()  # made now or by an earlier run: still checked
    if users:
        robot.append("users_file: users.txt")
    files = {"robot": folder / "robot.yaml", "env": folder / f"{env_name}.yaml"}
    _write(files["robot"], ("\n".join(robot) + "\n").encode())
    _write(files["env"], ("\n".join(env) + "\n").encode())
    _write(folder / "robot_zenoh.json5", _zenoh_config(folder.absolute(), users))
    return files


def _zenoh_config(folder: Path, users: bool) -> bytes:
    """The robot's side as a Zenoh configuration (JSON5), for a robot not run by us."""
    transport: dict[str, object] = {
        "link": {
            "tls": {
                "root_ca_certificate": str(folder / "ca.pem"),
                "listen_certificate": str(folder / "robot.pem"),
                "listen_private_key": str(folder / "robot.key"),
                "enable_mtls": True,
            }
        }
    }
    if users:
        transport["auth"] = {"usrpwd": {"dictionary_file": str(folder / "users.txt")}}
    head = "// The robot's side of the tensegrity-gym link (scripts/make_link_certs.py).\n"
    return (head + json.dumps({"transport": transport}, indent=2) + "\n").encode()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description="Make a lab's CA and the robot's and an env's link credentials."
    )
    parser.add_argument("out", type=Path, help="folder for the files (made if missing)")
    parser.add_argument(
        "--host",
        action="append",
        default=[],
        help="a DNS name or IP address the env reaches the robot by; repeatable "
        f"(default: {' '.join(DEFAULT_HOSTS)})",
    )
    parser.add_argument("--env-name", default="env", help="the env certificate's name")
    parser.add_argument("--user", default=None, help="also make a user and password")
    parser.add_argument("--days", type=int, default=825, help="days the certificates last")
    parser.add_argument(
        "--reissue-robot",
        action="store_true",
        help="replace the robot's certificate (kept by default when OUT has one)",
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        import cryptography  # noqa: F401
    except ImportError:
        log.error("make_link_certs needs cryptography: pip install 'tensegrity-gym[tls]'")
        return 2
    try:
        files = make_link_certs(
            args.out, args.host or DEFAULT_HOSTS, env_name=args.env_name, user=args.user,
            days=args.days, reissue_robot=args.reissue_robot,
        )  # fmt: skip
    except (ValueError, OSError) as err:
        log.error("%s", err)
        return 2
    log.info("robot side: --security %s", files["robot"])
    log.info("env side:   ?security=%s", files["env"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
