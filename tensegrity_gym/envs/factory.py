"""Entry points of the registered envs: assemble backend, estimator and task by name."""

from __future__ import annotations

import inspect
import os
import warnings
from typing import TYPE_CHECKING, Any

from tensegrity_gym.envs.calibration import apply_calibration, check_calibration
from tensegrity_gym.envs.tensegrity_env import TensegrityEnv
from tensegrity_gym.model.checks import check_fraction, check_number, check_whole
from tensegrity_gym.model.description import DEFAULT_GAIT, RobotDescription, load_robot
from tensegrity_gym.model.protocols import Backend, Estimator, backend_sample_kinds
from tensegrity_gym.model.randomization import Randomization, resolve_randomization
from tensegrity_gym.model.registry import ESTIMATORS, estimator_spec, task_spec
from tensegrity_gym.sim.engines import DEFAULT_ENGINE, check_engine, engine_spec
from tensegrity_gym.sim.terrain import Terrain, terrain_builder
from tensegrity_gym.sim.world import has_display
from tensegrity_gym.tasks.gaits import FaceGait

if TYPE_CHECKING:
    from pathlib import Path

    from hardware.recording import WriterSink
    from tensegrity_gym.model.registry import TaskSpec


__all__ = ["make_backend", "make_env", "make_estimator", "make_roll_env"]


def make_estimator(name: str | Estimator, backend: Backend) -> Estimator:
    """An estimator by its registered name (:mod:`tensegrity_gym.model.registry`), or the
    given object if it already is one. Refused, naming what is missing, when the backend
    cannot give what the estimator needs."""
    if not isinstance(name, str):
        if not isinstance(name, Estimator):
            raise TypeError(
                f"estimator must be one of {list(ESTIMATORS.names())} or an object with "
                f"reset() and update(); got {type(name).__name__}"
            )
        return name
    spec = estimator_spec(name)
    if spec.camera and hasattr(backend, "camera"):
        problem = backend.render_problem() if hasattr(backend, "render_problem") else None
        if problem is not None:
            raise ValueError(f"make: estimator {name!r} needs the RGB-D camera: {problem}")
        backend.camera = True  # the simulator says rgbd only while it renders frames
    missing = spec.missing(backend_sample_kinds(backend), backend.description)
    if missing is not None:
        raise ValueError(f"make: {missing}")
    return spec.create(backend.ground_truth)


_BACKEND_MEMBERS = (
    "description",
    "control_period",
    "calibration",
    "reset",
    "step",
    "stop",
    "ground_truth",
    "render",
    "close",
)


def _is_backend(obj: object) -> bool:
    """``isinstance(obj, Backend)`` without reading properties: on Python 3.11 the
    protocol check calls them, and a driver's ``calibration`` raises before ``reset``."""
    members = _BACKEND_MEMBERS
    return all(_has_static(obj, name) for name in members)


def _has_static(obj: object, name: str) -> bool:
    try:
        inspect.getattr_static(obj, name)
    except AttributeError:
        return False
    return True


def make_backend(
    description: RobotDescription,
    driver: str | Backend | None,
    *,
    control_period: float,
    time_step: float,
    gui: bool,
    spawn_radius: float,
    terrain: str | os.PathLike[str] | Terrain = "flat",
    world_seed: int = 0,
    randomization: Randomization | None = None,
    engine: str = DEFAULT_ENGINE,
) -> Backend:
    """The backend a ``driver`` names: None for PyBullet (on ``terrain``, see
    :mod:`tensegrity_gym.sim.terrain`), ``"zenoh/tcp/HOST:PORT"`` for a robot on the
    network (:class:`hardware.link.ZenohDriver`), ``"bag:PATH"`` to replay a recorded
    bag, or a Backend object (its robot must be ``description``'s). ``randomization``
    and ``engine`` apply to the simulator alone."""
    if driver is None:
        from tensegrity_gym.sim.backend import SimBackend

        return SimBackend(
            description,
            control_period=control_period,
            time_step=time_step,
            gui=gui,
            spawn_radius=spawn_radius,
            terrain=terrain,
            world_seed=world_seed,
            randomization=randomization,
            engine=engine,
        )
    if engine != DEFAULT_ENGINE:
        raise ValueError(
            f"make: engine={engine!r} picks the simulator's physics; driver={driver!r} has "
            f"a real robot: leave engine at {DEFAULT_ENGINE!r}"
        )
    if randomization is not None:
        raise ValueError(
            f"make: randomization draws the simulator's world; driver={driver!r} has a real "
            "one: leave randomization at None"
        )
    if isinstance(driver, str):
        if driver.startswith("zenoh/"):
            from hardware.link.driver import ZenohDriver

            backend: Backend = ZenohDriver(description, driver, control_period=control_period)
        elif driver.startswith("bag:") and len(driver) > 4:
            from hardware.bag.replay import ReplayBackend

            backend = ReplayBackend(driver[4:])
        else:
            raise ValueError(
                f"driver={driver!r}: expected None (PyBullet), 'zenoh/tcp/HOST:PORT' (a robot "
                "on the network), 'bag:PATH' (replay a recorded bag) or a Backend object"
            )
    elif _is_backend(driver):
        backend = driver
    else:
        raise TypeError(
            "driver must be None, 'zenoh/...', 'bag:PATH' or a Backend object; "
            f"got {type(driver).__name__}"
        )
    if backend.description.name != description.name:
        backend.close()
        raise ValueError(
            f"driver {driver!r} runs the robot {backend.description.name!r}, but this env is "
            f"for {description.name!r}; make the env of that robot"
        )
    return backend


def _check_arguments(
    *,
    render_mode: object,
    record_dir: object,
    spawn_radius: object,
    control_period: object,
    time_step: object,
    terrain: object,
    driver: object,
    viewer_port: object,
    viewer_speed: object,
    engine: object = DEFAULT_ENGINE,
) -> None:
    """Refuse a bad argument of ``make`` by name, before anything is built (an unknown or
    uninstalled engine too, in a line, rather than at the first reset)."""
    try:
        check_engine(engine)
    except (ValueError, ImportError) as err:
        raise type(err)(f"make: {err}") from None
    modes = TensegrityEnv.metadata["render_modes"]
    if render_mode is not None and render_mode not in modes:
        raise ValueError(f"make: render_mode={render_mode!r} is not one of {[None, *modes]}")
    if record_dir is not None and not isinstance(record_dir, (str, os.PathLike)):
        raise ValueError(f"make: record_dir={record_dir!r} must be a folder path or None")
    check_number("spawn_radius", spawn_radius, non_negative=True)
    period = check_number("control_period", control_period, positive=True)
    step = check_number("time_step", time_step, positive=True)
    check_whole("viewer_port", viewer_port, 0, 65535)
    check_number("viewer_speed", viewer_speed, non_negative=True)
    if step > period:
        raise ValueError(
            f"make: time_step={time_step!r} is longer than control_period={control_period!r}"
        )
    try:
        terrain_builder(terrain)  # a height map file is read (and checked) here
    except ValueError as err:
        raise ValueError(f"make: {err}") from None
    if driver is not None and not (isinstance(terrain, str) and terrain == "flat"):
        raise ValueError(
            f"make: terrain={terrain!r} shapes the simulator's ground; driver={driver!r} "
            "has its own: leave terrain at 'flat'"
        )


def _window(render_mode: object, engine: str = DEFAULT_ENGINE) -> bool:
    """Whether to open the engine's window: for ``render_mode="human"`` where there is a
    display. Without one (a headless Linux machine), or on an engine that has none, the
    env warns and runs without it, so that ``check_env`` and scripts written for a
    desktop run there too."""
    if render_mode != "human":
        return False
    if not engine_spec(engine).window:
        warnings.warn(
            f"render_mode='human' opens a window; engine {engine!r} has none: "
            "use render_mode='rgb_array' for frames",
            RuntimeWarning,
            stacklevel=3,
        )
        return False
    if has_display():
        return True
    warnings.warn(
        "render_mode='human' needs a display (DISPLAY is not set): running without "
        "PyBullet's window; use render_mode='rgb_array' for frames",
        RuntimeWarning,
        stacklevel=3,
    )
    return False


def make_env(
    robot: str | Path | RobotDescription = "three_bar",
    task: str = "roll",
    *,
    estimator: str | Estimator = "ukf",
    driver: str | Backend | None = None,
    record_dir: str | Path | None = None,
    render_mode: str | None = None,
    spawn_radius: float = 0.0,
    control_period: float = 0.1,
    time_step: float = 0.001,
    engine: str = DEFAULT_ENGINE,
    terrain: str | Path | Terrain = "flat",
    calibration: str | Path = "estimated",
    world_seed: int = 0,
    randomization: str | Randomization | None = None,
    viewer_port: int = 8765,
    viewer_speed: float = 1.0,
    residual_gait: float | None = None,
    base_gait: str = DEFAULT_GAIT,
    observe_base: bool = False,
    residual_deadband: float = 0.0,
    **task_arguments: Any,
) -> TensegrityEnv:
    """Build an env: a robot, its backend, an estimator and a task, each by name.

    Args:
        robot: a preset name, a YAML path or a loaded description.
        task: a registered name (:data:`tensegrity_gym.model.registry.TASKS`): ``"roll"``
            (:class:`~tensegrity_gym.tasks.roll.RollTask`), ``"goto"``
            (:class:`~tensegrity_gym.tasks.goto.GoToTask`), a lab's own.
        estimator: a registered name (:data:`tensegrity_gym.model.registry.ESTIMATORS`):
            ``"ukf"`` (the unscented Kalman filter of Caluwaerts et al. 2016, the default),
            ``"icp"`` (the RGB-D tracker of Lu et al. 2022; renders camera frames),
            ``"oracle"`` (ground truth), a lab's own; or an Estimator object.
        driver: ``None`` for the PyBullet simulation, ``"zenoh/tcp/HOST:PORT"`` for a
            robot (or the emulator) on the network, ``"bag:PATH"`` to replay a recorded
            bag (its commands drive it; the policy's actions are ignored), or a Backend
            object. The driver's robot must be this env's.
        record_dir: write every episode to a ROS 2 bag in this folder (``episode_000``,
            ...): samples, commands, ground truth and estimates.
        render_mode: ``None``, ``"rgb_array"``, ``"human"`` (PyBullet's window;
            without a display a warning, and none) or ``"foxglove"`` (a live view: a
            Foxglove WebSocket server streams the run's topics, as a bag holds them,
            until the env closes; needs ``pip install tensegrity-gym[viewer]``).
        viewer_port, viewer_speed: the live view's port (0: a free one) and its pace
            (run time per wall-clock time; 0: as fast as the run goes).
        spawn_radius: the start position is drawn within this radius (m).
        control_period, time_step: seconds per env step and per physics step.
        engine: the simulator's physics engine (:mod:`tensegrity_gym.sim.engines`):
            ``"pybullet"`` (the default) or ``"mujoco"`` (``pip install
            tensegrity-gym[mujoco]``), the same robot from the same description, the
            same sensor models; only with the simulator (no ``driver``).
        terrain: the simulator's ground (:mod:`tensegrity_gym.sim.terrain`): ``"flat"``
            (the default), ``"valley"`` (a ring-shaped trough around the start),
            ``"rough"`` (smooth random bumps drawn at each reset from its seed), a lab's
            registered name, a ``.npy``/``.png`` height map with its ``.yaml`` sidecar,
            or a :class:`~tensegrity_gym.sim.terrain.Terrain`. No estimator is told it.
        calibration: the UWB anchors and offsets the estimators get
            (:mod:`tensegrity_gym.envs.calibration`): ``"estimated"`` (a lab's own: in
            the simulator, calibrated from a calibration run in this world, cached on
            disk), ``"true"`` (the simulator's, for ablations) or a calibration file.
        world_seed: draws the simulated lab once for the env's life: where its anchors
            stand and every pair's UWB offset (a real lab's are constants).
        randomization: ``None`` (the description, exactly), ``"mild"``, ``"strong"``,
            ``"description"`` (the description's own error alone), a lab's registered
            name or a
            :class:`~tensegrity_gym.model.randomization.Randomization`: each reset draws
            the simulated robot and world from its ranges (``info["randomization"]``);
            the estimators keep the nominal description.
        residual_gait: ``None``: an action is the rest-length targets; a scale: an
            action corrects the robot's scripted gait
            (:class:`~tensegrity_gym.tasks.gaits.FaceGait`, reading the same
            observation), the env commanding ``gait + residual_gait * action`` clipped
            to [-1, 1] (residual actions: a policy starts from the gait and learns to
            do better). The robot must have a gait. ``ctrl_cost`` then charges the
            policy's correction (before the scale), not the command: the gait's own
            commands cost nothing.
        base_gait: the name of the gait residual actions correct, any of the robot's
            :attr:`~tensegrity_gym.model.description.RobotDescription.gaits`:
            ``"forward"`` (the default), or ``"steer"``, which rolls toward the task's
            goal; another than ``"forward"`` only with ``residual_gait``.
        observe_base: with ``residual_gait``, the observation ends with the gait's
            action for the step to come, (m,) in [-1, 1]: where in its period the gait
            is and which contraction it chose, which the robot's state does not say.
        residual_deadband: with ``residual_gait``, each entry of the policy's action is
            moved toward 0 by this much (in [0, 1)) before it corrects the gait, those
            within it correcting nothing (soft thresholding): the policy's small, noisy
            means leave the gait as it is (:meth:`TensegrityEnv.correct`).
        task_arguments: the task's own (``goal_heading``, ``goal_distance``,
            ``ctrl_cost`` for ``"roll"``; ``goal_range``, ``success_radius``,
            ``success_bonus``, ``ctrl_cost`` for ``"goto"``); another is refused by name.
    """
    description = robot if isinstance(robot, RobotDescription) else load_robot(robot)
    spec = task_spec(task)
    if isinstance(estimator, str):
        estimator_spec(estimator)  # an unknown name is refused before anything starts
    _check_arguments(
        render_mode=render_mode,
        record_dir=record_dir,
        spawn_radius=spawn_radius,
        control_period=control_period,
        time_step=time_step,
        terrain=terrain,
        driver=driver,
        viewer_port=viewer_port,
        viewer_speed=viewer_speed,
        engine=engine,
    )
    check_calibration(calibration, world_seed)
    _check_residual(description, residual_gait, base_gait, observe_base, residual_deadband)
    ranges = resolve_randomization(randomization)
    # The task checks its own arguments before anything is started.
    spec.create(description, control_period, task_arguments)
    backend = make_backend(
        description,
        driver,
        control_period=control_period,
        time_step=time_step,
        gui=_window(render_mode, engine),
        spawn_radius=spawn_radius,
        terrain=terrain,
        world_seed=world_seed,
        randomization=ranges,
        engine=engine,
    )
    try:
        source = apply_calibration(
            backend, calibration, world_seed=world_seed, control_period=control_period,
            time_step=time_step,
        )  # fmt: skip
        viewer = {"port": viewer_port, "speed": viewer_speed}
        env = _assemble(backend, estimator, spec, description, task_arguments, record_dir,
                        render_mode, source, viewer)  # fmt: skip
        if residual_gait is not None:
            gait = FaceGait(description, env.task, gait=base_gait)
            env.correct(
                gait, float(residual_gait), observe=observe_base, deadband=residual_deadband
            )
        return env
    except BaseException:
        backend.close()  # nothing half made stays open: a simulator, a link session
        raise


def _check_residual(
    description: RobotDescription,
    residual_gait: float | None,
    base_gait: str,
    observe: bool,
    deadband: float,
) -> None:
    """Refuse residual actions' arguments that cannot be (see :func:`make_env`)."""
    check_fraction("residual_deadband", deadband)
    if not isinstance(base_gait, str):
        raise ValueError(f"make: base_gait must be a gait's name, got {base_gait!r}")
    if not isinstance(observe, bool):
        raise ValueError(f"make: observe_base must be True or False, got {observe!r}")
    # Each shapes residual actions: given without them, it would silently do nothing.
    needs_residual = (
        (deadband != 0.0, "residual_deadband leaves small corrections of the gait out"),
        (observe, "observe_base=True shows the policy the gait residual actions correct"),
        (base_gait != DEFAULT_GAIT, f"base_gait={base_gait!r} names the gait residual "
                                    "actions correct"),
    )  # fmt: skip
    for given, what in needs_residual:
        if residual_gait is None and given:
            raise ValueError(f"make: {what}; give residual_gait (the correction's scale) too")
    if residual_gait is not None:
        check_number("residual_gait", residual_gait, positive=True)
        if base_gait not in description.gaits:
            raise ValueError(
                f"make: base_gait: residual_gait corrects the robot's gait {base_gait!r}; "
                f"{description.name}'s gaits: {sorted(description.gaits) or 'none'}"
            )


def _assemble(
    backend: Backend,
    estimator: str | Estimator,
    spec: TaskSpec,
    description: RobotDescription,
    task_arguments: dict[str, Any],
    record_dir: str | Path | None,
    render_mode: str | None,
    calibration: str,
    viewer: dict[str, Any],
) -> TensegrityEnv:
    """The env around a made ``backend``: its estimator, recording, live view and task."""
    est_name = estimator if isinstance(estimator, str) else None
    est = make_estimator(estimator, backend)
    if hasattr(backend, "camera"):  # the simulator renders frames only when they are used
        backend.camera = est.needs_camera
    run_info: dict[str, Any] = {
        "robot": description.name,
        "estimator": est_name or type(estimator).__name__,
        "calibration": calibration,
    }
    sinks = _sinks(backend, run_info, record_dir, render_mode == "foxglove", viewer)
    if sinks:
        from hardware.recording import FanOutSink, RecordingBackend, RecordingEstimator

        sink = sinks[0] if len(sinks) == 1 else FanOutSink(sinks)
        backend = RecordingBackend(backend, sink)
        est = RecordingEstimator(est, sink, backend)
    # A replayed bag's own control period.
    made = spec.create(description, backend.control_period, task_arguments)
    for s in sinks:  # the markers draw the task's goal where it has one
        s.goal = getattr(made, "goal_position", None)
    return TensegrityEnv(backend, est, made, render_mode=render_mode, calibration=calibration)


def _sinks(
    backend: Backend,
    run_info: dict[str, Any],
    record_dir: str | Path | None,
    live: bool,
    viewer: dict[str, Any],
) -> list[WriterSink]:
    """Where the run goes besides the env: a folder of bags, a Foxglove live view."""
    if record_dir is None and not live:
        return []
    from hardware.recording import BagSink

    truth = getattr(backend, "true_uwb", None)
    if truth is not None:  # the simulator's, beside the calibration the bag carries
        run_info["true_calibration"] = {
            "anchors": truth.anchors.tolist(),
            "uwb_offsets": truth.uwb_offsets.tolist(),
        }
    sinks: list[WriterSink] = []
    if record_dir is not None:
        sinks.append(BagSink(record_dir, run_info))
    if live:
        from hardware.viewer import FoxgloveSink

        sinks.append(FoxgloveSink(run_info=run_info, **viewer))
    return sinks


def make_roll_env(
    robot: str | Path | RobotDescription = "three_bar", **kwargs: Any
) -> TensegrityEnv:
    """The rolling env: :func:`make_env` with ``task="roll"`` (``goal_heading`` (rad),
    ``goal_distance`` (m), ``ctrl_cost``: see :class:`~tensegrity_gym.tasks.roll.RollTask`)."""
    return make_env(robot, "roll", **kwargs)
