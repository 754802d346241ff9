"""The reference task: reach a target pose. Pure, vectorised functions of the robots' state.

At each reset the robot stands at ``start_pose`` at rest and a target pose is drawn: a position at
a distance uniform in ``[min_distance_m, max_distance_m]`` and a bearing uniform in
``[-180, 180)`` deg from the start, and a heading uniform in ``[-180, 180)`` deg. The reward is
potential-based shaping plus a bonus::

    potential = -(distance_m / position_scale_m + |heading_error_deg| / heading_scale_deg)
    reward    = potential(after) - potential(before) - time_cost_per_s * period_s
                + success_bonus   [on success]  - leave_penalty   [on leaving the arena]

so the return of an episode is the improvement of the potential, minus the time spent, plus the
bonus: a policy maximises it by reaching the target pose quickly. The episode terminates on success
(position error below ``position_tolerance_m`` and heading error below ``heading_tolerance_deg``) or
when the robot leaves the arena (farther than ``arena_radius_m`` from the start), and is truncated
after ``episode_s`` seconds (rounded to whole control periods).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from ..model import DEFAULT_POSE


@dataclass(frozen=True)
class ReachTask:
    """Parameters of the reach-a-target-pose task (see the module docstring).

    Attributes
    ----------
    start_pose : tuple of 3 float
        ``(X [m], Y [m], phi [deg])`` at reset.
    min_distance_m, max_distance_m : float
        Range of the target's distance from the start [m].
    position_tolerance_m : float
        Position error counted as reached [m].
    heading_tolerance_deg : float
        Heading error counted as reached [deg].
    position_scale_m, heading_scale_deg : float
        Errors worth one unit of potential [m], [deg].
    time_cost_per_s : float
        Reward lost per second [1/s].
    success_bonus, leave_penalty : float
        Reward on success; reward lost on leaving the arena.
    arena_radius_m : float
        Distance from the start at which the episode ends as a failure [m].
    episode_s : float
        Episode length before truncation [s].
    """

    start_pose: tuple[float, float, float] = DEFAULT_POSE
    min_distance_m: float = 0.5
    max_distance_m: float = 2.0
    position_tolerance_m: float = 0.05
    heading_tolerance_deg: float = 5.0
    position_scale_m: float = 1.0
    heading_scale_deg: float = 180.0
    time_cost_per_s: float = 0.1
    success_bonus: float = 1.0
    leave_penalty: float = 1.0
    arena_radius_m: float = 5.0
    episode_s: float = 10.0

    def __post_init__(self) -> None:
        if not 0 <= self.min_distance_m <= self.max_distance_m < self.arena_radius_m:
            raise ConfigError("ReachTask: need 0 <= min_distance_m <= max_distance_m < "
                              "arena_radius_m")
        for name in ("position_tolerance_m", "heading_tolerance_deg", "position_scale_m",
                     "heading_scale_deg", "episode_s"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"ReachTask: {name} must be > 0")

    def draw_target(self, rng: np.random.Generator) -> np.ndarray:
        """A target pose ``(X [m], Y [m], phi [deg])`` (three uniform variates from ``rng``)."""
        u = rng.random(3)
        dist = self.min_distance_m + u[0] * (self.max_distance_m - self.min_distance_m)
        bearing = np.deg2rad(-180.0 + 360.0 * u[1])
        x0, y0, _ = self.start_pose
        return np.array([x0 + dist * np.cos(bearing), y0 + dist * np.sin(bearing),
                         -180.0 + 360.0 * u[2]])

    def kernel_parameters(self) -> np.ndarray:
        """The parameters the compiled evaluation reads (``mecanum_hil.envs._kernels``)."""
        x0, y0, _ = self.start_pose
        return np.array([x0, y0, self.position_scale_m, self.heading_scale_deg,
                         self.position_tolerance_m, self.heading_tolerance_deg,
                         self.arena_radius_m], dtype=float)
