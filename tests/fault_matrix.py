"""The fault matrix: what a hostile but fair user does wrong, and what must come of it.

Each :class:`Fault` is run in a process of its own (a crash, a hang or a traceback is
then seen as such, not masked by the test runner) and must end as its row says: a
command-line mistake in exit status 2 with one ``ERROR`` line matching ``expect`` and no
traceback; a Python mistake in one exception line matching it; a fault the project
survives in exit status 0 with its output matching it. Every run is bounded by
``timeout`` (s): a hang fails the row.

``tests/test_fault_matrix.py`` runs every row in the slow suite (``bash scripts/test.sh
-m slow -k fault_matrix``); ``python -m tests.fault_matrix [NAME ...]`` runs them here and
prints one line a row. The rows' inputs (bags, maps, broken files) are made by
:func:`make_inputs` into one folder.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import re
import subprocess
import sys
import tempfile
import textwrap
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml

if TYPE_CHECKING:
    from collections.abc import Callable

    from tensegrity_gym.model.samples import Sample

ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Fault:
    """One row of the matrix.

    Args:
        name: what is done wrong, in a few words.
        kind: ``"cli"`` (``argv`` to ``tensegrity-gym``, exit 2 and one ERROR line),
            ``"api"`` (``code``, Python, must raise one exception line), or ``"ok"``
            (``code`` or ``argv`` must exit 0, its stdout and stderr matching).
        expect: a regular expression the error line (or the output) must match.
        argv: the command line, ``{inputs}`` and ``{out}`` filled in.
        code: a Python snippet, ``INPUTS`` and ``OUT`` (paths) defined for it.
        timeout: seconds the row may take, start-up included.
        since: where the fault was found (``39`` for issue 39, ``earlier`` for the
            matrix before it).
    """

    name: str
    kind: str
    expect: str
    argv: tuple[str, ...] = ()
    code: str = ""
    timeout: float = 120.0
    since: str = "39"


@dataclass(frozen=True)
class Outcome:
    fault: Fault
    passed: bool
    seconds: float
    why: str


# ---------------------------------------------------------------------- inputs


def robot_bag(
    path: Path,
    *,
    periods: int = 25,
    commands: bool = True,
    edit: Callable[[Sample], Sample] | None = None,
) -> Path:
    """A 3-bar bag of ``periods`` at rest (0.1 s each) with ground truth; ``edit``
    changes samples; without ``commands`` the command topic is left out."""
    from hardware.bag.writer import BagWriter
    from tensegrity_gym.model.description import load_robot
    from tensegrity_gym.sim.backend import SimBackend

    d = load_robot("three_bar")
    sim = SimBackend(d)
    result = sim.reset(np.random.default_rng(1))
    hold = d.rest_lengths[d.actuated]
    change = edit or (lambda s: s)
    with BagWriter(path, d, sim.calibration, {"control_period": 0.1}, flush_period=0.2) as writer:
        for period in range(periods + 1):
            if period and commands:
                writer.write_command(max(s.t for s in result.samples), hold)
            if period:
                result = sim.step(hold)
            writer.write_samples([change(s) for s in result.samples])
            truth = sim.ground_truth()
            assert truth is not None
            writer.write_truth(truth)
    sim.close()
    return path


def foreign_publisher(address: str, session: str) -> tuple[Any, Any]:
    """A raw Zenoh session on the link that publishes, 50 times a second, commands
    driving every motor to its shortest: without a session, and as ``session`` (with
    heartbeats of its own). Returns (session, stop event)."""
    import threading

    from hardware.bag.codec import RobotCodec
    from hardware.link.wire import COMMAND_TOPIC, HEARTBEAT_TOPIC, LinkAddress, open_session
    from tensegrity_gym.model.description import load_robot

    robot = load_robot("three_bar")
    link = LinkAddress.parse(address)
    zsession = open_session(link, listen=False, timeout=5.0)
    codec = RobotCodec(robot)
    lo, _, _ = robot.motor_limits
    _, anonymous = codec.encode_command(0.0, lo)
    named = codec.serialize(
        codec.store.types["sensor_msgs/msg/JointState"](
            header=codec.header(0.0, session),
            name=codec.actuated_names,
            position=lo,
            velocity=np.empty(0),
            effort=np.empty(0),
        ),
        "sensor_msgs/msg/JointState",
    )
    heartbeat = codec.serialize(codec.header(0.0, session), "std_msgs/msg/Header")
    stop = threading.Event()

    def publish() -> None:
        while not stop.wait(0.02):
            zsession.put(link.key(COMMAND_TOPIC), anonymous)
            zsession.put(link.key(COMMAND_TOPIC), named)
            zsession.put(link.key(HEARTBEAT_TOPIC), heartbeat)

    threading.Thread(target=publish, daemon=True).start()
    return zsession, stop


def absurd_ranges(sample: Sample) -> Sample:
    """A UWB round whose ranges are -50 m and 10 km, alternately; other samples as they are."""
    from tensegrity_gym.model.samples import UwbRangeSample

    if not isinstance(sample, UwbRangeSample):
        return sample
    ranges = np.where(np.arange(len(sample.ranges)) % 2, -50.0, 1e4)
    return dataclasses.replace(sample, ranges=ranges)


def poisoned_imu(sample: Sample) -> Sample:
    """Every other IMU reading's specific force NaN (a sensor's glitch); others as they are."""
    from tensegrity_gym.model.samples import ImuSample

    if not isinstance(sample, ImuSample) or round(sample.t * 1000) % 2:
        return sample
    return dataclasses.replace(sample, accel=np.full(3, np.nan))


def _height_map(folder: Path, name: str, heights: np.ndarray, **sidecar: object) -> None:
    np.save(folder / f"{name}.npy", heights)
    (folder / f"{name}.yaml").write_text(yaml.safe_dump({"cell_size": 0.1, **sidecar}))


CACHE_SECONDS = 12.0
"""The calibration runs of the cache rows: the shortest ``calibrate`` takes."""


def _honest_cache(root: Path) -> Path:
    """A calibration of the 3-bar robot in world 0 made into the cache at ``root``."""
    from tensegrity_gym.envs.calibration import CACHE_VARIABLE, cache_path
    from tensegrity_gym.envs.calibration_run import estimated_uwb_calibration
    from tensegrity_gym.model.description import load_robot

    d = load_robot("three_bar")
    before = os.environ.get(CACHE_VARIABLE)
    os.environ[CACHE_VARIABLE] = str(root)
    try:
        estimated_uwb_calibration(d, world_seed=0, seconds=CACHE_SECONDS)
        return cache_path(d, 0, CACHE_SECONDS)
    finally:
        if before is None:
            del os.environ[CACHE_VARIABLE]
        else:
            os.environ[CACHE_VARIABLE] = before


def make_inputs(folder: Path) -> Path:
    """Every file the rows read, into ``folder``: bags (intact, without commands, with
    absurd UWB ranges, cut short), height maps, broken YAML and binary files."""
    folder.mkdir(parents=True, exist_ok=True)
    bag = robot_bag(folder / "intact", periods=60)
    robot_bag(folder / "no_commands", commands=False)
    robot_bag(folder / "absurd_uwb", edit=absurd_ranges)
    robot_bag(folder / "poisoned_imu", edit=poisoned_imu)
    mcap = next(bag.glob("*.mcap")).read_bytes()
    cut = folder / "cut_short"
    cut.mkdir(exist_ok=True)
    (cut / "cut_short.mcap").write_bytes(mcap[: len(mcap) * 2 // 3])  # a crash mid-write
    heights = np.random.default_rng(0).random((20, 20))
    _height_map(folder, "scaled_1e6", heights, height_scale=1e6)
    _height_map(folder, "nan_origin", heights * 0.01, origin=[float("nan"), float("nan")])
    for lab in ("ours", "theirs"):  # a lab's link credentials, and another lab's
        subprocess.run(
            [sys.executable, str(ROOT / "scripts" / "make_link_certs.py"), str(folder / lab),
             "--host", "127.0.0.1", "--user", "env"],
            check=True, capture_output=True,
        )  # fmt: skip
    ours = folder / "ours"
    (folder / "wrong_password.yaml").write_text(
        f"tls: {{ca: {ours}/ca.pem, certificate: {ours}/env.pem, key: {ours}/env.key}}\n"
        "user: env\npassword: not-the-password\n"
    )
    _honest_cache(folder / "cache")
    (folder / "broken.yaml").write_text("name: x\nrods: [\n  - {a: 1\n")
    (folder / "binary.yaml").write_bytes(bytes(range(256))[::-1] * 4)
    return folder


# ---------------------------------------------------------------------- rows

ENV = "tensegrity_gym/ThreeBarRoll-v0"
HW = "tensegrity_gym_hardware/ThreeBarRoll-v0"
_MAKE = f"import gymnasium as gym, tensegrity_gym\nenv = gym.make({ENV!r}"
_EMULATOR = (
    "import gymnasium as gym, tensegrity_gym\nfrom hardware.link.process import EmulatorProcess\n"
    "from hardware.link.wire import LinkError\nemu = EmulatorProcess('three_bar'"
)
"""A snippet's start: an emulated 3-bar robot ``emu``; the row closes the call (``)``
or ``, security=...)``) and starts it."""

_CACHE = (
    "import logging, os, shutil, sys\nfrom dataclasses import replace\n"
    "import gymnasium as gym, tensegrity_gym\n"
    "from estimation.uwb_calibration import load_calibration, save_calibration\n"
    "from tensegrity_gym.envs.calibration_run import estimated_uwb_calibration\n"
    "from tensegrity_gym.envs.calibration import cache_path\n"
    "from tensegrity_gym.model.description import load_robot\n"
    "logging.basicConfig(level=logging.WARNING, stream=sys.stdout)\n"
    "os.environ['TENSEGRITY_GYM_CACHE'] = OUT + '/cache'\n"
    "shutil.copytree(INPUTS + '/cache', OUT + '/cache', dirs_exist_ok=True)\n"
    "d = load_robot('three_bar')\npath = cache_path(d, 0, 12.0)\n"
)
"""A snippet's start: the honest 12 s cache of :func:`make_inputs` copied into the
row's own cache, ``path`` its file; logging (warnings) on stdout."""

FAULTS: tuple[Fault, ...] = (
    # -- issue 39: crashes and hangs
    Fault("terrain of 3000 x 3000 heights", "api",
          r"^ValueError: make: terrain 'huge' has 3000 x 3000 = 9,000,000 heights; PyBullet's "
          r"heightfield holds at most 4,194,304",
          code="import numpy as np\nfrom tensegrity_gym.sim.terrain import Terrain\n"
          f"{_MAKE}, terrain=Terrain(np.zeros((3000, 3000)), 0.01, name='huge'))\n"
          "env.reset(seed=0)"),
    # -- issue 39: silent wrong results
    Fault("train --hyperparams gamma:2.0", "cli", r"gamma: 2\.0 is not a number in \[0, 1\]",
          argv=("train", "--out", "{out}/t", "--hyperparams", "gamma:2.0")),
    Fault("train --hyperparams n_steps:-5", "cli", r"n_steps: -5 is not a whole number >= 1",
          argv=("train", "--out", "{out}/t", "--hyperparams", "n_steps:-5")),
    Fault("train --hyperparams batch_size:0", "cli", r"batch_size: 0 is not a whole number",
          argv=("train", "--out", "{out}/t", "--hyperparams", "batch_size:0")),
    Fault("terrain origin [nan, nan]", "api", r"origin=\[nan, nan\] must be two finite numbers",
          code=f"{_MAKE}, terrain=INPUTS + '/nan_origin.npy')"),
    Fault("bag with absurd UWB ranges", "ok",
          r"implausible measurements rejected \(uwb_range_negative \d+, uwb_range_too_long \d+\)",
          argv=("estimate", "{inputs}/absurd_uwb", "--out", "{out}/e", "--no-progress")),
    # -- issue 39: errors that did not say what or where
    Fault("binary file as --calibration", "cli",
          r"binary\.yaml.*not a calibration file",
          argv=("estimate", "{inputs}/intact", "--out", "{out}/e", "--no-progress",
                "--calibration", "{inputs}/binary.yaml")),
    Fault("bag without commands", "cli",
          r"no_commands: no /commands/rest_length_targets messages",
          argv=("estimate", "{inputs}/no_commands", "--out", "{out}/e", "--no-progress")),
    Fault("calibrate --seconds nan", "cli", r"argument --seconds",
          argv=("calibrate", "--env", ENV, "--seconds", "nan", "--out", "{out}/c.yaml")),
    Fault("calibrate --seconds 0", "cli", r"argument --seconds",
          argv=("calibrate", "--env", ENV, "--seconds", "0", "--out", "{out}/c.yaml")),
    Fault("calibrate --seconds -5", "cli", r"argument --seconds",
          argv=("calibrate", "--env", ENV, "--seconds", "-5", "--out", "{out}/c.yaml")),
    Fault("calibrate --seconds 1e9", "cli", r"argument --seconds",
          argv=("calibrate", "--env", ENV, "--seconds", "1e9", "--out", "{out}/c.yaml")),
    Fault("calibrate --out into a folder", "cli", r"c_dir",
          argv=("calibrate", "--env", ENV, "--seconds", "60", "--out", "{out}/c_dir"),
          timeout=60.0),
    Fault("identify --segment-seconds 0", "cli", r"argument --segment-seconds",
          argv=("identify", "{inputs}/intact", "--out", "{out}/r.yaml",
                "--segment-seconds", "0")),
    Fault("identify --out a folder", "cli", r"--out '.*c_dir' is a folder, not a file",
          argv=("identify", "{inputs}/intact", "--out", "{out}/c_dir")),
    Fault("view --port 70000", "cli", r"argument --port: must be a TCP port in \[0, 65535\]",
          argv=("view", "--port", "70000")),
    Fault("height_scale=1e6", "api", r"steeper than 100 .*check height_scale",
          code=f"{_MAKE}, terrain=INPUTS + '/scaled_1e6.npy')"),
    Fault("numpy float32 bounds in a Randomization", "ok", r"^\(0\.89999\d*, 1\.10000\d*\)",
          code="import numpy as np\n"
          "from tensegrity_gym.model.randomization import Randomization\n"
          "print(Randomization(rod_mass=(np.float32(0.9), np.float32(1.1))).rod_mass)"),
    Fault("broken description YAML through estimate", "cli",
          r"broken\.yaml: not valid YAML: line 3, column 3: ",
          argv=("estimate", "{inputs}/intact", "--robot", "{inputs}/broken.yaml",
                "--out", "{out}/e", "--no-progress")),
    # -- issue 39: a leak
    Fault("20 envs dropped without close", "ok", r"^connected 0 of 20$",
          code="import gc, pybullet, gymnasium as gym, tensegrity_gym\nclients = []\n"
          f"for seed in range(20):\n    env = gym.make({ENV!r})\n    env.reset(seed=seed)\n"
          "    clients.append(env.unwrapped.backend.world.client)\n    del env\n    gc.collect()\n"
          "    assert not pybullet.getConnectionInfo(clients[-1])['isConnected']\n"
          "print(f'connected {sum(pybullet.getConnectionInfo(c)[\"isConnected\"] for c in "
          "set(clients))} of 20')"),
    # -- issue 39: the robot link
    Fault("a script that never closes its env after a failed reset", "ok",
          r"^LinkError: robot at .*prefix=wrong: no /tensegrity/calibration message within 5 s",
          timeout=40.0,
          code=f"{_EMULATOR}).start()\n"
          f"env = gym.make({HW!r}, driver=emu.address + '?prefix=wrong')\n"
          "try:\n    env.reset(seed=0)\nexcept LinkError as err:\n"
          "    print(f'LinkError: {err}')\n"),
    Fault("another lab's certificate", "api",
          r"^LinkError: could not reach the robot at zenoh/tls/127\.0\.0\.1:\d+\?security=.*"
          r"theirs/env\.yaml within 5 s: .*refused them", timeout=60.0,
          code=f"{_EMULATOR}, security=INPUTS + '/ours/robot.yaml').start()\n"
          f"env = gym.make({HW!r}, driver=emu.address + '?security=' + INPUTS + "
          "'/theirs/env.yaml')\nenv.reset(seed=0)"),
    Fault("a tls endpoint without a security file", "api",
          r"^ValueError: .*a tls/ endpoint needs security=FILE", timeout=30.0,
          code=f"import gymnasium as gym, tensegrity_gym\n"
          f"gym.make({HW!r}, driver='zenoh/tls/127.0.0.1:7447')"),
    Fault("emulate --duration nan", "cli", r"--duration nan must be a finite number",
          argv=("emulate", "--duration", "nan")),
    Fault("another env publishing commands", "ok", r"^held$", timeout=60.0,
          code=f"{_EMULATOR}).start()\nimport numpy as np\n"
          "from hardware.link import ZenohDriver\n"
          "from tests.fault_matrix import foreign_publisher\n"
          "from tensegrity_gym.model.description import load_robot\n"
          "from tensegrity_gym.model.samples import EncoderSample\n"
          "d = load_robot('three_bar')\nhold = d.rest_lengths[d.actuated]\n"
          "driver = ZenohDriver(d, emu.address)\ndriver.reset(np.random.default_rng(0))\n"
          "foreign, stop = foreign_publisher(emu.address, 'intruder')\nworst = 0.0\n"
          "for _ in range(15):\n    for s in driver.step(hold).samples:\n"
          "        if isinstance(s, EncoderSample):\n"
          "            worst = max(worst, float(np.abs(s.rest_lengths - hold).max()))\n"
          "stop.set()\ndriver.close()\nforeign.close()\n"
          "print('held' if worst < 5e-4 else f'moved {1e3 * worst:.2f} mm')"),
    Fault("a wrong password", "api",
          r"^LinkError: could not reach the robot at .*wrong_password\.yaml within 5 s",
          timeout=60.0,
          code=f"{_EMULATOR}, security=INPUTS + '/ours/robot.yaml').start()\n"
          f"env = gym.make({HW!r}, driver=emu.address + '?security=' + INPUTS + "
          "'/wrong_password.yaml')\nenv.reset(seed=0)"),
    # -- issue 39: the calibration cache
    Fault("a cache whose offsets are shifted by 5 m", "ok",
          r"does not fit the first 3 s of ranges .*calibrating again", timeout=120.0,
          code=_CACHE + "c = load_calibration(path)\nn = d.n_nodes\no = c.offsets.copy()\n"
          "o[n:, :n] += 5.0\no[:n, n:] += 5.0\n"
          "save_calibration(path, replace(c.result, offsets=o), robot=c.robot)\n"
          "estimated_uwb_calibration(d, world_seed=0, seconds=12.0)"),
    Fault("a cache with the wrong anchor count", "ok",
          r"it has 4 anchors .* has 8 .*calibrating again", timeout=120.0,
          code=_CACHE + "import numpy as np\nc = load_calibration(path)\n"
          "keep = list(range(d.n_nodes + 4))\n"
          "lab = replace(c.to_calibration(), anchors=c.anchors[:4],\n"
          "              uwb_offsets=c.offsets[np.ix_(keep, keep)])\n"
          "save_calibration(path, lab, robot=d.name)\n"
          "estimated_uwb_calibration(d, world_seed=0, seconds=12.0)"),
    Fault("a cache path that is a folder", "api", r"calibration cache .* is a folder, not a file",
          code=_CACHE + "cache_path(d, 0, 120.0).mkdir(parents=True)  # make's default run\n"
          f"gym.make({ENV!r}, calibration='estimated')"),
    Fault("a binary file as calibration=", "api",
          r"^\w+Error: make: calibration='.*binary\.yaml': not a calibration file: binary",
          code=f"{_MAKE}, calibration=INPUTS + '/binary.yaml')"),
    # -- issue 39: training
    Fault("a training run that diverges", "cli", r"training diverged: non-finite .* timestep",
          timeout=300.0,
          argv=("train", "--out", "{out}/t", "--timesteps", "512", "--n-envs", "1",
                "--hyperparams", "learning_rate:1e30", "n_steps:64", "batch_size:32")),
    # -- the matrix before issue 39
    Fault("the robot dies mid-episode", "api", r"^LinkError: .*no sensor message",
          since="earlier", timeout=60.0,
          code=f"{_EMULATOR}).start()\nenv = gym.make({HW!r}, driver=emu.address)\n"
          "env.reset(seed=0)\n"
          "emu.kill()\nfor _ in range(100):\n    env.step(env.action_space.sample() * 0)"),
    Fault("a NaN action", "api", r"^ValueError: .*action.*finite", since="earlier",
          code=f"import numpy as np\n{_MAKE})\nenv.reset(seed=0)\n"
          "env.step(np.full(env.action_space.shape, np.nan))"),
    Fault("2,000 extreme steps", "ok", r"^finite 2000$", since="earlier", timeout=300.0,
          code=f"import numpy as np\n{_MAKE})\nobs, _ = env.reset(seed=0)\n"
          "rng = np.random.default_rng(0)\nok = 0\nfor _ in range(2000):\n"
          "    a = rng.choice([-1.0, 1.0], size=env.action_space.shape).astype(np.float32)\n"
          "    obs, r, term, trunc, _ = env.step(a)\n"
          "    ok += bool(np.all(np.isfinite(obs)) and np.isfinite(r))\n"
          "    if term or trunc:\n        env.reset()\nprint('finite', ok)"),
    Fault("a bag with NaN IMU readings", "ok", r"^finite \{'undecodable': [1-9]\d*",
          since="earlier",
          code="import json\nfrom pathlib import Path\n"
          "from agents.recordings.offline import estimate_bag\n"
          "[m] = estimate_bag(INPUTS + '/poisoned_imu', 'ukf', Path(OUT) / 'e', progress=False)\n"
          "print('finite' if m['finite'] else 'NOT FINITE', m['skipped_messages'])"),
    Fault("a lossy, jittery, reordering link", "ok", r"^finite 30 of 30$", since="earlier",
          timeout=90.0,
          code="import numpy as np\nimport gymnasium as gym, tensegrity_gym\n"
          "from hardware.link.process import EmulatorProcess\n"
          "emu = EmulatorProcess('three_bar', options=['--loss', '0.5', '--jitter', '0.03', "
          "'--reorder', '0.2', '--seed', '0']).start()\n"
          f"env = gym.make({HW!r}, driver=emu.address)\nobs, _ = env.reset(seed=0)\nok = 0\n"
          "hold = np.zeros(env.action_space.shape, np.float32)\n"
          "for _ in range(30):\n    obs, r, *_ = env.step(hold)\n"
          "    ok += bool(np.all(np.isfinite(obs)) and np.isfinite(r))\n"
          "env.close()\nemu.stop()\nprint(f'finite {ok} of 30')"),
    Fault("a recording cut short by a crash", "ok", r"cut_short: \d+ steps", since="earlier",
          argv=("estimate", "{inputs}/cut_short", "--out", "{out}/e", "--no-progress")),
    Fault("an unknown env id", "cli", r"Environment `Nope` doesn't exist", since="earlier",
          argv=("gait", "--env", "tensegrity_gym/Nope-v0", "--out", "{out}/g")),
    Fault("a bag that is not there", "cli", r"no_such_bag", since="earlier",
          argv=("estimate", "{inputs}/no_such_bag", "--out", "{out}/e")),
)  # fmt: skip


# ---------------------------------------------------------------------- running


def _script(code: str, inputs: Path, out: Path) -> str:
    """``code`` with INPUTS and OUT defined, an exception printed as one line, exit 3."""
    body = textwrap.indent(code, "    ")
    return (
        f"import sys\nINPUTS, OUT = {str(inputs)!r}, {str(out)!r}\ntry:\n{body}\n"
        "except Exception as err:\n"
        "    sys.stderr.write(f'{type(err).__name__}: {err}\\n')\n    sys.exit(3)\n"
    )


def _command(fault: Fault, inputs: Path, out: Path) -> list[str]:
    if fault.argv:
        argv = [a.format(inputs=inputs, out=out) for a in fault.argv]
        return [sys.executable, "-m", "agents.cli", *argv]
    return [sys.executable, "-c", _script(fault.code, inputs, out)]


def _judge(fault: Fault, code: int, stdout: str, stderr: str) -> str | None:
    """Why the run's end is not what ``fault`` asks, or None."""
    if "Traceback" in stderr:
        return f"a traceback:\n{stderr[-2000:]}"
    if code < 0:
        return f"killed by signal {-code}"
    if fault.kind == "ok":
        if code != 0:
            return f"exit {code}:\n{stderr[-2000:]}"
        found = re.search(fault.expect, stdout + stderr, re.MULTILINE)
        return None if found else f"output does not match {fault.expect!r}:\n{stdout[-1000:]}"
    if fault.kind == "cli":
        errors = [ln for ln in stderr.splitlines() if ln.startswith("ERROR") or ": error: " in ln]
        if code != 2 or len(errors) != 1:
            return f"exit {code}, error lines {errors} (want exit 2 and one):\n{stderr[-2000:]}"
        line = errors[0]
    else:
        lines = stderr.strip().splitlines()
        if code != 3 or not lines:
            return f"exit {code} (want an exception):\n{stderr[-2000:]}"
        line = lines[-1]
    return None if re.search(fault.expect, line) else f"{line!r} does not match {fault.expect!r}"


def run_fault(fault: Fault, inputs: Path, out: Path) -> Outcome:
    """Run one row in a process of its own, in ``out`` (made if missing)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "c_dir").mkdir(exist_ok=True)  # a folder where a file belongs
    start = time.monotonic()
    try:
        done = subprocess.run(
            _command(fault, inputs, out),
            capture_output=True, text=True, timeout=fault.timeout, cwd=out,
            env={**os.environ, "PYTHONPATH": str(ROOT)},
        )  # fmt: skip
    except subprocess.TimeoutExpired:
        return Outcome(fault, False, fault.timeout, f"did not end within {fault.timeout:g} s")
    why = _judge(fault, done.returncode, done.stdout, done.stderr)
    return Outcome(fault, why is None, time.monotonic() - start, why or "")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", help="rows whose name contains one of these")
    args = parser.parse_args(argv)
    rows = [f for f in FAULTS if not args.names or any(n in f.name for n in args.names)]
    with tempfile.TemporaryDirectory() as tmp:
        inputs = make_inputs(Path(tmp) / "inputs")
        failed = 0
        for k, fault in enumerate(rows):
            outcome = run_fault(fault, inputs, Path(tmp) / f"row_{k}")
            failed += not outcome.passed
            mark = "ok  " if outcome.passed else "FAIL"
            print(f"{mark} {outcome.seconds:6.1f} s  [{fault.since}] {fault.name}")
            if not outcome.passed:
                print(textwrap.indent(outcome.why, "       "))
    print(f"{len(rows) - failed} of {len(rows)} rows as required")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
