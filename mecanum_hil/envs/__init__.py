"""Gymnasium environments on the fitted model: ``MecanumHIL-v0`` and its vectorised version.

Importing this module registers ``MecanumHIL-v0`` with Gymnasium (Gymnasium 1.x has no plugin
entry-point discovery, so an import is what makes the id known)::

    import gymnasium as gym
    import mecanum_hil.envs  # noqa: F401  (registers MecanumHIL-v0)

    env = gym.make("MecanumHIL-v0", calibration="CAL.toml")
    envs = gym.make_vec("MecanumHIL-v0", num_envs=4096, calibration="CAL.toml")
    dodge = gym.make("MecanumHIL-v0", calibration="CAL.toml", task="dodge")

or, without the import, ``gym.make("mecanum_hil.envs:MecanumHIL-v0", ...)`` (Gymnasium imports
the module named before the colon).
"""

from __future__ import annotations

import gymnasium

from ._core import observation_layout
from .mecanum_env import MecanumHILEnv
from .randomisation import CoefficientRanges
from .task import DodgeTask, ReachTask
from .vector_env import MecanumHILVectorEnv

ENV_ID = "MecanumHIL-v0"

if ENV_ID not in gymnasium.registry:
    gymnasium.register(
        id=ENV_ID,
        entry_point="mecanum_hil.envs.mecanum_env:MecanumHILEnv",
        vector_entry_point="mecanum_hil.envs.vector_env:MecanumHILVectorEnv",
    )

__all__ = [
    "ENV_ID",
    "CoefficientRanges",
    "DodgeTask",
    "MecanumHILEnv",
    "MecanumHILVectorEnv",
    "ReachTask",
    "observation_layout",
]
