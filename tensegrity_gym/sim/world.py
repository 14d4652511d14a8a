"""The PyBullet world of one robot: the only module of the project that imports pybullet.

Rods are rigid bodies, a tube between two wider endcap spheres, built with maximal
coordinates (as floating-base multibodies they blew up under actuation). Cables are
unilateral spring-dampers whose forces are applied to the rods every physics step; with
tension positive and the force on node i equal to q (x_j - x_i), damping enters as
``+c dL/dt`` in the tension. Motors slew the actuated cables' rest lengths toward their
targets at a limited speed; a motor with a ``min_tension`` also reels in its cable's
slack at once, so its rest length (the encoder's reading) never exceeds the endcap
distance less that tension's stretch.

The hot loop is plain Python over floats: for 9-24 cables it beats numpy, whose
per-call overhead dominates at these sizes.
"""

from __future__ import annotations

import os
import sys
import weakref
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from tensegrity_gym.model.kinematics import (
    member_lengths,
    rod_node_states,
    rod_quaternion_from_axis,
)
from tensegrity_gym.model.samples import ns_to_seconds
from tensegrity_gym.sim.cables import cable_wrenches, slew_motors

if TYPE_CHECKING:
    from collections.abc import Iterator, Sequence

    from numpy.typing import NDArray

    from tensegrity_gym.model.description import CameraConfig, RobotDescription
    from tensegrity_gym.sim.terrain import Terrain

__all__ = [
    "MAX_HEIGHTFIELD_POINTS",
    "Checkpoint",
    "PhysicsWorld",
    "Snapshot",
    "check_heightfield",
    "has_display",
]

MAX_HEIGHTFIELD_POINTS = 2048 * 2048
"""The most heights a terrain may have. PyBullet (3.2.x) takes a heightfield's data in
one command buffer and crashes the process (SIGSEGV, no message) from about 8 million
points on (2,860 x 2,860 did here; 2,840 x 2,840 passed once and 2 x 4,000,000 failed
once); half of that, 2048 x 2048, built and stepped every time."""


def check_heightfield(terrain: Terrain) -> None:
    """Raise ValueError if ``terrain`` has more heights than PyBullet's heightfield
    holds (:data:`MAX_HEIGHTFIELD_POINTS`), naming its shape and the limit."""
    rows, cols = terrain.heights.shape
    if rows * cols > MAX_HEIGHTFIELD_POINTS:
        name = f" {terrain.name!r}" if terrain.name else ""
        raise ValueError(
            f"terrain{name} has {rows} x {cols} = {rows * cols:,} heights; PyBullet's "
            f"heightfield holds at most {MAX_HEIGHTFIELD_POINTS:,} (2048 x 2048): "
            "use coarser cells or a smaller map"
        )


@contextmanager
def _stderr_silenced() -> Iterator[None]:
    """File descriptor 2 pointed at the null device for the block, then restored: what
    C code writes to stderr meanwhile is dropped (Python's own ``sys.stderr`` is flushed
    first). Where fd 2 cannot be duplicated (closed), the block runs as it is."""
    sys.stderr.flush()
    try:
        saved = os.dup(2)
    except OSError:
        yield
        return
    try:
        null = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(null, 2)
        finally:
            os.close(null)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


# PyBullet's C extension prints "pybullet build time: ..." on stderr at import: not
# something a user of the env (or of every command) needs on the terminal.
with _stderr_silenced():
    import pybullet

Checkpoint = tuple[int, list[float], list[float], list[float], list[float], int]
"""PyBullet's saved state, the rest lengths the motors set and those in effect, the
motors' targets, the cable lengths of the damping term, the clock (ns)."""


def has_display() -> bool:
    """Whether PyBullet's window can open: off Linux always, on Linux with ``DISPLAY`` set
    (without an X server its GUI ends the whole process)."""
    return not sys.platform.startswith("linux") or bool(os.environ.get("DISPLAY"))


@dataclass(frozen=True, slots=True)
class Snapshot:
    """The true state at one physics step, for the sensor models."""

    t: float
    rod_positions: Sequence[Sequence[float]]
    """(r, 3) m."""
    rod_quaternions: Sequence[Sequence[float]]
    """(r, 4) (x, y, z, w)."""
    rod_linear_velocities: Sequence[Sequence[float]]
    """(r, 3) m/s, world frame."""
    rod_angular_velocities: Sequence[Sequence[float]]
    """(r, 3) rad/s, world frame."""
    node_positions: list[list[float]]
    """(n, 3) m."""
    rest_lengths: list[float]
    """(n_cables,) m, in effect (what the encoders read)."""


class PhysicsWorld:
    """A PyBullet client holding one robot on the ground.

    Args:
        description: the robot.
        time_step: physics step (s).
        gui: open PyBullet's window instead of a headless client.
        terrain: the ground: None or a flat one is the infinite plane z = 0, another a
            heightfield whose surface is the map's heights; :meth:`_build` (each
            episode) builds the current :attr:`terrain`.
    """

    def __init__(
        self,
        description: RobotDescription,
        time_step: float,
        gui: bool = False,
        terrain: Terrain | None = None,
    ) -> None:
        self.description = description
        self.time_step = time_step
        self.terrain = terrain
        if gui and not has_display():
            # PyBullet's GUI ends the whole process when it finds no X server.
            raise RuntimeError(
                "render_mode='human' needs a display (DISPLAY is not set); "
                "use render_mode='rgb_array' on a headless machine"
            )
        self.client = pybullet.connect(pybullet.GUI if gui else pybullet.DIRECT)
        if self.client < 0:
            raise RuntimeError("could not start a PyBullet client")
        # The clients this world started; a world dropped without close() (an env
        # garbage-collected) disconnects them, not leaving a simulator's memory behind.
        self._clients = [self.client]
        self._release = weakref.finalize(self, _disconnect, self._clients)
        self._gui = gui
        self._floor_client = -1  # started on the first camera image
        self._floor_images: dict[
            tuple[tuple[float, ...], tuple[float, ...], int, int],
            tuple[NDArray[np.uint8], NDArray[np.float64]],
        ] = {}
        d = description
        self.gravity = np.array([0.0, 0.0, -d.gravity])
        """(3,) m/s^2 in the world frame, set at the next :meth:`_build`."""
        self._configure(d)
        self.rest_lengths: list[float] = d.rest_lengths.tolist()
        """The rest lengths the motors' positions set (m), (n_cables,), and the passive
        cables' own."""
        self.spool_lengths: list[float] = d.rest_lengths.tolist()
        """The rest lengths in effect (m), (n_cables,), what the encoders read: those of
        :attr:`rest_lengths`, or shorter where a motor has reeled in slack."""
        self.targets: list[float] = [self.rest_lengths[k] for k in self._actuated]
        self._time_step_ns = round(time_step * 1e9)
        self.time_ns = 0
        """Simulated time in whole nanoseconds: stamps stay exact through a ROS bag."""
        self.bodies: list[int] = []
        self._cable_lengths: list[float] = [0.0] * d.n_cables
        self._build()

    # ------------------------------------------------------------------ construction

    def _configure(self, d: RobotDescription) -> None:
        """What the hot loop reads of the robot: rods, cables, motors."""
        self._half = [0.5 * r.length for r in d.rods]
        self._node_of = [(int(r.nodes[0]), int(r.nodes[1])) for r in d.rods]
        self._half_arr = np.array(self._half)
        self._actuated = [int(k) for k in d.actuated]
        self._actuated_arr = np.asarray(d.actuated, dtype=np.int64)
        self._node_of_arr = np.asarray(self._node_of, dtype=np.int64).reshape(-1, 2)
        self._cable_arrays = (
            np.asarray(d.cable_nodes, dtype=np.int64),
            np.array([cable.stiffness for cable in d.cables]),
            np.array([cable.damping for cable in d.cables]),
        )
        lo, hi, speed = d.motor_limits
        self._motor_lo = lo.tolist()
        self._motor_hi = hi.tolist()
        self._motor_step = speed * self.time_step  # m per physics step
        # Motors that hold a minimum tension reel in slack (cable_wrenches): per cable,
        # the least stretch (m; NaN: the cable may go slack).
        self._reel = np.full(d.n_cables, np.nan)
        self._reel[d.actuated] = d.motor_min_stretch

    def reconfigure(self, description: RobotDescription, gravity: NDArray[np.float64]) -> None:
        """Build the next episode (:meth:`_build`) with another ``description`` of the
        same robot (masses, cables, motors, ground drawn apart from the nominal one)
        and ``gravity`` (3,) m/s^2 (tilted: a slope)."""
        if description.n_cables != self.description.n_cables or (
            description.n_rods != self.description.n_rods
        ):
            raise ValueError(f"reconfigure: {description.name} is not this world's robot")
        self.description = description
        self.gravity = np.asarray(gravity, dtype=np.float64).copy()
        self._configure(description)

    def _build(self) -> None:
        c = self.client
        d = self.description
        pybullet.resetSimulation(physicsClientId=c)
        gx, gy, gz = (float(g) for g in self.gravity)
        pybullet.setGravity(gx, gy, gz, physicsClientId=c)
        pybullet.setTimeStep(self.time_step, physicsClientId=c)
        pybullet.setPhysicsEngineParameter(deterministicOverlappingPairs=1, physicsClientId=c)
        terrain = self.terrain
        if terrain is None or terrain.is_flat:
            plane = pybullet.createCollisionShape(pybullet.GEOM_PLANE, physicsClientId=c)
            # Headless, the floor is drawn in a client of its own (see camera_image) and
            # is transparent here (with no visual at all TinyRenderer would draw the
            # collision plane); the GUI window shows it.
            floor_visual = _floor_visual(c, alpha=1.0 if self._gui else 0.0)
            self.ground = pybullet.createMultiBody(0.0, plane, floor_visual, physicsClientId=c)
        else:
            self.ground = _heightfield(c, terrain)
        pybullet.changeDynamics(
            self.ground,
            -1,
            lateralFriction=d.ground.lateral_friction,
            rollingFriction=d.ground.rolling_friction,
            spinningFriction=d.ground.spinning_friction,
            restitution=d.ground.restitution,
            physicsClientId=c,
        )
        self.bodies = []
        for rod in d.rods:
            # The rod as built: a thin tube between two wider endcaps, for collisions
            # as for drawing (rods lying side by side come as close as their tubes let).
            h = 0.5 * rod.length
            parts = {
                "shapeTypes": [pybullet.GEOM_CYLINDER, pybullet.GEOM_SPHERE, pybullet.GEOM_SPHERE],
                "radii": [rod.radius, rod.endcap_radius, rod.endcap_radius],
                "lengths": [rod.length, 0.0, 0.0],
            }
            frames = [[0.0, 0.0, 0.0], [0.0, 0.0, -h], [0.0, 0.0, h]]
            col = pybullet.createCollisionShapeArray(
                **parts, collisionFramePositions=frames, physicsClientId=c
            )
            vis = pybullet.createVisualShapeArray(
                **parts, visualFramePositions=frames, physicsClientId=c
            )
            body = pybullet.createMultiBody(
                rod.mass, col, vis, useMaximalCoordinates=True, physicsClientId=c
            )
            pybullet.changeDynamics(
                body,
                -1,
                lateralFriction=d.ground.lateral_friction,
                rollingFriction=d.ground.rolling_friction,
                spinningFriction=d.ground.spinning_friction,
                restitution=d.ground.restitution,
                linearDamping=0.0,
                angularDamping=0.0,
                physicsClientId=c,
            )
            # Rod body grey, endcaps in the rod's colour (Lu et al. 2022 paints endcaps).
            pybullet.changeVisualShape(
                body, -1, shapeIndex=0, rgbaColor=[0.3, 0.3, 0.3, 1.0], physicsClientId=c
            )
            for shape in (1, 2):
                pybullet.changeVisualShape(
                    body, -1, shapeIndex=shape, rgbaColor=list(rod.color), physicsClientId=c
                )
            self.bodies.append(body)

    @property
    def flat_ground(self) -> bool:
        """The ground is the plane z = 0 (no terrain, or a flat one)."""
        return self.terrain is None or self.terrain.is_flat

    def ground_heights(self, xy: NDArray[np.float64]) -> NDArray[np.float64]:
        """The ground's surface height (m) under each world (x, y) of ``xy`` (k, 2) (m),
        by a vertical ray test (k,); NaN where the ray meets a rod first or no ground."""
        pts = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        terrain = self.terrain
        top, bottom = 1.0, -1.0
        if terrain is not None and not terrain.is_flat:
            top += float(terrain.heights.max())
            bottom += float(terrain.heights.min())
        starts = [[x, y, top] for x, y in pts.tolist()]
        ends = [[x, y, bottom] for x, y in pts.tolist()]
        hits = pybullet.rayTestBatch(starts, ends, physicsClientId=self.client)
        return np.array([h[3][2] if h[0] == self.ground else np.nan for h in hits])

    # ------------------------------------------------------------------ state access

    def set_node_positions(self, nodes: NDArray[np.float64]) -> None:
        """Place each rod so its endcaps sit at the given nodes (n, 3), at rest."""
        for k, body in enumerate(self.bodies):
            a, b = self._node_of[k]
            axis = nodes[b] - nodes[a]
            axis = axis / np.linalg.norm(axis)
            centre = 0.5 * (nodes[a] + nodes[b])
            q = rod_quaternion_from_axis(axis)
            pybullet.resetBasePositionAndOrientation(
                body, centre.tolist(), q.tolist(), physicsClientId=self.client
            )
            pybullet.resetBaseVelocity(body, [0.0] * 3, [0.0] * 3, physicsClientId=self.client)
        self._sync_cable_lengths()

    def set_rod_states(
        self,
        positions: NDArray[np.float64],
        quaternions: NDArray[np.float64],
        linear: NDArray[np.float64] | None = None,
        angular: NDArray[np.float64] | None = None,
    ) -> None:
        """Set every rod's pose (r, 3), (r, 4) and velocities (r, 3) (zero if omitted)."""
        for k, body in enumerate(self.bodies):
            pybullet.resetBasePositionAndOrientation(
                body, positions[k].tolist(), quaternions[k].tolist(), physicsClientId=self.client
            )
            lin = [0.0] * 3 if linear is None else linear[k].tolist()
            ang = [0.0] * 3 if angular is None else angular[k].tolist()
            pybullet.resetBaseVelocity(body, lin, ang, physicsClientId=self.client)
        self._sync_cable_lengths()

    def _sync_cable_lengths(self) -> None:
        """Reset the cable-length history of the damping term after a teleport: the
        lengths one step ago that the set velocities imply, so that the first step's
        damping force is that of the cables' stretching rate, not zero (a restart
        from a vibrating robot's state would otherwise feel an undamped first step)."""
        x, xd = self.node_states()
        pairs = self.description.cable_nodes
        lengths = member_lengths(x, pairs)
        along = (x[pairs[:, 1]] - x[pairs[:, 0]]) / np.maximum(lengths, 1e-12)[:, None]
        rate = np.sum(along * (xd[pairs[:, 1]] - xd[pairs[:, 0]]), axis=1)
        self._cable_lengths = (lengths - self.time_step * rate).tolist()

    def set_rest_lengths(self, rest_lengths: Sequence[float] | NDArray[np.float64]) -> None:
        """Set all cables' rest lengths (m); actuated targets follow."""
        self.rest_lengths = [float(x) for x in rest_lengths]
        self.spool_lengths = list(self.rest_lengths)
        self.targets = [self.rest_lengths[k] for k in self._actuated]

    def rod_states(
        self,
    ) -> tuple[
        list[tuple[float, float, float]],
        list[tuple[float, float, float, float]],
        list[tuple[float, float, float]],
        list[tuple[float, float, float]],
    ]:
        """Positions, quaternions (x, y, z, w), linear and angular velocities of the rods."""
        c = self.client
        pos, orn, lin, ang = [], [], [], []
        for body in self.bodies:
            p, q = pybullet.getBasePositionAndOrientation(body, physicsClientId=c)
            v, w = pybullet.getBaseVelocity(body, physicsClientId=c)
            pos.append(p)
            orn.append(q)
            lin.append(v)
            ang.append(w)
        return pos, orn, lin, ang

    def node_states(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Node positions and velocities, each (n, 3)."""
        pos, orn, lin, ang = self.rod_states()
        return rod_node_states(pos, orn, lin, ang, self._half_arr, self.description.rod_nodes)

    # ------------------------------------------------------------------ stepping

    def advance(
        self, n_steps: int, targets: Sequence[float], snapshot_steps: Sequence[bool]
    ) -> list[Snapshot]:
        """Run ``n_steps`` physics steps toward the actuated rest-length ``targets`` (m).

        ``snapshot_steps[i]`` asks for the state after step i. Returns those snapshots.
        """
        c = self.client
        bodies = self.bodies
        n_rods = len(bodies)
        lo, hi = self._motor_lo, self._motor_hi
        tgt = [min(max(float(x), lo[i]), hi[i]) for i, x in enumerate(targets)]
        self.targets = tgt
        targets_arr = np.array(tgt)
        rest = np.array(self.rest_lengths)
        prev_len = np.array(self._cable_lengths, dtype=np.float64)
        half = self._half_arr
        node_of = self._node_of_arr
        cable_nodes, stiffness, damping = self._cable_arrays
        actuated, max_step = self._actuated_arr, self._motor_step
        reel = self._reel
        spool = np.array(self.spool_lengths)
        n_nodes = self.description.n_nodes
        get_pose = pybullet.getBasePositionAndOrientation
        apply_force = pybullet.applyExternalForce
        apply_torque = pybullet.applyExternalTorque
        step_sim = pybullet.stepSimulation
        world_frame = pybullet.WORLD_FRAME
        inv_dt = 1.0 / self.time_step
        snapshots: list[Snapshot] = []
        poses = np.empty((n_rods, 7))
        wrench = np.empty((n_rods, 6))
        moving = True
        for step in range(n_steps):
            if moving:  # motors slew toward their targets
                moving = slew_motors(rest, actuated, targets_arr, max_step)
            for r in range(n_rods):
                p, q = get_pose(bodies[r], physicsClientId=c)
                poses[r, :3] = p
                poses[r, 3:] = q
            cable_wrenches(
                poses, half, node_of, cable_nodes, stiffness, damping, rest, reel,
                spool, prev_len, inv_dt, n_nodes, wrench,
            )  # fmt: skip
            w = wrench.tolist()
            centres = poses[:, :3].tolist()
            for r in range(n_rods):
                wr = w[r]
                apply_force(bodies[r], -1, wr[:3], centres[r], world_frame, physicsClientId=c)
                apply_torque(bodies[r], -1, wr[3:], world_frame, physicsClientId=c)
            step_sim(physicsClientId=c)
            self.time_ns += self._time_step_ns
            if snapshot_steps[step]:
                self.rest_lengths, self.spool_lengths = rest.tolist(), spool.tolist()
                snapshots.append(self.snapshot())
        self.rest_lengths, self.spool_lengths = rest.tolist(), spool.tolist()
        self._cable_lengths = prev_len.tolist()
        return snapshots

    def step_bare(self, n_steps: int) -> None:
        """Step PyBullet alone, no cables (the rods fall apart): the engine's own cost that
        the benchmark puts beside the env's. Not a ceiling: rods piling up on the ground
        can cost more than a standing robot."""
        for _ in range(n_steps):
            pybullet.stepSimulation(physicsClientId=self.client)

    def save_state(self) -> Checkpoint:
        """An in-memory checkpoint of the bodies, motors and clock."""
        state = pybullet.saveState(physicsClientId=self.client)
        return (
            state,
            list(self.rest_lengths),
            list(self.spool_lengths),
            list(self.targets),
            list(self._cable_lengths),
            self.time_ns,
        )

    def restore_state(self, checkpoint: Checkpoint) -> None:
        state, rest, spool, targets, lengths, t_ns = checkpoint
        pybullet.restoreState(state, physicsClientId=self.client)
        self.rest_lengths, self.spool_lengths = list(rest), list(spool)
        self.targets = list(targets)
        self._cable_lengths, self.time_ns = list(lengths), t_ns

    @property
    def time(self) -> float:
        """Simulated time (s), a whole number of nanoseconds."""
        return ns_to_seconds(self.time_ns)

    def snapshot(self) -> Snapshot:
        pos, orn, lin, ang = self.rod_states()
        nodes: list[list[float]] = [[0.0, 0.0, 0.0] for _ in range(self.description.n_nodes)]
        for r in range(len(self.bodies)):
            qx, qy, qz, qw = orn[r]
            h = self._half[r]
            ax = 2.0 * (qx * qz + qw * qy) * h
            ay = 2.0 * (qy * qz - qw * qx) * h
            az = (1.0 - 2.0 * (qx * qx + qy * qy)) * h
            a, b = self._node_of[r]
            p = pos[r]
            nodes[a] = [p[0] - ax, p[1] - ay, p[2] - az]
            nodes[b] = [p[0] + ax, p[1] + ay, p[2] + az]
        return Snapshot(self.time, pos, orn, lin, ang, nodes, list(self.spool_lengths))

    # ------------------------------------------------------------------ rendering

    def camera_image(
        self,
        camera: CameraConfig,
        width: int | None = None,
        height: int | None = None,
        segments: Sequence[
            tuple[NDArray[np.float64], NDArray[np.float64], tuple[int, int, int]]
        ] = (),
        segment_points: Sequence[int] | None = None,
    ) -> tuple[NDArray[np.uint8], NDArray[np.float32]]:
        """RGB (H, W, 3) and metric depth along the optical axis (H, W) from ``camera``.

        ``segments`` are (start (3,), end (3,), colour) lines drawn over the colour image
        for people (cables, a ground grid); TinyRenderer cannot draw lines itself. They
        are hidden where the scene is nearer to the camera. Each is drawn as that many
        points of ``segment_points`` (400 each by default).
        """
        w = width or camera.width
        h = height or camera.height
        view = pybullet.computeViewMatrix(
            camera.position, camera.target, camera.up, physicsClientId=self.client
        )
        proj = pybullet.computeProjectionMatrixFOV(
            camera.vertical_fov, w / h, camera.near, camera.far, physicsClientId=self.client
        )
        rgb, zb = _render(self.client, w, h, view, proj)
        if self.flat_ground:
            # TinyRenderer spends ~90 % of a frame filling the floor's screen-sized
            # triangles, so the floor is rendered once per camera pose in a client
            # holding only the floor, and the robot is z-composited over it: the same
            # pixels as one render of both (tested), at a tenth of the cost for a fixed
            # camera. A heightfield is drawn with the robot.
            floor_rgb, floor_zb = self._floor_image(w, h, view, proj)
            floor_nearer = floor_zb <= zb
            rgb[floor_nearer] = floor_rgb[floor_nearer]
            zb = np.where(floor_nearer, floor_zb, zb)
        near, far = camera.near, camera.far
        depth = (far * near / (far - (far - near) * zb)).astype(np.float32)
        if segments:
            # Matrices are column-major 4x4 lists.
            clip_from_world = np.asarray(proj).reshape(4, 4).T @ np.asarray(view).reshape(4, 4).T
            n = np.full(len(segments), 400) if segment_points is None else segment_points
            _draw_segments(rgb, zb, clip_from_world, segments, np.asarray(n, dtype=np.intp))
        return rgb, depth

    def _floor_image(
        self, w: int, h: int, view: Sequence[float], proj: Sequence[float]
    ) -> tuple[NDArray[np.uint8], NDArray[np.float64]]:
        """The floor alone seen from a camera: RGB (h, w, 3) and depth buffer (h, w)."""
        key = (tuple(view), tuple(proj), w, h)
        image = self._floor_images.get(key)
        if image is None:
            if self._floor_client < 0:
                self._floor_client = pybullet.connect(pybullet.DIRECT)
                if self._floor_client < 0:
                    raise RuntimeError("could not start a PyBullet client for the floor")
                self._clients.append(self._floor_client)
                pybullet.createMultiBody(
                    0.0, -1, _floor_visual(self._floor_client), physicsClientId=self._floor_client
                )
            image = _render(self._floor_client, w, h, view, proj)
            if len(self._floor_images) >= 4:  # a moving camera: keep the newest few
                self._floor_images.pop(next(iter(self._floor_images)))
            self._floor_images[key] = image
        return image

    def close(self) -> None:
        """Disconnect this world's PyBullet clients; closing again does nothing."""
        self._release()
        self._floor_client = -1
        self.client = -1


def _disconnect(clients: list[int]) -> None:
    """Disconnect PyBullet ``clients`` (ids) and empty the list."""
    while clients:
        try:
            pybullet.disconnect(physicsClientId=clients.pop())
        except pybullet.error:
            pass  # already gone (e.g. the GUI window was closed)


_FLOOR_RGB = [0.55, 0.55, 0.5]


def _floor_visual(client: int, alpha: float = 1.0) -> int:
    """The floor's visual shape: a thin grey slab whose top face is z = 0."""
    return int(
        pybullet.createVisualShape(
            pybullet.GEOM_BOX,
            halfExtents=[50.0, 50.0, 0.0005],
            rgbaColor=[*_FLOOR_RGB, alpha],
            visualFramePosition=[0.0, 0.0, -0.0005],
            physicsClientId=client,
        )
    )


def _draw_segments(
    rgb: NDArray[np.uint8],
    zb: NDArray[np.float64],
    clip_from_world: NDArray[np.float64],
    segments: Sequence[tuple[NDArray[np.float64], NDArray[np.float64], tuple[int, int, int]]],
    points: NDArray[np.intp],
) -> None:
    """Draw line ``segments`` (start (3,), end (3,), colour) into ``rgb`` (h, w, 3), the
    i-th as ``points[i]`` >= 2 evenly spaced points, hidden where the depth buffer ``zb``
    (h, w) is nearer; a later segment over an earlier one. All at once: a grid draped
    over a terrain has thousands of pieces."""
    h, w = zb.shape
    which = np.repeat(np.arange(len(segments)), points)
    first_point = np.cumsum(points) - points
    # np.linspace(0, 1, n) point by point: k * (1 / (n - 1)), the last exactly 1.
    k = np.arange(len(which)) - first_point[which]
    t = k * (1.0 / (points[which] - 1.0))
    t[k == points[which] - 1] = 1.0
    starts = np.array([s for s, _, _ in segments], dtype=np.float64)[which]
    ends = np.array([e for _, e, _ in segments], dtype=np.float64)[which]
    pts = starts + t[:, None] * (ends - starts)
    clip = np.c_[pts, np.ones(len(pts))] @ clip_from_world.T
    front = clip[:, 3] > 1e-6
    ndc = clip[front, :3] / clip[front, 3:4]
    which = which[front]
    u = ((ndc[:, 0] + 1.0) * 0.5 * w).astype(int)
    v = ((1.0 - ndc[:, 1]) * 0.5 * h).astype(int)
    zbuf = 0.5 * (ndc[:, 2] + 1.0)
    ok = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    u, v, zbuf, which = u[ok], v[ok], zbuf[ok], which[ok]
    seen = zbuf <= zb[v, u] + 1e-4
    pixel = (v * w + u)[seen][::-1]
    # The first of each pixel in reverse order is the last segment drawn over it.
    pixel, first = np.unique(pixel, return_index=True)
    colours = np.array([c for _, _, c in segments], dtype=np.uint8)
    rgb.reshape(-1, 3)[pixel] = colours[which[seen][::-1][first]]


def _heightfield(client: int, terrain: Terrain) -> int:
    """A static body whose surface is ``terrain``'s heights at their world (x, y, z).

    PyBullet's heightfield takes its data with x varying fastest (``numHeightfieldRows``
    points along x) and centres the grid on its body's origin, in z on the mid-height of
    the data's range: the body is placed at the map's centre and that mid-height. It has
    no visual shape: TinyRenderer and the GUI draw the collision mesh, in the floor's
    colour.
    """
    check_heightfield(terrain)  # beyond it PyBullet crashes the process
    h = terrain.heights
    rows, cols = h.shape
    x0, x1, y0, y1 = terrain.extent
    shape = pybullet.createCollisionShape(
        pybullet.GEOM_HEIGHTFIELD,
        meshScale=[terrain.cell_size, terrain.cell_size, 1.0],
        heightfieldData=h.ravel().tolist(),
        numHeightfieldRows=cols,
        numHeightfieldColumns=rows,
        physicsClientId=client,
    )
    centre = [0.5 * (x0 + x1), 0.5 * (y0 + y1), 0.5 * (float(h.min()) + float(h.max()))]
    body = int(pybullet.createMultiBody(0.0, shape, -1, centre, physicsClientId=client))
    # No texture: TinyRenderer's default checker would split the map in four.
    pybullet.changeVisualShape(
        body, -1, textureUniqueId=-1, rgbaColor=[*_FLOOR_RGB, 1.0], physicsClientId=client
    )
    return body


def _render(
    client: int, w: int, h: int, view: Sequence[float], proj: Sequence[float]
) -> tuple[NDArray[np.uint8], NDArray[np.float64]]:
    """TinyRenderer's RGB (h, w, 3) and raw depth buffer (h, w) in [0, 1]."""
    _, _, rgba, depth_buffer, _ = pybullet.getCameraImage(
        w,
        h,
        view,
        proj,
        renderer=pybullet.ER_TINY_RENDERER,
        flags=pybullet.ER_NO_SEGMENTATION_MASK,
        physicsClientId=client,
    )
    rgb = np.asarray(rgba, dtype=np.uint8).reshape(h, w, 4)[..., :3].copy()
    return rgb, np.asarray(depth_buffer, dtype=np.float64).reshape(h, w)
