"""The overhead scene (``scene.toml``): markers on the floor at known places and the robot's.

World frame of docs/conventions.md (X, Y on the floor [m], z up). A marker's own frame: origin at
its centre, x axis from its top-left to its top-right corner as printed, y axis from its bottom
edge to its top edge, z out of its face (up). Its corners in OpenCV's order (top-left,
top-right, bottom-right, bottom-left) are then ``(-s/2, s/2), (s/2, s/2), (s/2, -s/2),
(-s/2, -s/2)`` with ``s`` the black square's side.

``scene.toml``::

    [markers]
    dictionary = "DICT_4X4_50"

    [[floor]]
    id = 1
    x_m = 0.0
    y_m = -0.8
    size_m = 0.25
    yaw_deg = 30.0

    [robot]
    marker_id = 0
    size_m = 0.2
    height_m = 0.23      # the marker's plane above the floor
    forward_m = 0.2      # its centre from the robot's centre, robot frame (x forward, y left)
    left_m = 0.1
    yaw_deg = -70.0      # from the robot's forward axis to the marker's x axis
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..io.toml_config import TableReader, load_toml, toml_value, write_toml

#: Marker corners in the marker's frame for a unit side, OpenCV's order.
UNIT_CORNERS = np.array([[-0.5, 0.5], [0.5, 0.5], [0.5, -0.5], [-0.5, -0.5]])


@dataclass(frozen=True)
class FloorMarker:
    """A marker lying flat on the floor: id, centre ``(x_m, y_m)`` [m], side [m], yaw [deg]."""

    id: int
    x_m: float
    y_m: float
    size_m: float
    yaw_deg: float

    def corners_m(self) -> np.ndarray:
        """World corners ``(X, Y, 0)`` [m] in OpenCV's order, shape (4, 3)."""
        xy = marker_corners_xy(self.x_m, self.y_m, self.size_m, self.yaw_deg)
        return np.column_stack([xy, np.zeros(4)])


@dataclass(frozen=True)
class RobotMarker:
    """The marker on the robot.

    Attributes
    ----------
    marker_id : int
    size_m : float
        The black square's side [m].
    height_m : float
        Height of the marker's plane above the floor [m].
    forward_m, left_m : float
        The marker's centre from the robot's centre, robot frame [m].
    yaw_deg : float
        From the robot's forward axis to the marker's x axis [deg].
    """

    marker_id: int
    size_m: float
    height_m: float
    forward_m: float = 0.0
    left_m: float = 0.0
    yaw_deg: float = -90.0

    def marker_pose(self, x_m, y_m, phi_deg):
        """World pose of the marker's centre ``(X, Y, yaw_deg)`` for robot poses (arrays)."""
        phi = np.radians(phi_deg)
        c, s = np.cos(phi), np.sin(phi)
        return (x_m + c * self.forward_m - s * self.left_m,
                y_m + s * self.forward_m + c * self.left_m, phi_deg + self.yaw_deg)

    def robot_pose(self, mx_m, my_m, marker_yaw_deg):
        """Robot pose ``(X, Y, phi_deg)`` from the marker's world pose (arrays)."""
        phi_deg = marker_yaw_deg - self.yaw_deg
        phi = np.radians(phi_deg)
        c, s = np.cos(phi), np.sin(phi)
        return (mx_m - (c * self.forward_m - s * self.left_m),
                my_m - (s * self.forward_m + c * self.left_m), phi_deg)


@dataclass(frozen=True)
class Scene:
    """Dictionary, floor markers and the robot's marker."""

    dictionary: str
    floor: tuple[FloorMarker, ...]
    robot: RobotMarker

    def floor_by_id(self) -> dict[int, FloorMarker]:
        """Floor markers by id."""
        return {m.id: m for m in self.floor}


def marker_corners_xy(x_m, y_m, size_m, yaw_deg) -> np.ndarray:
    """Corners (4, 2) [m] of a square marker centred at ``(x_m, y_m)`` turned by ``yaw_deg``."""
    a = math.radians(yaw_deg)
    rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    return np.array([x_m, y_m]) + (UNIT_CORNERS * size_m) @ rot.T


def dictionary_by_name(name: str):
    """OpenCV's predefined ArUco/AprilTag dictionary ``name`` (e.g. ``DICT_4X4_50``,
    ``DICT_APRILTAG_36h11``)."""
    import cv2

    key = name if name.startswith("DICT_") else f"DICT_{name}"
    value = getattr(cv2.aruco, key, None)
    if not isinstance(value, int):
        raise ConfigError(f"unknown marker dictionary '{name}' (OpenCV names such as "
                          "DICT_4X4_50, DICT_6X6_250, DICT_APRILTAG_36h11)")
    return cv2.aruco.getPredefinedDictionary(value)


def load_scene(path: str | Path) -> Scene:
    """Read ``scene.toml`` (see the module docstring).

    Raises
    ------
    ConfigError
        Missing file, table or key, bad value, duplicate ids, fewer than one floor marker.
    """
    p = Path(path)
    doc = load_toml(p)
    root = TableReader(doc, str(p))
    root.reject_unknown({"markers", "floor", "robot"})
    markers = root.sub("markers")
    assert markers is not None
    markers.reject_unknown({"dictionary"})
    dictionary = markers.string("dictionary")
    dictionary_by_name(dictionary)
    floor_list = doc.get("floor", [])
    if not isinstance(floor_list, list) or not floor_list:
        raise ConfigError(f"{p}: needs at least one [[floor]] marker")
    floor = []
    for i, tab in enumerate(floor_list):
        r = TableReader(tab, str(p), f"floor[{i}]")
        r.reject_unknown({"id", "x_m", "y_m", "size_m", "yaw_deg"})
        mid = r.whole_number("id", minimum=0)
        floor.append(FloorMarker(mid, r.number("x_m"), r.number("y_m"),
                                 r.number("size_m", minimum=0, strict_minimum=True),
                                 r.number("yaw_deg", 0.0)))
    rob = root.sub("robot")
    assert rob is not None
    rob.reject_unknown({"marker_id", "size_m", "height_m", "forward_m", "left_m", "yaw_deg"})
    rid = rob.whole_number("marker_id", minimum=0)
    robot = RobotMarker(rid, rob.number("size_m", minimum=0, strict_minimum=True),
                        rob.number("height_m", minimum=0), rob.number("forward_m", 0.0),
                        rob.number("left_m", 0.0), rob.number("yaw_deg", -90.0))
    ids = [m.id for m in floor] + [robot.marker_id]
    if len(set(ids)) != len(ids):
        raise ConfigError(f"{p}: marker ids must be distinct (floor and robot), got {ids}")
    return Scene(dictionary, tuple(floor), robot)


def scene_to_toml(scene: Scene, header: str = "") -> str:
    """``scene.toml`` text."""
    lines = [f"# {line}" for line in header.splitlines()] if header else []
    lines += ["[markers]", f"dictionary = {toml_value(scene.dictionary)}", ""]
    for m in scene.floor:
        lines += ["[[floor]]", f"id = {m.id}", f"x_m = {toml_value(float(m.x_m))}",
                  f"y_m = {toml_value(float(m.y_m))}", f"size_m = {toml_value(float(m.size_m))}",
                  f"yaw_deg = {toml_value(float(m.yaw_deg))}", ""]
    r = scene.robot
    lines += ["[robot]", f"marker_id = {r.marker_id}", f"size_m = {toml_value(float(r.size_m))}",
              f"height_m = {toml_value(float(r.height_m))}",
              f"forward_m = {toml_value(float(r.forward_m))}",
              f"left_m = {toml_value(float(r.left_m))}",
              f"yaw_deg = {toml_value(float(r.yaw_deg))}"]
    return "\n".join(lines) + "\n"


def save_scene(scene: Scene, path: str | Path, header: str = "") -> Path:
    """Write ``scene.toml``."""
    return write_toml(path, scene_to_toml(scene, header), "the scene file")
