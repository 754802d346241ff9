"""The reference tasks: reach a target pose, or dodge a strike. Parameters and draws.

Both tasks share the reward's form, potential-based shaping plus a bonus or a penalty at the
end::

    reward = potential(after) - potential(before) - time_cost_per_s * control_period_s
             + success_bonus    [on success]
             - failure_penalty  [on failure]

Shaping by a difference of potentials leaves the optimal policy unchanged; an episode's return
is the potential gained, minus the time spent, plus the bonus or minus the penalty. The per-robot
arithmetic (observation entries 10..12, potential, success, failure) is compiled, in
:mod:`mecanum_hil.envs._kernels`.

**reach** (:class:`ReachTask`): the robot starts at ``start_pose`` at rest; a target pose is
drawn at a distance uniform in ``[min_distance_m, max_distance_m]`` and a bearing uniform in
``[-180, 180)`` deg from the start, with a heading uniform in ``[-180, 180)`` deg. Potential
``-(distance_m / position_scale_m + |heading_error_deg| / heading_scale_deg)``. Success: position
error below ``position_tolerance_m`` and heading error below ``heading_tolerance_deg``. Failure:
farther than ``arena_radius_m`` from the start. Truncated after ``episode_s`` (rounded to whole
control periods).

**dodge** (:class:`DodgeTask`), the paper's motivation (a Tankendo sparring robot's evasive
moves): a strike comes from a direction within ``attack_arc_deg`` of the robot's initial heading,
along the line through the robot's start position, and lands after a deadline drawn uniformly in
``[min_deadline_s, max_deadline_s]``. The body (the robot profile's rectangle) must be off the
line at the deadline: the distance of its centre from the line must exceed the rectangle's
half-extent across the line (which depends on the heading) plus ``margin_m``. Potential
``-max(shortfall_m, 0) / position_scale_m`` with ``shortfall_m`` = half-extent + margin - distance.
The episode ends at the first control step at or after the deadline: success if clear, failure if
not; leaving the arena is a failure too.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from ..model import DEFAULT_POSE, RobotProfile
from . import _kernels

#: Longest simulated episode a task may ask for [s]: one hour (an evaluation of a few hundred
#: episodes of it already runs minutes; a policy file asking for more is refused, not run).
MAX_EPISODE_S = 3600.0


def _finite(task: object) -> None:
    """Every parameter a finite number (a task from a policy file may hold anything)."""
    for f in dataclasses.fields(task):  # type: ignore[arg-type]
        value = getattr(task, f.name)
        for v in value if isinstance(value, tuple | list | np.ndarray) else (value,):
            if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v):
                raise ConfigError(f"{type(task).__name__}: {f.name} must be a finite number, "
                                  f"got {value!r}")


def _positive(task: object, *names: str) -> None:
    for name in names:
        if not getattr(task, name) > 0:
            raise ConfigError(f"{type(task).__name__}: {name} must be > 0")


@dataclass(frozen=True)
class ReachTask:
    """Reach a target pose (see the module docstring).

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
    success_bonus, failure_penalty : float
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
    failure_penalty: float = 1.0
    arena_radius_m: float = 5.0
    episode_s: float = 10.0

    #: What a reset draws per robot (``task_state`` columns).
    state_names = ("target_x_m", "target_y_m", "target_phi_deg")
    #: Observation entries 10..12: name and meaning.
    observation_names = (
        ("target_forward_m", "target position ahead of the robot, robot frame [m]"),
        ("target_left_m", "target position to the robot's left, robot frame [m]"),
        ("target_dphi_deg", "target heading minus heading, wrapped to [-180, 180) [deg]"),
    )

    def __post_init__(self) -> None:
        _finite(self)
        if len(self.start_pose) != 3:
            raise ConfigError("ReachTask: start_pose must be (X, Y, phi)")
        if not 0 <= self.min_distance_m <= self.max_distance_m < self.arena_radius_m:
            raise ConfigError("ReachTask: need 0 <= min_distance_m <= max_distance_m < "
                              "arena_radius_m")
        _positive(self, "position_tolerance_m", "heading_tolerance_deg", "position_scale_m",
                  "heading_scale_deg", "episode_s")
        if self.episode_s > MAX_EPISODE_S:
            raise ConfigError(f"ReachTask: episode_s must be at most {MAX_EPISODE_S:g} s, got "
                              f"{self.episode_s:g}")

    def draw(self, rng: np.random.Generator) -> np.ndarray:
        """A target pose ``(X [m], Y [m], phi [deg])`` (three uniform variates from ``rng``)."""
        u = rng.random(3)
        dist = self.min_distance_m + u[0] * (self.max_distance_m - self.min_distance_m)
        bearing = np.deg2rad(-180.0 + 360.0 * u[1])
        x0, y0, _ = self.start_pose
        return np.array([x0 + dist * np.cos(bearing), y0 + dist * np.sin(bearing),
                         -180.0 + 360.0 * u[2]])

    def kernel_parameters(self, robot: RobotProfile) -> np.ndarray:
        """The parameters :func:`~mecanum_hil.envs._kernels.evaluate_reach` reads."""
        x0, y0, _ = self.start_pose
        return np.array([x0, y0, self.position_scale_m, self.heading_scale_deg,
                         self.position_tolerance_m, self.heading_tolerance_deg,
                         self.arena_radius_m], dtype=float)

    @property
    def evaluate(self):
        """The compiled evaluation of this task."""
        return _kernels.evaluate_reach


@dataclass(frozen=True)
class DodgeTask:
    """Move the body out of a line of attack before the strike lands (see the module docstring).

    Attributes
    ----------
    start_pose : tuple of 3 float
        ``(X [m], Y [m], phi [deg])`` at reset; the strike's line passes through this position.
    attack_arc_deg : float
        The strike comes from a direction within this angle either side of the start heading
        [deg] (90: anywhere in front; 180: from anywhere).
    min_deadline_s, max_deadline_s : float
        Range of the time until the strike lands [s].
    margin_m : float
        Clearance required beyond the body's half-extent across the line [m].
    position_scale_m : float
        Shortfall worth one unit of potential [m].
    time_cost_per_s : float
        Reward lost per second [1/s].
    success_bonus, failure_penalty : float
        Reward when clear at the deadline; reward lost when hit or on leaving the arena.
    arena_radius_m : float
        Distance from the start at which the episode ends as a failure [m].
    """

    start_pose: tuple[float, float, float] = DEFAULT_POSE
    attack_arc_deg: float = 90.0
    min_deadline_s: float = 0.6
    max_deadline_s: float = 1.2
    margin_m: float = 0.05
    position_scale_m: float = 1.0
    time_cost_per_s: float = 0.0
    success_bonus: float = 1.0
    failure_penalty: float = 1.0
    arena_radius_m: float = 5.0

    state_names = ("attack_bearing_deg", "deadline_s")
    observation_names = (
        ("line_offset_m", "distance of the robot's centre from the line of attack, positive to "
                          "the left of the strike's direction [m]"),
        ("time_to_strike_s", "time left until the strike lands [s]"),
        ("attacker_bearing_deg", "direction the strike comes from, robot frame, 0 ahead, CCW "
                                 "positive, wrapped to [-180, 180) [deg]"),
    )

    def __post_init__(self) -> None:
        _finite(self)
        if len(self.start_pose) != 3:
            raise ConfigError("DodgeTask: start_pose must be (X, Y, phi)")
        if not 0 < self.min_deadline_s <= self.max_deadline_s:
            raise ConfigError("DodgeTask: need 0 < min_deadline_s <= max_deadline_s")
        if self.max_deadline_s + 1.0 > MAX_EPISODE_S:
            raise ConfigError(f"DodgeTask: max_deadline_s must be at most "
                              f"{MAX_EPISODE_S - 1:g} s, got {self.max_deadline_s:g}")
        if not 0 <= self.attack_arc_deg <= 180:
            raise ConfigError("DodgeTask: attack_arc_deg must be within [0, 180]")
        if self.margin_m < 0:
            raise ConfigError("DodgeTask: margin_m must be >= 0")
        _positive(self, "position_scale_m", "arena_radius_m")

    @property
    def episode_s(self) -> float:
        """Longer than any deadline: the deadline, not truncation, ends an episode [s]."""
        return self.max_deadline_s + 1.0

    def draw(self, rng: np.random.Generator) -> np.ndarray:
        """``(bearing of the strike's direction [deg], deadline [s])`` (two uniform variates)."""
        u = rng.random(2)
        attacker = self.start_pose[2] + self.attack_arc_deg * (2.0 * u[0] - 1.0)
        deadline = self.min_deadline_s + u[1] * (self.max_deadline_s - self.min_deadline_s)
        return np.array([attacker + 180.0, deadline])

    def kernel_parameters(self, robot: RobotProfile) -> np.ndarray:
        """The parameters :func:`~mecanum_hil.envs._kernels.evaluate_dodge` reads."""
        x0, y0, _ = self.start_pose
        return np.array([x0, y0, self.position_scale_m, self.margin_m, self.arena_radius_m,
                         robot.body_length_m / 2.0, robot.body_width_m / 2.0], dtype=float)

    @property
    def evaluate(self):
        """The compiled evaluation of this task."""
        return _kernels.evaluate_dodge


TASKS = {"reach": ReachTask, "dodge": DodgeTask}


def resolve_task(task: ReachTask | DodgeTask | str | None) -> ReachTask | DodgeTask:
    """A task object from an object, a name (``"reach"``, ``"dodge"``) or None (reach)."""
    if task is None:
        return ReachTask()
    if isinstance(task, str):
        if task not in TASKS:
            raise ConfigError(f"unknown task {task!r} (known: {', '.join(TASKS)})")
        return TASKS[task]()
    if not isinstance(task, ReachTask | DodgeTask):
        raise ConfigError(f"task must be 'reach', 'dodge' or a task object, got {task!r}")
    return task
