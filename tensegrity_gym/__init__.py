"""Gymnasium environments for tensegrity robots whose policies see estimated states.

Importing the package only registers the env ids; nothing heavy is imported.
"""

from gymnasium.envs.registration import WrapperSpec, register

__version__ = "0.1.0"

_ENTRY = "tensegrity_gym.envs.factory:make_roll_env"
# Outermost: whatever fails in the stack gym.make builds, the motors stop.
_SAFETY = (WrapperSpec("StopOnError", "tensegrity_gym.envs.safety:StopOnError", {}),)

register(
    id="tensegrity_gym/ThreeBarRoll-v0",
    entry_point=_ENTRY,
    max_episode_steps=300,
    additional_wrappers=_SAFETY,
    kwargs={"robot": "three_bar"},
)
register(
    id="tensegrity_gym/ThreeBarLargeRoll-v0",
    entry_point=_ENTRY,
    max_episode_steps=300,
    additional_wrappers=_SAFETY,
    kwargs={"robot": "three_bar_large"},
)
register(
    id="tensegrity_gym/SuperBallRoll-v0",
    entry_point=_ENTRY,
    max_episode_steps=300,
    additional_wrappers=_SAFETY,
    kwargs={"robot": "superball"},
)

# The same robots through the hardware driver: the real robot, or the emulator
# (``tensegrity-gym emulate``), on the network. Pass driver="zenoh/tcp/HOST:PORT".
register(
    id="tensegrity_gym/ThreeBarRollHardware-v0",
    entry_point=_ENTRY,
    max_episode_steps=300,
    additional_wrappers=_SAFETY,
    nondeterministic=True,
    kwargs={"robot": "three_bar", "driver": "zenoh/tcp/127.0.0.1:7447"},
)
register(
    id="tensegrity_gym/SuperBallRollHardware-v0",
    entry_point=_ENTRY,
    max_episode_steps=300,
    additional_wrappers=_SAFETY,
    nondeterministic=True,
    kwargs={"robot": "superball", "driver": "zenoh/tcp/127.0.0.1:7447"},
)
