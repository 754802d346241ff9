"""The pure parts: exact wheel angle, the differentiator, unwrapping, outliers, the ellipse."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mecanum_hil.errors import VideoError
from mecanum_hil.vision.geometry import Ellipse, angular_coverage, fit_ellipse
from mecanum_hil.vision.render import wheel_turns
from mecanum_hil.vision.speed import local_slope, reject_outliers, unwrap_runs, wheel_speed_rpm


def test_wheel_turns_is_the_exact_integral_of_a_piecewise_linear_speed():
    t = np.array([0.0, 1.0, 3.0])
    rpm = np.array([0.0, 60.0, 60.0])  # 0 -> 1 turn/s over 1 s, then 1 turn/s
    q = np.array([-1.0, 0.0, 0.5, 1.0, 2.0, 3.0, 4.0])
    expect = np.array([0.0, 0.0, 0.125, 0.5, 1.5, 2.5, 3.5])
    np.testing.assert_allclose(wheel_turns(t, rpm, q), expect, atol=1e-12)


def test_local_quadratic_slope_is_exact_on_a_parabola_even_with_uneven_times_and_gaps():
    rng = np.random.default_rng(1)
    t = np.cumsum(rng.uniform(0.02, 0.04, 60))
    y = 0.3 + 2.0 * t + 1.5 * t ** 2
    run = np.zeros(t.size, dtype=int)
    run[20:25] = -1
    y[20:25] = np.nan
    run[25:] = 1
    slope = local_slope(t, y, run, 2)
    ok = run >= 0
    np.testing.assert_allclose(slope[ok], (2.0 + 3.0 * t)[ok], rtol=1e-9)
    assert np.isnan(slope[20:25]).all()


def test_noise_of_the_speed_is_that_of_the_regression():
    rng = np.random.default_rng(2)
    fps, sigma = 30.0, 0.002  # [rad]
    t = np.arange(3000) / fps
    angle = 2 * np.pi * 1.0 * t + rng.normal(0.0, sigma, t.size)  # 60 rpm
    rpm, _, _ = wheel_speed_rpm(t, np.angle(np.exp(1j * angle)), 0.1)
    h = 2
    expect = sigma * fps * math.sqrt(3.0 / (h * (h + 1) * (2 * h + 1))) / (2 * np.pi) * 60.0
    assert np.std(rpm[h:-h]) == pytest.approx(expect, rel=0.1)
    assert np.mean(rpm) == pytest.approx(60.0, abs=0.01)


def test_unwrap_keeps_runs_apart_across_long_gaps():
    a = np.array([0.1, 0.2, 0.3, np.nan, np.nan, np.nan, np.nan, 0.9, 1.0]) * 2 * np.pi
    turns, run = unwrap_runs(np.angle(np.exp(1j * a)), np.arange(9) / 30.0)
    assert list(run) == [0, 0, 0, -1, -1, -1, -1, 1, 1]
    np.testing.assert_allclose(turns[[0, 1, 2]], [0.1, 0.2, 0.3])


def test_aliasing_raises_and_a_single_outlier_is_dropped():
    t = np.arange(40) / 30.0
    fast = 2 * np.pi * 0.45 * np.arange(40) ** 1.2 / 40 ** 0.2  # accelerates through 0.5 turn
    with pytest.raises(VideoError, match="aliasing"):
        wheel_speed_rpm(t, np.angle(np.exp(1j * fast)), 0.1)
    slow = 2 * np.pi * 0.02 * np.arange(40)
    slow[17] += np.pi  # one frame: something else on the path, half a turn away
    cleaned, n = reject_outliers(np.angle(np.exp(1j * slow)))
    assert n == 1 and np.isnan(cleaned[17]) and np.isfinite(np.delete(cleaned, 17)).all()
    rpm, _, dropped = wheel_speed_rpm(t, np.angle(np.exp(1j * slow)), 0.1)
    assert dropped == 1 and np.isnan(rpm[17])
    np.testing.assert_allclose(np.delete(rpm, 17), 0.02 * 30 * 60, rtol=1e-9)


def test_ellipse_maps_an_oblique_circle_back_to_uniform_angles():
    phi = np.linspace(0, 2 * np.pi, 72, endpoint=False)
    tilt, axis = math.radians(50), math.radians(30)
    rot = np.array([[math.cos(axis), -math.sin(axis)], [math.sin(axis), math.cos(axis)]])
    view = rot @ np.diag([1.0, math.cos(tilt)]) @ rot.T
    pts = (view @ np.vstack([40 * np.cos(phi), -40 * np.sin(phi)])).T + np.array([100.0, 80.0])
    e = fit_ellipse(pts)
    assert isinstance(e, Ellipse) and e.tilt_deg == pytest.approx(50.0, abs=0.01)
    rho, ang = e.unit(pts)
    np.testing.assert_allclose(rho, 1.0, atol=1e-6)
    step = np.diff(np.unwrap(ang))
    np.testing.assert_allclose(step, 2 * np.pi / 72, atol=1e-6)  # CCW positive, uniform
    assert angular_coverage(ang) == pytest.approx(1 - 1 / 72)


def test_a_wide_window_on_a_long_video_stays_small_in_memory_and_exact(monkeypatch):
    """5 min at 60 fps with a 10 s window: (frames x window) at once would take gigabytes."""
    import tracemalloc

    from mecanum_hil.vision import speed

    t = np.arange(18000) / 60.0
    y = 0.5 * t + 0.01 * t ** 2
    run = np.zeros(t.size, dtype=int)
    tracemalloc.start()
    slope = speed.local_slope(t, y, run, 300)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 300e6, peak
    np.testing.assert_allclose(slope, 0.5 + 0.02 * t, rtol=1e-6)
    # Chunked or not, the same numbers (runs and gaps cross the chunks' borders).
    t = np.arange(400) / 30.0
    y = np.sin(t) + 0.1 * t
    run = np.where(np.arange(400) % 97 < 80, np.arange(400) // 97, -1)
    y[run < 0] = np.nan
    whole = speed.local_slope(t, y, run, 5)
    monkeypatch.setattr(speed, "SLOPE_CHUNK_VALUES", 37)
    np.testing.assert_array_equal(speed.local_slope(t, y, run, 5), whole)
