"""The robot profile: geometry and limits of one Mecanum robot (``drivers/*.toml``)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import LimitError
from ..io.resources import DEFAULT_ROBOT, resolve
from ..io.toml_config import TableReader, load_toml
from .kinematics import command_to_wheels


@dataclass(frozen=True)
class RobotProfile:
    """Geometry and limits of a four-wheel Mecanum robot.

    Attributes
    ----------
    name : str
        Short name of the robot.
    wheel_radius_m : float
        Wheel radius r [m].
    lx_plus_ly_m : float
        Half wheelbase plus half track, lx + ly [m].
    body_length_m, body_width_m : float
        Outer body size [m] (plots and the Gymnasium task).
    mass_kg : float
        Mass [kg] (documentation; the kinematic model does not use it).
    wheel_speed_max_rpm : float
        Largest wheel speed target the controller may be sent [rpm].
    source : str
        Where the profile came from: a shipped profile's name (``tdam-stm``), or a user's
        file as given.
    """

    name: str = "TDAM-STM"
    wheel_radius_m: float = 0.102
    lx_plus_ly_m: float = 0.465
    body_length_m: float = 0.977
    body_width_m: float = 0.775
    mass_kg: float = 100.0
    wheel_speed_max_rpm: float = 130.0
    source: str = "<defaults>"

    @property
    def k(self) -> float:
        """``(lx + ly) / r`` [-], the turning term of the Mecanum kinematics."""
        return self.lx_plus_ly_m / self.wheel_radius_m

    @property
    def omega_max_dps(self) -> float:
        """Turning speed at which a pure turn reaches the wheel speed limit [deg/s]."""
        return self.wheel_speed_max_rpm * 6.0 / self.k

    def check_commands(self, commands, what: str = "command profile") -> None:
        """Refuse commands whose wheel targets exceed the limit.

        Parameters
        ----------
        commands : array_like, shape (..., 3)
            ``(n [rpm], omega [deg/s], theta [deg])`` rows.
        what : str
            Name used in the error message.

        Raises
        ------
        LimitError
            If any value is not finite or any wheel target exceeds ``wheel_speed_max_rpm``.
        """
        c = np.asarray(commands, dtype=float).reshape(-1, 3)
        if c.size == 0:
            return
        bad = ~np.isfinite(c).all(axis=1)
        if bad.any():
            raise LimitError(f"{what}: command row {int(np.argmax(bad))} is not a finite number")
        wheels = command_to_wheels(c[:, 0], c[:, 1], c[:, 2], self.k)
        peak = np.abs(wheels).max(axis=1)
        limit = self.wheel_speed_max_rpm * (1 + 1e-9)
        if (peak > limit).any():
            i = int(np.argmax(peak > limit))
            n, w, th = c[i]
            raise LimitError(
                f"{what}: row {i} (n={n:g} rpm, omega={w:g} deg/s, theta={th:g} deg) needs a "
                f"wheel speed of {peak[i]:.1f} rpm, beyond the robot's limit of "
                f"{self.wheel_speed_max_rpm:g} rpm ({self.name})"
            )


def load_robot_profile(name_or_path: str | Path = DEFAULT_ROBOT) -> RobotProfile:
    """Read a robot profile TOML file (a shipped name such as ``tdam-stm`` or a path).

    The file has a ``[robot]`` table with ``name``, ``wheel_radius_m``, ``lx_plus_ly_m``,
    ``body_length_m``, ``body_width_m``, ``mass_kg`` and a ``[limits]`` table with
    ``wheel_speed_max_rpm``.
    """
    path = resolve("drivers", name_or_path)
    doc = TableReader(load_toml(path), str(path))
    doc.reject_unknown({"robot", "limits"})
    robot = doc.sub("robot")
    robot.reject_unknown(
        {"name", "description", "wheel_radius_m", "lx_plus_ly_m", "body_length_m",
         "body_width_m", "mass_kg"}
    )
    limits = doc.sub("limits")
    limits.reject_unknown({"wheel_speed_max_rpm"})
    return RobotProfile(
        name=robot.string("name"),
        wheel_radius_m=robot.number("wheel_radius_m", minimum=0, strict_minimum=True),
        lx_plus_ly_m=robot.number("lx_plus_ly_m", minimum=0, strict_minimum=True),
        body_length_m=robot.number("body_length_m", minimum=0, strict_minimum=True),
        body_width_m=robot.number("body_width_m", minimum=0, strict_minimum=True),
        mass_kg=robot.number("mass_kg", minimum=0, strict_minimum=True),
        wheel_speed_max_rpm=limits.number("wheel_speed_max_rpm", minimum=0, strict_minimum=True),
        # a shipped profile by its name, a user's file as given: never this machine's folders
        source=str(path) if path == Path(name_or_path) else str(name_or_path),
    )
