"""The pinned kinematic conventions."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from mecanum_hil.model import (
    RobotProfile,
    command_to_twist,
    command_to_wheels,
    direction_scale,
    twist_to_wheels,
    wheels_to_twist,
)

K = RobotProfile().k


def test_k_of_the_paper_robot():
    assert K == pytest.approx(0.465 / 0.102)


@pytest.mark.parametrize(
    ("n", "omega", "theta", "expected"),
    [
        (100, 0, 0, (100, -100, -100, 100)),
        (100, 0, 45, (100, 0, 0, 100)),
        (0, 60, 90, (-45.59, 45.59, -45.59, 45.59)),
        (100, 0, 90, (100, 100, 100, 100)),
        (100, 0, 180, (-100, 100, 100, -100)),
        (100, 0, 270, (-100, -100, -100, -100)),
    ],
)
def test_worked_commands_give_the_pinned_wheel_speeds(n, omega, theta, expected):
    np.testing.assert_allclose(command_to_wheels(n, omega, theta, K), expected, atol=0.005)


def test_direction_scale_bounds_and_fastest_wheel():
    th = np.linspace(0, 360, 721)
    f = direction_scale(th)
    assert f.min() == pytest.approx(1 / np.sqrt(2))
    assert f.max() == pytest.approx(1.0)
    wheels = command_to_wheels(np.full_like(th, 80.0), 0.0, th, K)
    np.testing.assert_allclose(np.abs(wheels).max(axis=1), 80.0)


def test_body_velocity_signs():
    # theta = 0 is to the robot's right: -y in the robot frame
    vx, vy, wz = command_to_twist(100, 0, 0)
    assert vx == pytest.approx(0, abs=1e-12) and vy == pytest.approx(-100)
    vx, vy, wz = command_to_twist(0, 60, 90)
    assert wz == pytest.approx(10.0)  # 60 deg/s = 10 rev/min


@given(st.lists(st.floats(-200, 200), min_size=3, max_size=3))
def test_forward_inverts_inverse(twist):
    back = wheels_to_twist(twist_to_wheels(twist, K), K)
    np.testing.assert_allclose(back, twist, atol=1e-9)


def test_forward_kinematics_formulas():
    w = np.array([3.0, 7.0, -2.0, 5.0])
    vx, vy, wz = wheels_to_twist(w, K)
    assert vx == pytest.approx(w.mean())
    assert vy == pytest.approx((-w[0] + w[1] + w[2] - w[3]) / 4)
    assert wz == pytest.approx((-w[0] + w[1] - w[2] + w[3]) / (4 * K))
