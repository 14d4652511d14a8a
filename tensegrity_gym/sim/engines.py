"""Physics engines by name: ``gym.make(ID, engine="mujoco")``.

An engine makes the world of one robot (:class:`World`): PyBullet's
(:class:`~tensegrity_gym.sim.world.PhysicsWorld`, the default) or MuJoCo's
(:class:`~tensegrity_gym.sim.mujoco_world.MujocoWorld`, the optional extra
``tensegrity-gym[mujoco]``). The sensor models, their noise and timing are the
backend's, shared by both. Built-in engines are named as ``"module:attribute"`` strings,
imported only when chosen; installed packages add engines through the entry-point group
``tensegrity_gym.engines`` (a factory taking ``(description, time_step, gui=...,
terrain=...)``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, Protocol

from tensegrity_gym.model.registry import Registry, resolve

if TYPE_CHECKING:
    from collections.abc import Callable, Sequence

    import numpy as np
    from numpy.typing import NDArray

    from tensegrity_gym.model.description import CameraConfig, RobotDescription
    from tensegrity_gym.sim.terrain import Terrain
    from tensegrity_gym.sim.world import Snapshot

__all__ = [
    "DEFAULT_ENGINE",
    "ENGINES",
    "EngineSpec",
    "World",
    "check_engine",
    "engine_spec",
    "register_engine",
]

DEFAULT_ENGINE = "pybullet"


class World(Protocol):
    """What the backend asks of an engine's world of one robot (see
    :class:`~tensegrity_gym.sim.world.PhysicsWorld` for each method's contract)."""

    description: RobotDescription
    terrain: Terrain | None
    time_ns: int
    rest_lengths: list[float]
    targets: list[float]

    @property
    def time(self) -> float: ...
    @property
    def flat_ground(self) -> bool: ...
    @property
    def spool_lengths(self) -> list[float]: ...
    def reconfigure(self, description: RobotDescription, gravity: NDArray[np.float64]) -> None: ...
    def _build(self) -> None: ...
    def ground_heights(self, xy: NDArray[np.float64]) -> NDArray[np.float64]: ...
    def set_node_positions(self, nodes: NDArray[np.float64]) -> None: ...
    def set_rod_states(
        self,
        positions: NDArray[np.float64],
        quaternions: NDArray[np.float64],
        linear: NDArray[np.float64] | None = None,
        angular: NDArray[np.float64] | None = None,
    ) -> None: ...
    def set_rest_lengths(self, rest_lengths: Sequence[float] | NDArray[np.float64]) -> None: ...
    def rod_states(self) -> tuple[list[Any], list[Any], list[Any], list[Any]]: ...
    def node_states(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]: ...
    def advance(
        self, n_steps: int, targets: Sequence[float], snapshot_steps: Sequence[bool]
    ) -> list[Snapshot]: ...
    def step_bare(self, n_steps: int) -> None: ...
    def save_state(self) -> Any: ...
    def restore_state(self, checkpoint: Any) -> None: ...
    def snapshot(self) -> Snapshot: ...
    def camera_image(
        self,
        camera: CameraConfig,
        width: int | None = None,
        height: int | None = None,
        segments: Sequence[Any] = (),
        segment_points: Sequence[int] | None = None,
    ) -> tuple[NDArray[np.uint8], NDArray[np.float32]]: ...
    def close(self) -> None: ...


@dataclass(frozen=True)
class EngineSpec:
    """A physics engine by name: the world factory and what it needs installed."""

    name: str
    factory: str | Callable[..., World]
    install: str = ""
    """What to install where the factory's module is missing (for the error)."""
    renders: str | Callable[[], str | None] | None = None
    """A check whether this machine can render its camera: returns None, or why not
    (None here: it always can)."""
    window: bool = False
    """Its world opens a window for ``render_mode="human"`` (``gui=True``)."""

    def world(
        self,
        description: RobotDescription,
        time_step: float,
        *,
        gui: bool = False,
        terrain: Terrain | None = None,
    ) -> World:
        """A world of ``description``, stepped at ``time_step`` seconds."""
        factory = self.load()
        return factory(description, time_step, gui=gui, terrain=terrain)

    def load(self) -> Callable[..., World]:
        """The world factory, its module imported now; ImportError saying what to
        install where it is missing."""
        try:
            return resolve(self.factory)
        except ImportError as err:
            missing = isinstance(err, ModuleNotFoundError) or "pip install" in str(err)
            if missing and self.install:
                raise ImportError(
                    f"engine {self.name!r} is not installed: {self.install}"
                ) from None
            raise ImportError(f"engine {self.name!r} did not import: {err}") from None

    def render_problem(self) -> str | None:
        """None where this engine can render the camera here, else why not."""
        if self.renders is None:
            return None
        check: Any = resolve(self.renders)
        return check()  # type: ignore[no-any-return]


def _from_plugin(name: str, obj: Any) -> EngineSpec:
    if isinstance(obj, EngineSpec):
        return obj if obj.name == name else replace(obj, name=name)
    if callable(obj):
        return EngineSpec(name, obj)
    raise TypeError(f"expected an EngineSpec or a world factory, got {type(obj).__name__}")


ENGINES: Registry[EngineSpec] = Registry("engine", "tensegrity_gym.engines", _from_plugin)


def register_engine(
    name: str,
    factory: str | Callable[..., World],
    *,
    install: str = "",
    renders: str | Callable[[], str | None] | None = None,
    window: bool = False,
    overwrite: bool = False,
) -> EngineSpec:
    """Register a physics engine: ``gym.make(ID, engine=name)`` then builds its worlds."""
    spec = EngineSpec(name, factory, install, renders, window)
    return ENGINES.register(name, spec, overwrite=overwrite)


def engine_spec(name: str) -> EngineSpec:
    """The registered engine ``name``; ValueError listing the choices if none is."""
    return ENGINES[name]


def check_engine(name: object) -> EngineSpec:
    """The engine ``name``, its module importable: ValueError (unknown name) or
    ImportError (not installed), each one line, at ``make`` rather than at reset."""
    if not isinstance(name, str):
        raise ValueError(f"engine must be a name such as 'pybullet', got {name!r}")
    spec = engine_spec(name)
    spec.load()
    return spec


register_engine("pybullet", "tensegrity_gym.sim.world:PhysicsWorld", window=True)
_MUJOCO_INSTALL = "pip install 'tensegrity-gym[mujoco]'"
_MUJOCO_RENDERS = "tensegrity_gym.sim.mujoco_world:can_render"
register_engine(
    "mujoco",
    "tensegrity_gym.sim.mujoco_world:MujocoWorld",
    install=_MUJOCO_INSTALL,
    renders=_MUJOCO_RENDERS,
)
register_engine(  # a world to test estimators on: hard impacts
    "mujoco_stiff",
    "tensegrity_gym.sim.mujoco_world:stiff_contacts_world",
    install=_MUJOCO_INSTALL,
    renders=_MUJOCO_RENDERS,
)
