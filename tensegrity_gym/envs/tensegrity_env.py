"""The Gymnasium env, assembled from a backend, an estimator and a task.

The policy sees only the estimator's output. Ground truth, where the backend has it,
goes to ``info`` (``com_true``, ``estimation_error``) and nowhere else.
"""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from tensegrity_gym.model.checks import check_fraction, check_open
from tensegrity_gym.model.protocols import backend_can_wait
from tensegrity_gym.tasks.common import ObservationField

if TYPE_CHECKING:
    from collections.abc import Sequence

    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.estimate import Estimate
    from tensegrity_gym.model.protocols import ActionBase, Backend, Estimator, StepResult, Task
    from tensegrity_gym.model.samples import Sample

__all__ = ["TensegrityEnv", "base_action_layout"]

logger = logging.getLogger(__name__)


class TensegrityEnv(gym.Env[np.ndarray, np.ndarray]):
    """A tensegrity robot whose policy sees estimated states.

    Actions are ``Box(-1, 1, (m,), float32)``, one per actuated cable, mapped linearly
    onto each motor's rest-length range ``[min_rest_length, max_rest_length]``. Values
    outside [-1, 1] are clipped silently; NaN or inf raises ``ValueError``.

    The task (:class:`~tensegrity_gym.model.protocols.Task`) gives the observation, the
    reward and the end of an episode.

    ``info`` holds ``com_estimate`` (m, (3,)), ``progress`` (m, the task's),
    ``estimator_healthy``, ``estimator_reinitialised`` (and
    ``estimator_reinitialised_because``, its reason or None), ``estimator_failed_streams``
    (streams the estimator stopped fusing as implausible), ``estimator_rejected``
    (implausible measurements by kind), ``estimator_description_mismatch`` (where the
    readings contradict the description, a line each; those readings are kept),
    ``estimator_heading_std_deg`` (where the estimator tracks a pose covariance: its
    heading's std, which dead reckoning lets grow), ``reward_rejected`` (why a step
    earned no reward,
    else None), ``sim_diverged``, ``calibration`` (where the estimators' UWB calibration
    came from: ``"estimated"``, ``"true"`` or a file) and, where the backend has ground
    truth, ``com_true`` and
    ``estimation_error`` (CoM distance, m), and the task's own entries (:meth:`Task.info`).
    """

    metadata = {"render_modes": ["human", "rgb_array", "foxglove"], "render_fps": 10}  # noqa: RUF012

    def __init__(
        self,
        backend: Backend,
        estimator: Estimator,
        task: Task,
        *,
        render_mode: str | None = None,
        render_size: tuple[int, int] = (480, 360),
        calibration: str = "estimated",
        action_base: ActionBase | None = None,
        residual_scale: float = 1.0,
        observe_base: bool = False,
        residual_deadband: float = 0.0,
    ) -> None:
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"render_mode={render_mode!r} is not one of {self.metadata['render_modes']}"
            )
        self.backend = backend
        self.estimator = estimator
        self.task = task
        self.render_mode = render_mode
        self.render_size = render_size
        self.calibration = calibration
        """Where the estimators' UWB calibration comes from (``info["calibration"]``)."""
        d = backend.description
        self.action_space = spaces.Box(-1.0, 1.0, (d.n_actuated,), dtype=np.float32)
        self.action_base: ActionBase | None = None
        """None: an action is the rest-length targets; else the targets are this
        controller's action plus ``residual_scale`` times the policy's (residual)."""
        self.residual_scale = residual_scale
        self.residual_deadband = 0.0
        """The policy's actions within this of 0 are no correction (:meth:`correct`)."""
        self._observe_base = False
        self.observation_space = task.observation_space
        self._base: NDArray[np.float64] | None = None  # the base's action for the next step
        if action_base is None and residual_deadband != 0.0:
            raise ValueError(
                "TensegrityEnv: residual_deadband leaves small corrections of a base out; "
                "give action_base too"
            )
        if action_base is not None:
            self.correct(
                action_base, residual_scale, observe=observe_base, deadband=residual_deadband
            )
        lo, hi, _ = d.motor_limits
        self._target_lo, self._target_span = lo, hi - lo
        self._backend_waits = backend_can_wait(backend)
        self.stops_sent = 0
        """Stop commands this env sent (:meth:`stop_backend`)."""
        self._estimate: Estimate | None = None
        self._observation: NDArray[np.float32] | None = None
        self._closed = False

    # ------------------------------------------------------------------ helpers

    def action_to_targets(self, action: NDArray[np.floating[Any]]) -> NDArray[np.float64]:
        """Rest-length targets (m), (m,), for an action in [-1, 1]^m (clipped)."""
        a = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        return self._target_lo + 0.5 * (a + 1.0) * self._target_span

    def targets_to_action(self, targets: NDArray[np.float64]) -> NDArray[np.float32]:
        """The action that commands the given rest-length targets (m)."""
        a = 2.0 * (np.asarray(targets) - self._target_lo) / self._target_span - 1.0
        return np.clip(a, -1.0, 1.0).astype(np.float32)

    def _check_action(self, action: Any) -> NDArray[np.float64]:
        a = np.asarray(action, dtype=np.float64)
        if a.shape != self.action_space.shape:
            raise ValueError(
                f"action has shape {a.shape}, expected {self.action_space.shape} "
                f"(one entry per actuated cable)"
            )
        bad = np.flatnonzero(~np.isfinite(a))
        if bad.size:
            names = [self.backend.description.cables[int(k)].name for k in
                     self.backend.description.actuated[bad]]  # fmt: skip
            raise ValueError(
                f"action entries {bad.tolist()} (cables {names}) are not finite: {a[bad].tolist()}"
            )
        return a

    def _info(self, estimate: Estimate, diverged: bool = False) -> dict[str, Any]:
        info: dict[str, Any] = {
            "com_estimate": estimate.com.copy(),
            "progress": self.task.progress(estimate),
            "estimator_healthy": estimate.healthy,
            "estimator_reinitialised": estimate.reinitialised,
            "estimator_reinitialised_because": estimate.reinitialised_because,
            "sim_diverged": diverged,
            "estimator_failed_streams": list(estimate.failed_streams),
            "estimator_rejected": dict(estimate.rejected or {}),
            "estimator_description_mismatch": list(estimate.description_mismatch),
            "reward_rejected": None,
            "calibration": self.calibration,
        }
        if estimate.pose_covariance is not None:  # the heading a dead reckoner is unsure of
            yaw = float(estimate.pose_covariance[2, 2])
            finite = math.isfinite(yaw) and yaw >= 0.0
            info["estimator_heading_std_deg"] = math.degrees(math.sqrt(yaw)) if finite else None
        info.update(self.task.info(estimate))
        truth = None if diverged else self.backend.ground_truth()
        if truth is not None:
            info["com_true"] = truth.com.copy()
            info["estimation_error"] = float(np.linalg.norm(truth.com - estimate.com))
        return info

    def correct(
        self, base: ActionBase, scale: float, *, observe: bool = False, deadband: float = 0.0
    ) -> None:
        """Make an action a correction of ``base``: the env commands ``base``'s action
        for the observation plus ``scale`` times the policy's, clipped to [-1, 1]
        (residual actions). ``observe``: the observation ends with ``base``'s action for
        the step to come, (m,) in [-1, 1], so that a policy sees where in its period a
        periodic controller is and what it chose (a gait's phase is its own state, not
        the robot's). ``deadband`` (in [0, 1)): each entry of the policy's action is
        moved toward 0 by this much first, those within it becoming 0 (soft
        thresholding), so that a policy corrects the base only where its action is
        confidently away from 0: a marginal gait is not perturbed by a policy's small,
        noisy means. The next step needs a reset first."""
        deadband = check_fraction("deadband", deadband, where="correct")
        self.action_base, self.residual_scale, self._observe_base = base, scale, observe
        self.residual_deadband = float(deadband)
        self._estimate = self._observation = self._base = None
        space = self.task.observation_space
        if observe:
            m = self.backend.description.n_actuated
            low = np.concatenate([space.low, -np.ones(m, dtype=np.float32)])
            high = np.concatenate([space.high, np.ones(m, dtype=np.float32)])
            space = spaces.Box(low, high, dtype=np.float32)
        self.observation_space = space

    @property
    def observe_base(self) -> bool:
        """Whether the observation ends with the base's action for the step (m,)
        (:meth:`correct`)."""
        return self._observe_base

    def observation_layout(self) -> list[ObservationField]:
        """The observation's fields, entry by entry: the task's (its
        ``observation_layout()``, as :class:`~tensegrity_gym.tasks.common.GoalFrameTask`
        gives) and, with an observed base (:meth:`correct`), the base's action
        (:func:`base_action_layout`). TypeError for a task that gives no layout."""
        layout = getattr(self.task, "observation_layout", None)
        if layout is None:
            raise TypeError(f"the task {type(self.task).__name__} gives no observation_layout()")
        fields: list[ObservationField] = list(layout())
        if self._observe_base:
            start = fields[-1].stop if fields else 0
            fields += base_action_layout(self.backend.description, start)
        return fields

    def _observe(self, estimate: Estimate) -> NDArray[np.float32]:
        """The task's observation of ``estimate``; with residual actions, the base's
        action for the next step is taken from it now (and appended where observed)."""
        observation = self.task.observation(estimate)
        if self.action_base is None:
            return observation
        try:
            self._base = np.asarray(self.action_base(observation), dtype=np.float64)
        except BaseException:
            self._observation = self._base = None  # no step on from half a state
            raise
        if not self._observe_base:
            return observation
        extra = np.clip(self._base, -1.0, 1.0).astype(np.float32)
        return np.concatenate([observation, extra])

    # ------------------------------------------------------------------ gym API

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[NDArray[np.float32], dict[str, Any]]:
        check_open(self._closed, "reset")
        task_options, backend_options = self._split_options(options)
        super().reset(seed=seed)
        try:
            return self._reset(task_options, backend_options)
        except BaseException:
            self.stop_backend()
            raise

    def reset_options(self) -> list[str]:
        """The keys ``reset(options=...)`` takes: the task's (e.g. Roll's ``goal_heading``,
        ``goal_distance``) and the backend's (the simulator's ``spawn``)."""
        keys = getattr(self.task, "reset_options", ()), getattr(self.backend, "reset_options", ())
        return sorted({str(k) for group in keys for k in group})

    def _split_options(self, options: object) -> tuple[dict[str, Any], dict[str, Any]]:
        """``reset``'s options as the task's and the backend's; ValueError naming the
        keys neither takes, with the valid ones."""
        if options is None:
            return {}, {}
        if not isinstance(options, dict):
            raise ValueError(f"reset: options must be a dict, got {type(options).__name__}")
        valid = self.reset_options()
        unknown = sorted(str(k) for k in options if k not in valid)
        if unknown:
            raise ValueError(f"reset: unknown options {unknown}; valid: {valid}")
        task_keys = getattr(self.task, "reset_options", ())
        task = {k: v for k, v in options.items() if k in task_keys}
        return task, {k: v for k, v in options.items() if k not in task_keys}

    def _reset(
        self, task_options: dict[str, Any], backend_options: dict[str, Any]
    ) -> tuple[NDArray[np.float32], dict[str, Any]]:
        # Until this reset succeeds there is no episode: a step must not command the robot
        # from the previous one's state.
        self._estimate = self._observation = self._base = None
        start = self._reset_backend(backend_options)
        d = self.backend.description
        command = d.rest_lengths[d.actuated].copy()  # the motors hold their initial lengths
        estimate = self.estimator.reset(
            self.backend.description,
            self.backend.calibration,
            start.samples,
            command,
            self.np_random,
        )
        task_reset: Any = self.task.reset  # a task without options takes none
        task_reset(estimate, self.np_random, **task_options)
        if self.action_base is not None:
            self.action_base.reset()
        self._estimate = estimate
        self._observation = self._observe(estimate)
        if self.render_mode == "human":
            self.render()
        info = self._info(estimate)
        info.update(start.info)
        return self._observation, info

    def _reset_backend(self, options: dict[str, Any]) -> StepResult:
        """Reset the backend with ``options`` (its :attr:`reset_options`); one that can
        wait (a robot) waits until the estimator has what it needs to initialise."""
        check = getattr(self.estimator, "initialisation_missing", None)
        reset: Any = self.backend.reset  # a backend without options takes none
        if check is None or not self._backend_waits:
            return reset(self.np_random, **options)  # type: ignore[no-any-return]
        d = self.backend.description

        def ready(samples: Sequence[Sample]) -> str | None:
            missing: str | None = check(d, self.backend.calibration, samples)
            return missing

        return reset(self.np_random, ready=ready, **options)  # type: ignore[no-any-return]

    def step(
        self, action: NDArray[np.float32]
    ) -> tuple[NDArray[np.float32], float, bool, bool, dict[str, Any]]:
        check_open(self._closed, "step")
        try:
            return self._step(action)
        except BaseException:  # Ctrl-C included: a robot holds its motors first
            self.stop_backend()
            raise

    def stop_backend(self) -> None:
        """Hold the motors now (``Backend.stop``); a failure to do so is logged, not raised,
        so that the exception that called for it is the one the user sees."""
        self.stops_sent += 1  # read by envs.safety, which then stops no second time
        try:
            self.backend.stop()
        except Exception:
            logger.exception("the backend's stop() failed")

    def _step(
        self, action: NDArray[np.float32]
    ) -> tuple[NDArray[np.float32], float, bool, bool, dict[str, Any]]:
        if self._estimate is None or self._observation is None:
            raise RuntimeError("call reset() before step() (and again after a reset that failed)")
        a = policy_action = self._check_action(action)
        base = self._base
        if base is not None:  # the policy corrects the scripted controller
            a = np.clip(base + self.residual_scale * self.correction(a), -1.0, 1.0)
        asked = self.action_to_targets(a)
        result = self.backend.step(asked)
        if result.diverged:
            # The episode ends here; the policy gets the last finite observation.
            info = self._info(self._estimate, diverged=True)
            info.update(result.info)
            return self._observation, 0.0, False, True, info
        # What drove the period: a replayed log drives itself, a robot's limiter may trim.
        targets = asked if result.command is None else np.asarray(result.command, dtype=np.float64)
        previous = self._estimate
        estimate = self.estimator.update(result.samples, targets)
        self._estimate = estimate
        # An implausible step earns 0 whatever the task's reward would say.
        rejected = self.task.implausible_step(previous, estimate)
        reward = 0.0
        if rejected is None:
            charged = self._charged(policy_action, base, asked, targets)
            reward = self.task.reward(previous, estimate, charged)
            if not np.isfinite(reward):
                reward, rejected = 0.0, f"the reward was {reward}"
        self.task.advance(previous, estimate)  # e.g. a reached goal is replaced
        terminated = self.task.terminated(estimate)
        self._observation = self._observe(estimate)
        info = self._info(estimate)
        info["reward_rejected"] = rejected
        info.update(result.info)
        if self.render_mode == "human":
            self.render()
        return self._observation, float(reward), terminated, result.ended and not terminated, info

    def correction(self, action: NDArray[np.float64]) -> NDArray[np.float64]:
        """The correction a policy's ``action`` (m,) makes before the scale: the action
        soft-thresholded by :attr:`residual_deadband` (the action itself at 0)."""
        d = self.residual_deadband
        if d == 0.0:
            return action
        return np.sign(action) * np.maximum(np.abs(action) - d, 0.0)

    def _charged(
        self,
        action: NDArray[np.float64],
        base: NDArray[np.float64] | None,
        asked: NDArray[np.float64],
        driven: NDArray[np.float64],
    ) -> NDArray[np.float32]:
        """What the control cost charges, (m,) in [-1, 1]: the policy's ``action``; with
        residual actions that is its correction of the ``base`` before the scale (and
        before the deadband), so the gait's own commands are free and the cost does not
        teach the policy to stop rolling. Where the backend drove other rest-length
        targets (m) than those ``asked`` (a replayed log; a robot's limiter), the least
        action that implies ``driven``."""
        # ``driven is asked`` where the backend reported no command: the usual step.
        if driven is not asked and not np.allclose(driven, asked, rtol=0.0, atol=1e-9):
            action = self.targets_to_action(driven).astype(np.float64)
            if base is not None:
                correction = (action - base) / self.residual_scale
                # the deadband's inverse: a correction c came from |c| + d at least
                d = self.residual_deadband * (correction != 0.0)
                action = np.sign(correction) * (np.abs(correction) + d)
        return np.clip(action, -1.0, 1.0).astype(np.float32)

    def render(self) -> NDArray[np.uint8] | None:
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; pass render_mode to make()")
            return None
        if self.render_mode == "rgb_array":
            w, h = self.render_size
            return self.backend.render(w, h)
        return None  # "human": PyBullet's window; "foxglove": the live view streams it

    def close(self) -> None:
        """Close the backend; later resets and steps raise ``RuntimeError`` (closing
        again does nothing)."""
        if self._closed:
            return
        self._closed = True
        self._estimate = self._observation = None
        self.backend.close()


def base_action_layout(description: RobotDescription, start: int) -> list[ObservationField]:
    """What an observed base (:meth:`TensegrityEnv.correct` with ``observe=True``) appends
    to the observation from entry ``start`` on: the base's action for the step to come,
    one field per actuated cable, (m,) in total, each in [-1, 1]."""
    fields = []
    for k, index in enumerate(description.actuated):
        cable = description.cables[int(index)]
        meaning = f"the gait's action for the step to come, cable {cable.name}"
        fields.append(ObservationField(start + k, start + k + 1, meaning, "1", -1.0, 1.0))
    return fields
