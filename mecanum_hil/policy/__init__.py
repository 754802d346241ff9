"""Policies trained on the model and run on the robot.

- :mod:`.network`: the policy network in numpy (features, normalisation, polar action map);
- :mod:`.policies`: the trained network and its portable file, the scripted baselines;
- :mod:`.train`: training by CMA-ES through the compiled vector environment (``rl`` extra);
- :mod:`.evaluate`: success rate, return, time to target, margin, in simulation.

Running a policy on the robot is ``record --policy`` (:mod:`mecanum_hil.link.policy_session`).
"""

from __future__ import annotations

from .evaluate import Evaluation, episode_draw, evaluate
from .policies import NetworkPolicy, ScriptedPolicy, load_policy, resolve_policy

__all__ = ["Evaluation", "NetworkPolicy", "ScriptedPolicy", "episode_draw", "evaluate",
           "load_policy", "resolve_policy"]
