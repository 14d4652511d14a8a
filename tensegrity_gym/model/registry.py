"""Registries of plug-in parts, found by name: estimators and tasks.

A part is registered by name with a factory and what it needs. Built-in parts name
their factories as ``"module:attribute"`` strings, imported only when one is made, so
this module imports nothing heavy. Installed packages add parts through entry points
(group ``tensegrity_gym.estimators``), read the first time a name is looked up.

Example: a lab's own estimator::

    from tensegrity_gym.model.registry import register_estimator

    register_estimator("my_filter", MyFilter, requires=("uwb", "imu"))
    env = gym.make("tensegrity_gym/ThreeBarRoll-v0", estimator="my_filter")

and a task (group ``tensegrity_gym.tasks``), made by ``make_env(robot, task=name)``::

    register_task("stand_up", StandUpTask, arguments=("height",))
    env = make_env("three_bar", task="stand_up", height=0.3)
"""

from __future__ import annotations

import importlib
import logging
from dataclasses import dataclass, field, replace
from importlib.metadata import entry_points
from typing import TYPE_CHECKING, Any, Generic, TypeVar

from tensegrity_gym.model.samples import GROUND_TRUTH, SAMPLE_KINDS

if TYPE_CHECKING:
    from collections.abc import Callable, Collection, Iterable

    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.protocols import Estimator, Task
    from tensegrity_gym.model.samples import GroundTruth

__all__ = [
    "ESTIMATORS",
    "TASKS",
    "EstimatorSpec",
    "Registry",
    "TaskSpec",
    "estimator_spec",
    "register_estimator",
    "register_task",
    "resolve",
    "task_spec",
]

log = logging.getLogger(__name__)

T = TypeVar("T")


def resolve(target: str | Callable[..., Any]) -> Callable[..., Any]:
    """A callable, or the one a ``"module:attribute"`` string names (imported now)."""
    if not isinstance(target, str):
        return target
    module, _, attribute = target.partition(":")
    obj: Any = importlib.import_module(module)
    for part in attribute.split("."):
        obj = getattr(obj, part)
    if not callable(obj):
        raise TypeError(f"{target!r} is not callable")
    return obj  # type: ignore[no-any-return]


class Registry(Generic[T]):
    """Name -> entry, filled by :meth:`register` and by the entry-point ``group``.

    Args:
        kind: what the entries are, for messages (``"estimator"``).
        group: the entry-point group installed packages register under.
        convert: turns what an entry point loads (and its name) into an entry.
    """

    def __init__(self, kind: str, group: str, convert: Callable[[str, Any], T]) -> None:
        self.kind, self.group, self._convert = kind, group, convert
        self._entries: dict[str, T] = {}
        self._plugins_read = False

    def register(self, name: str, entry: T, *, overwrite: bool = False) -> T:
        if not isinstance(name, str) or not name:
            raise ValueError(f"a {self.kind} needs a non-empty name, got {name!r}")
        if name in self._entries and not overwrite:
            raise ValueError(f"{self.kind} {name!r} is already registered (pass overwrite=True)")
        self._entries[name] = entry
        return entry

    def unregister(self, name: str) -> None:
        self._entries.pop(name, None)

    def _read_plugins(self) -> None:
        if self._plugins_read:
            return
        self._plugins_read = True
        for ep in entry_points(group=self.group):
            if ep.name in self._entries:
                continue
            try:
                self._entries[ep.name] = self._convert(ep.name, ep.load())
            except Exception as err:  # a broken plug-in must not take the others down
                log.warning("%s plug-in %r (%s) did not load: %s", self.kind, ep.name,
                            ep.value, err)  # fmt: skip

    def names(self) -> tuple[str, ...]:
        self._read_plugins()
        return tuple(self._entries)

    def __contains__(self, name: object) -> bool:
        self._read_plugins()
        return name in self._entries

    def __getitem__(self, name: str) -> T:
        self._read_plugins()
        try:
            return self._entries[name]
        except (KeyError, TypeError):
            raise ValueError(
                f"unknown {self.kind} {name!r}; valid choices: {list(self._entries)}"
            ) from None


@dataclass(frozen=True)
class EstimatorSpec:
    """An estimator by name: how to make it and what it cannot run without.

    ``factory()`` makes one; one that reads ground truth is handed the source of it,
    ``factory(ground_truth)``, a callable returning the true state or None.
    """

    name: str
    factory: str | Callable[..., Estimator]
    requires: frozenset[str] = frozenset()
    """Sample kinds (:data:`SAMPLE_KINDS`) it cannot run without, and ``"ground_truth"``
    for one that reads the true state."""
    camera: bool = False
    """The simulator must render RGB-D frames for it."""
    robots: frozenset[str] | None = None
    """The robot descriptions (by name) it supports; None: any."""
    summary: str = ""
    needs: dict[str, str] = field(default_factory=dict, compare=False)
    """Why each requirement, for messages: kind -> what it is used for."""
    structure: str | Callable[[RobotDescription], str | None] | None = None
    """What it needs of the robot's structure, whatever its name and size:
    ``structure(description)`` says why it cannot serve that robot, or None where it
    can (a ``"module:attribute"`` string, imported when a robot is checked)."""

    def __post_init__(self) -> None:
        unknown = sorted(self.requires - set(SAMPLE_KINDS) - {GROUND_TRUTH})
        if unknown:
            raise ValueError(
                f"estimator {self.name!r} requires unknown kinds {unknown}; valid: "
                f"{[*SAMPLE_KINDS, GROUND_TRUTH]}"
            )

    @property
    def ground_truth(self) -> bool:
        return GROUND_TRUTH in self.requires

    def create(self, ground_truth: Callable[[], GroundTruth | None] | None = None) -> Estimator:
        factory = resolve(self.factory)
        if self.ground_truth:
            return factory(ground_truth)  # type: ignore[no-any-return]
        return factory()  # type: ignore[no-any-return]

    def missing(
        self, available: Collection[str] | None, robot: RobotDescription | str | None = None
    ) -> str | None:
        """Why this estimator cannot run on a source that provides the kinds
        ``available`` (None: not known yet) for the robot ``robot`` (its description,
        whose structure is checked too, or its name), else None."""
        name = robot if robot is None or isinstance(robot, str) else robot.name
        if name is not None and self.robots is not None and name not in self.robots:
            return (
                f"estimator {self.name!r} supports the robots {sorted(self.robots)}, not {name!r}"
            )
        if self.structure is not None and robot is not None and not isinstance(robot, str):
            problem = resolve(self.structure)(robot)
            if problem is not None:
                return f"estimator {self.name!r} cannot serve robot {name!r}: {problem}"
        if available is None:
            return None
        lacking = [k for k in sorted(self.requires) if k not in available]
        if not lacking:
            return None
        what = ", ".join(f"{k} ({self.needs[k]})" if k in self.needs else k for k in lacking)
        return f"estimator {self.name!r} needs {what}; the source has none"


def _spec_from_plugin(name: str, obj: Any) -> EstimatorSpec:
    if isinstance(obj, EstimatorSpec):
        return obj if obj.name == name else replace(obj, name=name)
    if callable(obj):
        return EstimatorSpec(name, obj)
    raise TypeError(f"expected an EstimatorSpec or a factory, got {type(obj).__name__}")


ESTIMATORS: Registry[EstimatorSpec] = Registry(
    "estimator", "tensegrity_gym.estimators", _spec_from_plugin
)


def register_estimator(
    name: str,
    factory: str | Callable[..., Estimator],
    *,
    requires: Iterable[str] = (),
    camera: bool = False,
    robots: Iterable[str] | None = None,
    summary: str = "",
    needs: dict[str, str] | None = None,
    structure: str | Callable[[RobotDescription], str | None] | None = None,
    overwrite: bool = False,
) -> EstimatorSpec:
    """Register an estimator: ``gym.make(..., estimator=name)``, ``estimate``, ``train``,
    ``evaluate`` and ``record`` then know it. See :class:`EstimatorSpec` for the fields."""
    spec = EstimatorSpec(
        name,
        factory,
        frozenset(requires),
        camera,
        None if robots is None else frozenset(robots),
        summary,
        dict(needs or {}),
        structure,
    )
    return ESTIMATORS.register(name, spec, overwrite=overwrite)


def estimator_spec(name: str) -> EstimatorSpec:
    """The registered estimator ``name``; ValueError listing the choices if none is."""
    return ESTIMATORS[name]


register_estimator(
    "ukf",
    "estimation.ukf:UkfEstimator",
    requires=("uwb",),
    summary="the unscented Kalman filter of Caluwaerts et al. 2016 (AHRS, UWB, cable lengths)",
    needs={"uwb": "UWB ranges to anchors, to place the robot"},
)
register_estimator(
    "icp",
    "estimation.icp:IcpEstimator",
    requires=("rgbd", "cable_lengths"),
    camera=True,
    structure="estimation.icp.estimator:structure_problem",
    summary="the RGB-D tracker of Lu et al. 2022",
    needs={"rgbd": "RGB-D camera frames", "cable_lengths": "cable-length sensors"},
)
register_estimator(
    "inekf",
    "estimation.inekf:InekfEstimator",
    requires=("imu", "encoders"),
    structure="estimation.inekf.shape:structure_problem",
    summary="the proprioceptive invariant EKF of Tong et al. 2024 (IMU, encoders, contacts)",
    needs={
        "imu": "the base rod's IMU, to propagate the pose",
        "encoders": "motor encoders, to reconstruct the shape",
    },
)
register_estimator(
    "oracle",
    "estimation.oracle:OracleEstimator",
    requires=(GROUND_TRUTH,),
    summary="ground truth (the simulator, or motion capture)",
    needs={GROUND_TRUTH: "the true state: the simulator or motion capture"},
)


@dataclass(frozen=True)
class TaskSpec:
    """A task by name: how to make it and the arguments of ``make`` that are its own.

    ``factory(description, control_period=seconds, **arguments)`` makes one for the
    robot ``description`` stepped every ``control_period`` seconds; ``arguments`` are the
    keyword arguments of ``gym.make`` (``make_env``) the task takes, by name.
    """

    name: str
    factory: str | Callable[..., Task]
    arguments: frozenset[str] = frozenset()
    summary: str = ""

    def check(self, arguments: Collection[str]) -> None:
        """ValueError naming each argument this task does not take."""
        unknown = sorted(set(arguments) - self.arguments)
        if unknown:
            raise ValueError(
                f"make: unknown argument {', '.join(map(repr, unknown))}: the task "
                f"{self.name!r} takes {sorted(self.arguments)} beside make's own"
            )

    def create(
        self, description: RobotDescription, control_period: float, arguments: dict[str, Any]
    ) -> Task:
        """The task for ``description``; its factory checks the values of ``arguments``."""
        self.check(arguments)
        factory = resolve(self.factory)
        return factory(description, control_period=control_period, **arguments)  # type: ignore[no-any-return]


def _task_from_plugin(name: str, obj: Any) -> TaskSpec:
    if isinstance(obj, TaskSpec):
        return obj if obj.name == name else replace(obj, name=name)
    raise TypeError(f"expected a TaskSpec, got {type(obj).__name__}")


TASKS: Registry[TaskSpec] = Registry("task", "tensegrity_gym.tasks", _task_from_plugin)


def register_task(
    name: str,
    factory: str | Callable[..., Task],
    *,
    arguments: Iterable[str] = (),
    summary: str = "",
    overwrite: bool = False,
) -> TaskSpec:
    """Register a task: ``make_env(robot, task=name, **arguments)`` then makes it. See
    :class:`TaskSpec` for the fields."""
    spec = TaskSpec(name, factory, frozenset(arguments), summary)
    return TASKS.register(name, spec, overwrite=overwrite)


def task_spec(name: str) -> TaskSpec:
    """The registered task ``name``; ValueError listing the choices if none is."""
    return TASKS[name]


register_task(
    "roll",
    "tensegrity_gym.tasks.roll:RollTask",
    arguments=("goal_heading", "goal_distance", "ctrl_cost"),
    summary="roll the CoM along a goal heading",
)
register_task(
    "goto",
    "tensegrity_gym.tasks.goto:GoToTask",
    arguments=("goal_range", "success_radius", "success_bonus", "ctrl_cost"),
    summary="reach goal points on the ground, one after another",
)
