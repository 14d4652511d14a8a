"""The MuJoCo world of one robot: the only module of the project that imports mujoco.

The same robot as :class:`~tensegrity_gym.sim.world.PhysicsWorld` (PyBullet), from the
same description through :func:`~tensegrity_gym.sim.mjcf.robot_mjcf`, behind the same
methods, so that :class:`~tensegrity_gym.sim.backend.SimBackend`'s sensor models, noise
and timing serve both engines; only reading the true state differs. Cables are tendons
pulled by actuators (see :mod:`tensegrity_gym.sim.mjcf`), so a physics step runs in
MuJoCo's C code alone: a period is a few ``mj_step`` calls of many steps each, split
where a motor reaches its target or a sensor samples.

Motors slew their rest lengths toward the targets at the speed limit, as PyBullet's do
(:func:`~tensegrity_gym.sim.cables.slew_motors`): the actuator's activation (the rest
length) integrates a rate set to the speed limit, or, on the step that reaches the
target, to what is left; the activation is then set to the target exactly.

Rendering (the RGB-D camera, ``render()``) uses MuJoCo's offscreen renderer; on a Linux
machine without a display it asks for EGL (``MUJOCO_GL=egl``) unless told otherwise.
"""

from __future__ import annotations

import functools
import math
import os
import sys
import weakref
from typing import TYPE_CHECKING, Any

import numba
import numpy as np

from tensegrity_gym.model.kinematics import (
    member_lengths,
    rod_node_states,
    rod_quaternion_from_axis,
)
from tensegrity_gym.model.lie import quat_to_matrix
from tensegrity_gym.model.samples import ns_to_seconds
from tensegrity_gym.sim.mjcf import MIN_CONTACT_STEPS, hfield_data, robot_mjcf
from tensegrity_gym.sim.world import Snapshot

if sys.platform.startswith("linux") and not os.environ.get("DISPLAY"):
    os.environ.setdefault("MUJOCO_GL", "egl")  # headless: GLFW has no window to open

try:
    import mujoco
except ImportError as err:  # pragma: no cover - tested by hiding the module
    raise ImportError(
        "the MuJoCo engine needs mujoco: pip install 'tensegrity-gym[mujoco]'"
    ) from err

if TYPE_CHECKING:
    from collections.abc import Sequence

    from numpy.typing import NDArray

    from tensegrity_gym.model.description import CameraConfig, RobotDescription
    from tensegrity_gym.sim.terrain import Terrain

__all__ = ["MujocoCheckpoint", "MujocoWorld", "can_render", "stiff_contacts_world"]

MujocoCheckpoint = tuple[Any, list[float], list[float], int]
"""MuJoCo's integration state (physics, controls: the passive cables' rest lengths, the
motors' rates), the rest lengths, the motors' targets, the clock (ns)."""

_STATE = mujoco.mjtState.mjSTATE_INTEGRATION  # physics, controls and warm start
_BLOWN_UP = np.array(
    [
        int(mujoco.mjtWarning.mjWARN_BADQACC),
        int(mujoco.mjtWarning.mjWARN_BADQVEL),
        int(mujoco.mjtWarning.mjWARN_BADQPOS),
    ]
)


def stiff_contacts_world(
    description: RobotDescription,
    time_step: float,
    gui: bool = False,
    terrain: Terrain | None = None,
) -> MujocoWorld:
    """The engine ``mujoco_stiff``: MuJoCo's world with contacts as stiff as it integrates
    (a time constant of :data:`~tensegrity_gym.sim.mjcf.MIN_CONTACT_STEPS` physics
    steps, 2 ms at 1 kHz, against 5 ms by default), as MuJoCo models of tensegrity robots
    written elsewhere often set them: impacts end within a few milliseconds, hard
    enough to clip the accelerometer, and the robot hops more. A world to test an
    estimator on, not one tuned to agree with PyBullet's."""
    return MujocoWorld(
        description, time_step, gui=gui, terrain=terrain, contact_steps=MIN_CONTACT_STEPS
    )


@functools.cache
def can_render() -> str | None:
    """None where MuJoCo's offscreen renderer starts on this machine, else why not."""
    try:
        model = mujoco.MjModel.from_xml_string("<mujoco><worldbody/></mujoco>")
        renderer = mujoco.Renderer(model, 8, 8)
    except Exception as err:  # any failure of the GL stack means no
        return _first_line(err)
    renderer.close()
    return None


def _first_line(err: BaseException) -> str:
    """The error's type and the first line of its message."""
    text = str(err).splitlines()[0] if str(err) else ""
    return f"{type(err).__name__}: {text}"


class MujocoWorld:
    """A MuJoCo model and data holding one robot on the ground.

    Args:
        description: the robot.
        time_step: physics step (s).
        gui: refused: MuJoCo's window is not offered (use ``render_mode="rgb_array"``).
        terrain: the ground: None or a flat one is the plane z = 0, another a height
            field; :meth:`_build` (each episode) builds the current :attr:`terrain`.
    """

    def __init__(
        self,
        description: RobotDescription,
        time_step: float,
        gui: bool = False,
        terrain: Terrain | None = None,
        contact_steps: float | None = None,
    ) -> None:
        if gui:
            raise RuntimeError(
                "render_mode='human' is not offered on engine 'mujoco'; use render_mode='rgb_array'"
            )
        self.description = description
        self.time_step = time_step
        self.terrain = terrain
        self.contact_steps = contact_steps
        """The contacts' time constant in physics steps (:func:`robot_mjcf`); None: the default."""
        self.gravity = np.array([0.0, 0.0, -description.gravity])
        """(3,) m/s^2 in the world frame, set at the next :meth:`_build`."""
        self._time_step_ns = round(time_step * 1e9)
        self.time_ns = 0
        """Simulated time in whole nanoseconds: stamps stay exact through a ROS bag."""
        self._key: tuple[object, ...] | None = None
        self._built_terrain: Terrain | None = None
        self._renderers: dict[tuple[int, int], Any] = {}
        self._release = weakref.finalize(self, _close_renderers, self._renderers)
        self.rest_lengths: list[float] = description.rest_lengths.tolist()
        """The rest lengths (m), (n_cables,), as of the last period's end."""
        self.targets: list[float] = [self.rest_lengths[k] for k in description.actuated]
        self.trace: list[tuple[NDArray[np.float64], NDArray[np.float64], int]] | None = None
        """None, or a list to which :meth:`advance` appends each ``mj_step`` call: the
        controls (nu,), the motors' rest lengths (na,) it started from and its steps;
        :meth:`replay` steps them again (the physics of the traced periods alone)."""
        self._build()

    # ------------------------------------------------------------------ construction

    def reconfigure(self, description: RobotDescription, gravity: NDArray[np.float64]) -> None:
        """Build the next episode (:meth:`_build`) with another ``description`` of the
        same robot and ``gravity`` (3,) m/s^2."""
        if description.n_cables != self.description.n_cables or (
            description.n_rods != self.description.n_rods
        ):
            raise ValueError(f"reconfigure: {description.name} is not this world's robot")
        self.description = description
        self.gravity = np.asarray(gravity, dtype=np.float64).copy()

    def _build(self) -> None:
        """A fresh episode: the model compiled anew where the robot, gravity or ground
        changed, the data reset (bit for bit the same start for the same inputs)."""
        d = self.description
        key = (d, self.gravity.tobytes(), self.time_step)
        if key != self._key or not _same_ground(self.terrain, self._built_terrain):
            text = robot_mjcf(d, time_step=self.time_step, gravity=self.gravity,
                              terrain=self.terrain, contact_steps=self.contact_steps)  # fmt: skip
            self.model = mujoco.MjModel.from_xml_string(text)
            if self.terrain is not None and not self.terrain.is_flat:
                self.model.hfield_data[:] = hfield_data(self.terrain)
            self.data = mujoco.MjData(self.model)
            self._configure(d)
            _close_renderers(self._renderers)
            self._key, self._built_terrain = key, self.terrain
        else:
            mujoco.mj_resetData(self.model, self.data)
        self._apply_rest_lengths()
        mujoco.mj_forward(self.model, self.data)

    def _configure(self, d: RobotDescription) -> None:
        """What stepping reads of the robot: motors, cables, the layout of the state."""
        self._half = np.array([0.5 * r.length for r in d.rods])
        self._actuated = np.asarray(d.actuated, dtype=np.intp)
        self._passive = np.setdiff1d(np.arange(d.n_cables), self._actuated)
        lo, hi, speed = d.motor_limits
        self._motor_lo, self._motor_hi, self._speed = lo, hi, speed
        self._max_step = speed * self.time_step  # m per physics step
        self._least = d.motor_min_stretch  # NaN: the cable may go slack
        self._held = ~np.isnan(self._least)
        self._any_held = bool(self._held.any())
        self._rate = np.zeros(d.n_actuated)  # the motors' rest-length rates (m/s)
        self._arrive = np.zeros(d.n_actuated, dtype=np.bool_)
        self._rod_nodes = np.asarray(d.rod_nodes, dtype=np.int64)
        r, n = d.n_rods, d.n_nodes
        self._rod_buffers = tuple(
            np.empty(shape) for shape in ((r, 3), (r, 4), (r, 3), (r, 3), (n, 3))
        )
        self._ground_geom = self.model.geom(0).id  # the floor or the height field is first

    @property
    def flat_ground(self) -> bool:
        """The ground is the plane z = 0 (no terrain, or a flat one)."""
        return self.terrain is None or self.terrain.is_flat

    def ground_heights(self, xy: NDArray[np.float64]) -> NDArray[np.float64]:
        """The ground's surface height (m) under each world (x, y) of ``xy`` (k, 2) (m),
        by a vertical ray (k,); NaN where the ray meets a rod first or no ground."""
        pts = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        top = 1.0 + (0.0 if self.flat_ground else float(self.terrain.heights.max()))  # type: ignore[union-attr]
        down = np.array([0.0, 0.0, -1.0])
        geom = np.zeros(1, dtype=np.int32)
        out = np.full(len(pts), np.nan)
        for i, (x, y) in enumerate(pts.tolist()):
            start = np.array([x, y, top])
            distance = mujoco.mj_ray(self.model, self.data, start, down, None, 1, -1, geom)
            if distance >= 0.0 and geom[0] == self._ground_geom:
                out[i] = top - distance
        return out

    # ------------------------------------------------------------------ state access

    def set_node_positions(self, nodes: NDArray[np.float64]) -> None:
        """Place each rod so its endcaps sit at the given nodes (n, 3), at rest."""
        rn = self.description.rod_nodes
        axes = nodes[rn[:, 1]] - nodes[rn[:, 0]]
        q = rod_quaternion_from_axis(axes / np.linalg.norm(axes, axis=1, keepdims=True))
        self.set_rod_states(0.5 * (nodes[rn[:, 0]] + nodes[rn[:, 1]]), q)

    def set_rod_states(
        self,
        positions: NDArray[np.float64],
        quaternions: NDArray[np.float64],
        linear: NDArray[np.float64] | None = None,
        angular: NDArray[np.float64] | None = None,
    ) -> None:
        """Set every rod's pose (r, 3), (r, 4) (x, y, z, w) and velocities (r, 3) in the
        world frame (zero if omitted)."""
        n = self.description.n_rods
        q = np.asarray(quaternions, dtype=np.float64)
        qpos = self.data.qpos.reshape(n, 7)
        qpos[:, :3] = positions
        qpos[:, 3] = q[:, 3]
        qpos[:, 4:] = q[:, :3]
        qvel = self.data.qvel.reshape(n, 6)
        qvel[:, :3] = 0.0 if linear is None else linear
        # A free joint's angular velocity is in the body frame.
        w = np.zeros((n, 3)) if angular is None else np.asarray(angular, dtype=np.float64)
        qvel[:, 3:] = np.einsum("rji,rj->ri", quat_to_matrix(q), w)
        mujoco.mj_forward(self.model, self.data)

    def set_rest_lengths(self, rest_lengths: Sequence[float] | NDArray[np.float64]) -> None:
        """Set all cables' rest lengths (m); actuated targets follow."""
        self.rest_lengths = [float(x) for x in rest_lengths]
        self.targets = [self.rest_lengths[k] for k in self.description.actuated]
        self._apply_rest_lengths()

    def _apply_rest_lengths(self) -> None:
        """Write :attr:`rest_lengths` into the data: passive cables' controls, the motors'
        activations."""
        rest = np.array(self.rest_lengths)
        self.data.ctrl[:] = 0.0
        self.data.ctrl[self._passive] = rest[self._passive]
        self.data.act[:] = rest[self._actuated]

    @property
    def spool_lengths(self) -> list[float]:
        """The rest lengths in effect (m), (n_cables,), what the encoders read: the
        motors' positions, or shorter where a motor holding a minimum tension has reeled
        in slack (the endcap distance less that tension's stretch)."""
        return self._spool(self._rod_arrays()[4])

    def _spool(self, nodes: NDArray[np.float64]) -> list[float]:
        """:attr:`spool_lengths` now (the motors' rest lengths mid-period included), with
        the nodes (n, 3) at hand."""
        rest = self._rest_now()
        if self._any_held:
            k = self._actuated[self._held]
            lengths = member_lengths(nodes, self.description.cable_nodes[k])
            rest[k] = np.minimum(rest[k], lengths - self._least[self._held])
        return [float(x) for x in rest]

    def _rod_arrays(self) -> tuple[NDArray[np.float64], ...]:
        """Centres (r, 3), quaternions (r, 4) (x, y, z, w), linear and angular velocities
        (r, 3) in the world frame, and the nodes (n, 3), from the free joints' state."""
        out = self._rod_buffers
        _read_rods(self.data.qpos, self.data.qvel, self._half, self._rod_nodes, *out)
        return tuple(a.copy() for a in out)

    def rod_states(
        self,
    ) -> tuple[
        list[tuple[float, float, float]],
        list[tuple[float, float, float, float]],
        list[tuple[float, float, float]],
        list[tuple[float, float, float]],
    ]:
        """Positions, quaternions (x, y, z, w), linear and angular velocities of the rods."""
        pos, orn, lin, ang = (list(map(tuple, a.tolist())) for a in self._rod_arrays()[:4])
        return pos, orn, lin, ang

    def node_states(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Node positions and velocities, each (n, 3)."""
        pos, orn, lin, ang, _ = self._rod_arrays()
        return rod_node_states(pos, orn, lin, ang, self._half, self.description.rod_nodes)

    # ------------------------------------------------------------------ stepping

    def advance(
        self, n_steps: int, targets: Sequence[float], snapshot_steps: Sequence[bool]
    ) -> list[Snapshot]:
        """Run ``n_steps`` physics steps toward the actuated rest-length ``targets`` (m).

        ``snapshot_steps[i]`` asks for the state after step i. Returns those snapshots.
        """
        tgt = np.clip(np.asarray(targets, dtype=np.float64), self._motor_lo, self._motor_hi)
        self.targets = tgt.tolist()
        ends = [i + 1 for i in range(n_steps) if snapshot_steps[i]] + [n_steps]
        snapshots: list[Snapshot] = []
        step = 0
        rate, arrive = self._rate, self._arrive
        end = iter(ends)
        due = next(end)
        while step < n_steps:
            hold = _motor_rates(self.data.act, tgt, self._max_step, self._speed,
                                self.time_step, rate, arrive)  # fmt: skip
            stop = min(step + hold, due)
            self.data.ctrl[self._actuated] = rate
            if self.trace is not None:
                self.trace.append((self.data.ctrl.copy(), self.data.act.copy(), stop - step))
            mujoco.mj_step(self.model, self.data, nstep=stop - step)
            self.time_ns += (stop - step) * self._time_step_ns
            if stop - step == hold:  # motors that took their last step sit on the target
                self.data.act[arrive] = tgt[arrive]
            step = stop
            if step == due:
                due = next(end, n_steps)
            if snapshot_steps[step - 1]:
                snapshots.append(self.snapshot())
        self.data.ctrl[self._actuated] = 0.0
        self.rest_lengths = self._rest_now().tolist()
        if self._unstable() and snapshots and snapshot_steps[n_steps - 1]:
            snapshots[-1] = self.snapshot()  # the period's end, as the backend checks it
        return snapshots

    def _unstable(self) -> bool:
        """Whether MuJoCo found the state blown up during the period: it then resets the
        data to the model's start and goes on, so the state is marked NaN here instead,
        for the backend's divergence check to see (the episode ends as on PyBullet)."""
        if not self.data.warning.number[_BLOWN_UP].any():
            return False
        self.data.qpos[:] = np.nan  # the warnings stay until the next reset
        self.data.qvel[:] = np.nan
        return True

    def _rest_now(self) -> NDArray[np.float64]:
        """The rest lengths (m), (n_cables,), now: the motors' where they have moved to."""
        rest = np.array(self.rest_lengths)
        rest[self._actuated] = self.data.act
        return rest

    def step_bare(self, n_steps: int) -> None:
        """``mj_step`` alone at the present controls: the ceiling the benchmark compares
        the env with (the cables pull: in MuJoCo they are part of the model)."""
        mujoco.mj_step(self.model, self.data, nstep=n_steps)

    def replay(self, trace: Sequence[tuple[NDArray[np.float64], NDArray[np.float64], int]]) -> None:
        """``mj_step`` alone through a :attr:`trace`'s calls, each from its controls and
        motors: from the state the trace began at, the same motion, without the env
        around it (the benchmark's ceiling for the env's own periods)."""
        model, data = self.model, self.data
        for ctrl, act, n_steps in trace:
            data.ctrl[:] = ctrl
            data.act[:] = act
            mujoco.mj_step(model, data, nstep=n_steps)

    def save_state(self) -> MujocoCheckpoint:
        """An in-memory checkpoint of the bodies, motors and clock."""
        state = np.empty(mujoco.mj_stateSize(self.model, _STATE))
        mujoco.mj_getState(self.model, self.data, state, _STATE)
        return state, list(self.rest_lengths), list(self.targets), self.time_ns

    def restore_state(self, checkpoint: MujocoCheckpoint) -> None:
        state, rest, targets, t_ns = checkpoint
        mujoco.mj_setState(self.model, self.data, state, _STATE)
        self.data.warning.number[_BLOWN_UP] = 0  # a restored state starts clean
        mujoco.mj_forward(self.model, self.data)
        self.rest_lengths, self.targets, self.time_ns = list(rest), list(targets), t_ns

    @property
    def time(self) -> float:
        """Simulated time (s), a whole number of nanoseconds."""
        return ns_to_seconds(self.time_ns)

    def snapshot(self) -> Snapshot:
        out = self._rod_buffers
        _read_rods(self.data.qpos, self.data.qvel, self._half, self._rod_nodes, *out)
        pos, orn, lin, ang, nodes = (a.tolist() for a in out)
        return Snapshot(self.time, pos, orn, lin, ang, nodes, self._spool(out[4]))

    # ------------------------------------------------------------------ rendering

    def camera_image(
        self,
        camera: CameraConfig,
        width: int | None = None,
        height: int | None = None,
        segments: Sequence[object] = (),
        segment_points: Sequence[int] | None = None,
    ) -> tuple[NDArray[np.uint8], NDArray[np.float32]]:
        """RGB (H, W, 3) and metric depth along the optical axis (H, W) from ``camera``.

        MuJoCo draws the cables (tendons) and the floor's grid itself: ``segments`` and
        ``segment_points`` (the PyBullet world's overlay lines) are not needed here.
        """
        w, h = width or camera.width, height or camera.height
        renderer = self._renderer(w, h)
        vis = self.model.vis
        vis.global_.fovy = camera.vertical_fov
        vis.map.znear, vis.map.zfar = camera.near, camera.far  # extent 1: metres
        view = _free_camera(camera)
        renderer.update_scene(self.data, camera=view)
        rgb = renderer.render().copy()
        renderer.enable_depth_rendering()
        renderer.update_scene(self.data, camera=view)
        depth = renderer.render().astype(np.float32)
        renderer.disable_depth_rendering()
        return rgb, depth

    def _renderer(self, width: int, height: int) -> Any:
        """The offscreen renderer of this size for the present model, made once."""
        renderer = self._renderers.get((width, height))
        if renderer is None:
            self.model.vis.global_.offwidth = max(self.model.vis.global_.offwidth, width)
            self.model.vis.global_.offheight = max(self.model.vis.global_.offheight, height)
            try:
                renderer = mujoco.Renderer(self.model, height, width)
            except Exception as err:  # the GL stack fails in many ways
                raise RuntimeError(
                    f"engine 'mujoco' cannot render on this machine ({_first_line(err)}); "
                    "set MUJOCO_GL=egl or osmesa where the machine has it"
                ) from None
            self._renderers[(width, height)] = renderer
        return renderer

    def close(self) -> None:
        """Free the renderers; closing again does nothing."""
        self._release()


@numba.njit(cache=True, nogil=True)
def _motor_rates(
    act: NDArray[np.float64],
    targets: NDArray[np.float64],
    max_step: NDArray[np.float64],
    speed: NDArray[np.float64],
    time_step: float,
    rate: NDArray[np.float64],
    arrive: NDArray[np.bool_],
) -> int:
    """The motors' rest-length rates (m/s) from their rest lengths ``act`` (m) on,
    written into ``rate``; returns for how many physics steps they hold, ``arrive``
    marking the motors that reach their targets on the last of those steps.

    As :func:`~tensegrity_gym.sim.cables.slew_motors`: a motor more than a step's travel
    off moves a full step at the speed limit (``ceil(|err| / max_step) - 1`` of them),
    else it arrives in one."""
    hold = 1 << 62  # no motor moves
    any_near = False
    for i in range(act.shape[0]):
        err = targets[i] - act[i]
        arrive[i] = False
        if abs(err) > max_step[i]:
            rate[i] = speed[i] if err > 0.0 else -speed[i]
            hold = min(hold, max(int(np.ceil(abs(err) / max_step[i])) - 1, 1))
        else:
            rate[i] = err / time_step
            if err != 0.0:
                arrive[i] = any_near = True
    return 1 if any_near else hold


@numba.njit(cache=True, nogil=True)
def _read_rods(
    qpos: NDArray[np.float64],
    qvel: NDArray[np.float64],
    half: NDArray[np.float64],
    rod_nodes: NDArray[np.int64],
    positions: NDArray[np.float64],
    quaternions: NDArray[np.float64],
    linear: NDArray[np.float64],
    angular: NDArray[np.float64],
    nodes: NDArray[np.float64],
) -> None:
    """The rods' free-joint state, ``qpos`` (7 r,) (centre, quaternion w x y z) and
    ``qvel`` (6 r,) (linear velocity, angular velocity in the body frame), written into
    centres (r, 3), quaternions (r, 4) (x, y, z, w), linear and world-frame angular
    velocities (r, 3), and the endcap nodes (n, 3), half a length (r,) off the centre
    along body z."""
    for r in range(half.shape[0]):
        w, x, y, z = qpos[7 * r + 3], qpos[7 * r + 4], qpos[7 * r + 5], qpos[7 * r + 6]
        quaternions[r, 0], quaternions[r, 1], quaternions[r, 2], quaternions[r, 3] = x, y, z, w
        # The rotation's columns: body x, y, z in the world frame.
        m00, m01, m02 = 1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - z * w), 2.0 * (x * z + y * w)
        m10, m11, m12 = 2.0 * (x * y + z * w), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - x * w)
        m20, m21, m22 = 2.0 * (x * z - y * w), 2.0 * (y * z + x * w), 1.0 - 2.0 * (x * x + y * y)
        wx, wy, wz = qvel[6 * r + 3], qvel[6 * r + 4], qvel[6 * r + 5]
        angular[r, 0] = m00 * wx + m01 * wy + m02 * wz
        angular[r, 1] = m10 * wx + m11 * wy + m12 * wz
        angular[r, 2] = m20 * wx + m21 * wy + m22 * wz
        h = half[r]
        for i in range(3):
            positions[r, i] = qpos[7 * r + i]
            linear[r, i] = qvel[6 * r + i]
        a, b = rod_nodes[r, 0], rod_nodes[r, 1]
        arm = (m02 * h, m12 * h, m22 * h)
        for i in range(3):
            nodes[a, i] = positions[r, i] - arm[i]
            nodes[b, i] = positions[r, i] + arm[i]


def _same_ground(a: Terrain | None, b: Terrain | None) -> bool:
    """Whether two grounds are the same surface (a new flat map each reset is the plane
    of the last one: the model need not be compiled again)."""
    if a is None or a.is_flat:
        return b is None or b.is_flat
    if b is None or b.is_flat:
        return False
    return (
        a.cell_size == b.cell_size
        and a.origin == b.origin
        and a.heights.shape == b.heights.shape
        and bool(np.array_equal(a.heights, b.heights))
    )


def _close_renderers(renderers: dict[tuple[int, int], Any]) -> None:
    while renderers:
        renderers.popitem()[1].close()


def _free_camera(camera: CameraConfig) -> Any:
    """MuJoCo's free camera looking from ``camera.position`` at ``camera.target``
    (z up)."""
    eye = np.asarray(camera.position, dtype=np.float64)
    target = np.asarray(camera.target, dtype=np.float64)
    forward = target - eye
    distance = float(np.linalg.norm(forward))
    view = mujoco.MjvCamera()
    view.type = mujoco.mjtCamera.mjCAMERA_FREE
    view.lookat[:] = target
    view.distance = distance
    view.azimuth = math.degrees(math.atan2(forward[1], forward[0]))
    view.elevation = math.degrees(math.asin(forward[2] / distance))
    return view
