"""The pure numerical core: kinematics, wheel dynamics, effects and the simulator."""

from .calibration import EFFECTS, Calibration, Effects, load_calibration, save_calibration
from .kinematics import (
    command_to_twist,
    command_to_wheels,
    direction_scale,
    twist_to_wheels,
    wheels_to_twist,
)
from .robot import RobotProfile, load_robot_profile
from .simulate import DEFAULT_POSE, Trajectory, simulate, simulate_batch, uniform_time

__all__ = [
    "DEFAULT_POSE",
    "EFFECTS",
    "Calibration",
    "Effects",
    "RobotProfile",
    "Trajectory",
    "command_to_twist",
    "command_to_wheels",
    "direction_scale",
    "load_calibration",
    "load_robot_profile",
    "save_calibration",
    "simulate",
    "simulate_batch",
    "twist_to_wheels",
    "uniform_time",
    "wheels_to_twist",
]
