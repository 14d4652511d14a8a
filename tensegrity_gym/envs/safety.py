"""The outermost wrapper of every registered id: whatever fails in the wrapper stack, the
motors stop, and a failed reset leaves nothing half done.

``TensegrityEnv`` already stops its backend on any exception inside its own ``reset`` and
``step``. The wrappers ``gym.make`` puts around it can fail after the env returned (the
passive env checker did, on the first step after a failed first reset: the command had
gone out and nothing stopped the robot). This wrapper sits outside them all.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import gymnasium as gym
from gymnasium.wrappers.common import PassiveEnvChecker

if TYPE_CHECKING:
    from tensegrity_gym.envs.tensegrity_env import TensegrityEnv

__all__ = ["StopOnError"]


class StopOnError(gym.Wrapper[Any, Any, Any, Any], gym.utils.RecordConstructorArgs):
    """Stop the backend (hold the motors) on any exception out of ``reset`` or ``step``,
    Ctrl-C included, and re-raise it.

    After a failed ``reset`` the passive env checker below is re-armed: it marks its
    reset as checked before calling it, so a failed first reset left it without the data
    it compares the first step with, and every later step raised ``TypeError``.
    """

    def __init__(self, env: gym.Env[Any, Any]) -> None:
        gym.utils.RecordConstructorArgs.__init__(self)
        gym.Wrapper.__init__(self, env)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        sent = self._stops_sent()
        try:
            return self.env.reset(seed=seed, options=options)
        except BaseException:
            self._stop(sent)
            self._rearm_checkers()
            raise

    def step(self, action: Any) -> tuple[Any, Any, bool, bool, dict[str, Any]]:
        sent = self._stops_sent()
        try:
            return self.env.step(action)
        except BaseException:
            self._stop(sent)
            raise

    def _stops_sent(self) -> int:
        return int(getattr(self.env.unwrapped, "stops_sent", 0))

    def _stop(self, sent_before: int) -> None:
        """Stop, unless the env itself already did for this exception."""
        env: TensegrityEnv = self.env.unwrapped  # type: ignore[assignment]
        stop = getattr(env, "stop_backend", None)
        if stop is not None and self._stops_sent() == sent_before:
            stop()

    def _rearm_checkers(self) -> None:
        env: Any = self.env
        while isinstance(env, gym.Wrapper):
            if isinstance(env, PassiveEnvChecker) and not env.checked_step:
                env.checked_reset = False
            env = env.env
