"""The drive's own dynamics in the simulator: controller period, drive lag, breakaway, braking
limit, fast-decay drive."""

from __future__ import annotations

import numpy as np
import pytest

from mecanum_hil.errors import ConfigError
from mecanum_hil.model import Calibration, Effects
from mecanum_hil.model.calibration import exchange_drive_lag, load_calibration, save_calibration
from mecanum_hil.model.simulate import simulate, uniform_time

T = uniform_time(1.5, 500)


def _commands(n_rpm=60.0, reverse_at=None):
    cmd = np.zeros((T.size, 3))
    cmd[:, 2] = 90.0
    cmd[5:, 0] = n_rpm
    if reverse_at is not None:
        cmd[reverse_at:, 0] = -n_rpm
    return cmd


def _wheel(effects: Effects, **kw) -> np.ndarray:
    return simulate(_commands(**kw), T, Calibration(effects=effects)).wheel_rpm[0, :, 0]


def test_tiny_effects_approach_the_paper_model():
    ref = _wheel(Effects())
    assert np.abs(_wheel(Effects(breakaway_rpm_per_s=1e-9)) - ref).max() < 1e-9
    assert np.abs(_wheel(Effects(drive_lag_s=1e-5)) - ref).max() < 0.1
    assert np.abs(_wheel(Effects(controller_period_s=1e-4)) - ref).max() < 0.1


def test_breakaway_holds_the_wheel_until_the_drive_exceeds_it():
    # the paper's PI: drive at rest = A u + C u t; with 60 rpm it reaches 3000 rpm/s after
    # (3000 - 14.7 * 60) / (303 * 60) = 0.117 s
    w = _wheel(Effects(breakaway_rpm_per_s=3000.0))
    t_go = (3000.0 - 14.7 * 60.0) / (303.0 * 60.0)
    step = T[5]
    assert np.all(w[T <= step + t_go - 0.003] == 0.0)
    assert w[np.searchsorted(T, step + t_go + 0.01)] > 0.5
    # the integrator wound up meanwhile: a larger overshoot than without
    assert w.max() > _wheel(Effects()).max() + 5.0
    assert w[-1] == pytest.approx(60.0, abs=0.5)


def test_breakaway_sticks_a_wheel_that_stops_on_a_reversal():
    w = _wheel(Effects(breakaway_rpm_per_s=3000.0), reverse_at=400)
    stuck = np.flatnonzero(w[400:] == 0.0)
    assert stuck.size > 5  # at rest for a while before the drive breaks it away backwards
    assert w[-1] < -50.0


def test_drive_lag_makes_the_loop_ring_more():
    base, lag = _wheel(Effects()), _wheel(Effects(drive_lag_s=0.03))
    assert lag.max() > base.max() + 3.0
    assert lag[-1] == pytest.approx(60.0, abs=0.5)


def test_controller_period_holds_the_output():
    w = _wheel(Effects(controller_period_s=0.02))
    # the output held over a period acts on old speeds: a visibly different response
    assert np.abs(w - _wheel(Effects())).max() > 1.0
    # the time to the controller's next tick travels in the state (column 20)
    traj = simulate(_commands()[:101], T[:101], Calibration(effects=Effects(
        controller_period_s=0.02)))
    # 0.2 s is ten whole periods: the next tick is due now
    assert traj.final_state[0, 20] == pytest.approx(0.0, abs=1e-9)
    assert w[-1] == pytest.approx(60.0, abs=0.5)


def _reference(u_rpm, A, B, C, brake, period_s=0.0, lag_s=0.0, top_rpm=np.inf, h=2e-6,
               coast=None, no_load=np.inf):
    """Wheel speed [rpm] at T of a PI loop (output limited to ``B top_rpm``, integrating only
    while the error does not push further into the limit) through an optional drive lag around
    a first-order motor with the braking limit, or through a fast-decay drive (friction
    ``coast`` [rpm/s], no-load speed ``no_load`` [rpm]), by forward Euler on a fine grid (the
    truth the kernel's pieces are checked against): ``u_rpm`` is the target in force from each
    sample of T."""
    dmax = B * top_rpm
    y = z = hold = dl = 0.0
    next_tick = 0.0
    out = np.empty(T.size)
    out[0] = 0.0
    k = 0
    for m in range(1, T.size):
        u = u_rpm[m - 1]
        for _ in range(round((T[m] - T[m - 1]) / h)):
            e = u - y
            if period_s > 0:
                if k * h >= next_tick - 1e-12:
                    c = A * e + C * (z + e * period_s)
                    if abs(c) <= dmax or (c > 0) != (e > 0):
                        z += e * period_s
                    hold = min(max(c, -dmax), dmax)
                    next_tick += period_s
                c = hold
            else:
                c = A * e + C * z
                if abs(c) <= dmax or (c > 0) != (e > 0):
                    z += e * h
                c = min(max(c, -dmax), dmax)
            if lag_s > 0:
                dl += (c - dl) * h / lag_s
                c = dl
            if coast is not None:
                s = 1.0 if y > 0 or (y == 0 and c >= 0) else -1.0
                acc = s * (max(s * c + coast, 0.0) * (1.0 - abs(y) / no_load) - coast
                           - B * abs(y))
                if y != 0 and (y + acc * h) * y < 0:  # at rest within the step: on from there
                    y = 0.0
                    k += 1
                    continue
            else:
                acc = c - B * y
            if y > 0 and acc < -brake:
                acc = -brake
            elif y < 0 and acc > brake:
                acc = brake
            y += acc * h
            k += 1
        out[m] = y
    return out


def _stop_commands():
    cmd = _commands(n_rpm=80.0)
    cmd[300:, 0] = 0.0  # a stop from 80 rpm: the loop brakes hard
    cmd[600:, 0] = -40.0  # then a reversal
    return cmd


@pytest.mark.parametrize("period_s", [0.0, 0.008])
def test_braking_limit_caps_the_deceleration_and_not_the_acceleration(period_s):
    # a stiff loop (A 30 1/s, B 20 1/s, C 600 1/s^2) stops from 80 rpm at up to ~4000 rpm/s
    # (2300 rpm/s over the first 2-ms sample); a drive that coasts slows it at 800 rpm/s at most
    A, B, C, brake = 30.0, 20.0, 600.0, 800.0
    cmd = _stop_commands()
    cal = Calibration(A=A, B=B, C=C, effects=Effects(braking_limit_rpm_per_s=brake,
                                                     controller_period_s=period_s))
    free = Calibration(A=A, B=B, C=C, effects=Effects(controller_period_s=period_s))
    w = simulate(cmd, T, cal).wheel_rpm[0, :, 0]
    w0 = simulate(cmd, T, free).wheel_rpm[0, :, 0]
    # the rise is not touched (it accelerates away from rest)
    np.testing.assert_allclose(w[:300], w0[:300], atol=1e-9)
    slope = np.diff(w) / np.diff(T)
    slope0 = np.diff(w0) / np.diff(T)
    assert -slope0[300:330].min() > 2.5 * brake  # without the limit it brakes far harder
    moving = (np.abs(w[:-1]) > 1.0) & (w[:-1] * w[1:] > 0)  # a sample that crosses rest
    # accelerates away from it in its second part
    towards_rest = -np.sign(w[:-1]) * slope
    assert towards_rest[moving].max() <= brake * (1 + 1e-9)
    assert towards_rest[300:320].min() == pytest.approx(brake, rel=1e-6)  # at the limit
    assert w[599] == pytest.approx(0.0, abs=0.5) and w[-1] == pytest.approx(-40.0, abs=0.5)
    # exact with a held output (the phase ends in closed form); first order in the 1 ms
    # sub-step with the continuous PI
    ref = _reference(cmd[:, 0], A, B, C, brake, period_s)
    assert np.abs(w - ref).max() < (0.05 if period_s else 0.3)


@pytest.mark.parametrize("period_s", [0.0, 0.006])
def test_braking_limit_with_a_lag_and_a_ceiling_follows_the_reference(period_s):
    # a saturated PI through a drive lag, braking into a reversal: while the limit holds the
    # drive at its ceiling, the integrator must stop winding up in the braking phase as well
    # (a second reading found it did not: 17 rpm off after the reversal)
    A, B, C, brake = 30.0, 20.0, 600.0, 800.0
    cmd = _commands(n_rpm=80.0)
    cmd[300:, 0] = -60.0
    cmd[550:, 0] = 50.0
    fx = Effects(braking_limit_rpm_per_s=brake, drive_lag_s=0.01, top_speed_rpm=70.0,
                 controller_period_s=period_s)
    w = simulate(cmd, T, Calibration(A=A, B=B, C=C, effects=fx)).wheel_rpm[0, :, 0]
    ref = _reference(cmd[:, 0], A, B, C, brake, period_s, lag_s=0.01, top_rpm=70.0)
    assert np.abs(w - ref).max() < 0.5


def test_a_braking_limit_beyond_every_deceleration_is_the_paper_model():
    ref = _wheel(Effects(), reverse_at=400)
    np.testing.assert_allclose(_wheel(Effects(braking_limit_rpm_per_s=1e7), reverse_at=400),
                               ref, atol=1e-9)


@pytest.mark.parametrize("effects", [
    Effects(controller_period_s=0.012), Effects(drive_lag_s=0.02),
    Effects(breakaway_rpm_per_s=2500.0), Effects(braking_limit_rpm_per_s=400.0),
    Effects(braking_limit_rpm_per_s=500.0, controller_period_s=0.007, drive_lag_s=0.01,
            breakaway_rpm_per_s=1200.0),
    Effects(controller_period_s=0.005, drive_lag_s=0.01, breakaway_rpm_per_s=1500.0,
            top_speed_rpm=70.0, rate_limit_rpm_per_s=800.0),
    Effects(coast_decel_rpm_per_s=600.0, no_load_rpm=150.0),
    Effects(coast_decel_rpm_per_s=600.0, no_load_rpm=150.0, controller_period_s=0.005,
            drive_lag_s=0.01, breakaway_rpm_per_s=300.0, top_speed_rpm=70.0),
])
def test_a_simulation_continues_exactly_from_its_final_state(effects):
    cal = Calibration(effects=effects)
    cmd = _commands(reverse_at=450)
    whole = simulate(cmd, T, cal)
    k = 333
    a = simulate(cmd[:k + 1], T[:k + 1], cal)
    b = simulate(cmd[k:], T[k:], cal, initial_state=a.final_state, initial_pose=a.pose[0, -1])
    np.testing.assert_allclose(b.wheel_rpm[0], whole.wheel_rpm[0, k:], atol=1e-9)
    np.testing.assert_allclose(b.pose[0], whole.pose[0, k:], atol=1e-9)


def test_a_wheels_only_state_is_accepted():
    a = simulate(_commands(), T, Calibration())
    b = simulate(_commands(), T, Calibration(), initial_state=a.final_state[:, :12])
    assert b.final_state.shape == (1, 21)


def test_new_effects_round_trip_through_a_calibration_file(tmp_path):
    eff = Effects(controller_period_s=0.004, drive_lag_s=0.015, breakaway_rpm_per_s=2200.0,
                  braking_limit_rpm_per_s=1800.0)
    path = save_calibration(Calibration(effects=eff), tmp_path / "c.toml")
    text = path.read_text()
    for name in ("controller_period", "drive_lag", "breakaway", "braking_limit"):
        assert f"[effects.{name}]" in text
    assert load_calibration(path).effects == eff


@pytest.mark.parametrize("effects", [
    Effects(drive_lag_s=0.12),
    Effects(drive_lag_s=0.03, top_speed_rpm=50.0, dead_time_s=0.02, gains=(1.0, 0.9, 1.1, 1.0),
            rate_limit_rpm_per_s=400.0, deadband_rpm=2.0, controller_period_s=0.006),
])
def test_drive_lag_and_motor_pole_are_interchangeable(effects):
    # the lag's twin (lag <-> 1 / B, A and C rescaled) gives the same wheel speeds exactly:
    # wheel speeds alone cannot tell which time constant is the drive's and which the motor's
    cal = Calibration(effects=effects)
    twin = exchange_drive_lag(cal)
    assert twin.effects.drive_lag_s == pytest.approx(1.0 / cal.B)
    assert twin.B == pytest.approx(1.0 / effects.drive_lag_s)
    cmd = _commands(reverse_at=400)
    a = simulate(cmd, T, cal).wheel_rpm[0]
    b = simulate(cmd, T, twin).wheel_rpm[0]
    assert np.abs(a - b).max() < 1e-6 * np.abs(a).max()
    assert exchange_drive_lag(twin).effects.drive_lag_s == pytest.approx(effects.drive_lag_s)


@pytest.mark.parametrize(("B", "lag", "says"), [
    # B near zero: the twin's lag 1 / B and its A, C times 1 / (tau B) are absurd
    (1e-20, 0.02, "drive_lag_s = 1 / B = 1e+20 s exceeds 5 s"),
    # a lag of a picosecond: the twin's B = 1 / tau and A, C overflow the model's range
    (0.5, 1e-12, "A must be at most 1e+12"),
])
def test_a_degenerate_twin_is_refused_with_its_name_not_the_file(tmp_path, B, lag, says):
    path = save_calibration(Calibration(B=B, effects=Effects(drive_lag_s=lag)),
                            tmp_path / "user.toml")
    cal = load_calibration(path)  # a valid model: only its exchange is degenerate
    with pytest.raises(ConfigError) as err:
        exchange_drive_lag(cal, "the drive_lag exchange of the fitted model")
    text = str(err.value)
    assert text.startswith("the drive_lag exchange of the fitted model: ") and says in text
    assert "user.toml" not in text and "motor." not in text


def test_breakaway_tells_the_lag_from_the_motor_pole():
    fx = Effects(drive_lag_s=0.03, breakaway_rpm_per_s=1500.0)
    assert exchange_drive_lag(Calibration(effects=fx)) is None


def test_a_braking_limit_tells_the_lag_from_the_motor_pole():
    fx = Effects(drive_lag_s=0.03, braking_limit_rpm_per_s=1500.0)
    assert exchange_drive_lag(Calibration(effects=fx)) is None


@pytest.mark.parametrize("bad", [0.0, -100.0, float("nan")])
def test_a_braking_limit_must_be_positive(bad):
    from mecanum_hil.errors import ConfigError

    with pytest.raises(ConfigError, match="braking_limit_rpm_per_s must be > 0"):
        Effects(braking_limit_rpm_per_s=bad)


# --- the fast-decay (coasting) PWM drive


@pytest.mark.parametrize("period_s", [0.0, 0.008])
def test_a_fast_decay_drive_follows_the_reference(period_s):
    # a stiff loop (A 100 1/s) stops from 80 rpm and reverses: the push along the motion falls
    # with speed
    # (no-load 200 rpm), and where the loop asks to brake the wheel coasts at 800 rpm/s + B y
    A, B, C, coast, no_load = 100.0, 20.0, 600.0, 800.0, 200.0
    cmd = _stop_commands()
    fx = Effects(coast_decel_rpm_per_s=coast, no_load_rpm=no_load, controller_period_s=period_s)
    w = simulate(cmd, T, Calibration(A=A, B=B, C=C, effects=fx)).wheel_rpm[0, :, 0]
    ref = _reference(cmd[:, 0], A, B, C, np.inf, period_s, coast=coast, no_load=no_load)
    # exact between ticks with a held output; the continuous PI's output is held over each
    # 1-ms sub-step at its middle
    assert np.abs(w - ref).max() < (0.05 if period_s else 0.3)
    slope = np.diff(w) / np.diff(T)
    towards_rest = -np.sign(w[:-1]) * slope
    moving = (np.abs(w[:-1]) > 1.0) & (w[:-1] * w[1:] > 0)
    # never slows faster than coasting does, and coasts on the stop
    assert (towards_rest[moving] <= coast + B * np.abs(w[:-1][moving]) + 1e-6).all()
    mid = 0.5 * np.abs(w[:-1] + w[1:])
    ratio = towards_rest[300:450] / (coast + B * mid[300:450])
    assert ratio.max() == pytest.approx(1.0, abs=0.01)  # it does coast: the duty is off
    assert w[-1] < -35.0  # and the push reverses it from rest


def test_a_fast_decay_drive_without_droop_is_a_braking_limit_without_a_pole():
    # no back-EMF droop and no motor pole: the drive coasts at exactly the braking limit
    cmd = _stop_commands()
    a = simulate(cmd, T, Calibration(A=30.0, B=0.0, C=600.0, effects=Effects(
        coast_decel_rpm_per_s=800.0))).wheel_rpm[0, :, 0]
    b = simulate(cmd, T, Calibration(A=30.0, B=0.0, C=600.0, effects=Effects(
        braking_limit_rpm_per_s=800.0))).wheel_rpm[0, :, 0]
    assert np.abs(a - b).max() < 0.3


def test_a_fast_decay_drive_starts_in_its_steady_state():
    from mecanum_hil.model.simulate import steady_state

    cal = Calibration(effects=Effects(coast_decel_rpm_per_s=500.0, no_load_rpm=180.0))
    cmd = np.zeros((T.size, 3))
    cmd[:, 0], cmd[:, 2] = 60.0, 90.0
    y0 = np.full(4, 60.0)  # theta 90 deg: every wheel's target is n
    state = steady_state(cal, y0, y0)
    w = simulate(cmd, T, cal, initial_state=state[None, :]).wheel_rpm[0]
    assert np.abs(w - 60.0).max() < 1e-6


def test_a_fast_decay_drive_round_trips_and_leaves_out_an_infinite_no_load_speed(tmp_path):
    for eff in (Effects(coast_decel_rpm_per_s=2900.0, no_load_rpm=700.0),
                Effects(coast_decel_rpm_per_s=2900.0)):
        path = save_calibration(Calibration(effects=eff), tmp_path / "c.toml")
        assert "[effects.fast_decay]" in path.read_text()
        assert "inf" not in path.read_text()
        assert load_calibration(path).effects == eff
    assert Effects(coast_decel_rpm_per_s=2900.0).active() == {
        "fast_decay": {"coast_decel_rpm_per_s": 2900.0}}


@pytest.mark.parametrize("kw, message", [
    ({"coast_decel_rpm_per_s": 500.0, "braking_limit_rpm_per_s": 800.0}, "not used together"),
    ({"no_load_rpm": 300.0}, "needs a finite coast_decel"),
    ({"coast_decel_rpm_per_s": -1.0}, "coast_decel_rpm_per_s >= 0"),
    ({"coast_decel_rpm_per_s": 500.0, "no_load_rpm": 0.0}, "no_load_rpm > 0"),
])
def test_a_fast_decay_drive_is_checked(kw, message):
    from mecanum_hil.errors import ConfigError

    with pytest.raises(ConfigError, match=message):
        Effects(**kw)


@pytest.mark.parametrize("A, C", [(100.0, 600.0), (30.0, 2000.0)])
def test_a_fast_decay_drive_with_a_lag_and_a_ceiling_follows_the_reference(A, C):
    # saturated through a lag into a reversal: the integrator must stop winding up on the
    # controller's clipped output, not on the lagged one that still has the old sign (a second
    # reading found 7-13 rpm of error there)
    B, coast, no_load = 20.0, 800.0, 200.0
    cmd = _stop_commands()
    fx = Effects(coast_decel_rpm_per_s=coast, no_load_rpm=no_load, drive_lag_s=0.05,
                 top_speed_rpm=70.0)
    w = simulate(cmd, T, Calibration(A=A, B=B, C=C, effects=fx)).wheel_rpm[0, :, 0]
    ref = _reference(cmd[:, 0], A, B, C, np.inf, lag_s=0.05, top_rpm=70.0, coast=coast,
                     no_load=no_load)
    assert np.abs(w - ref).max() < 0.6


def test_breakaway_through_a_fast_decay_drive_is_smooth_in_its_threshold():
    # the instant a stuck wheel leaves rest is found in closed form, as without the drive: the
    # wheel speeds change with the threshold, so least squares can fit it
    sums = [_wheel(Effects(breakaway_rpm_per_s=b, coast_decel_rpm_per_s=500.0,
                           no_load_rpm=300.0)).sum() for b in np.linspace(3000.0, 3000.5, 6)]
    steps = np.diff(sums)
    assert np.abs(steps).min() > 1e-3 and steps.min() / steps.max() > 0.9  # one sign, smooth


def test_a_calibration_file_with_both_coasting_effects_names_the_file(tmp_path):
    from mecanum_hil.errors import ConfigError

    path = tmp_path / "both.toml"
    path.write_text("[motor]\nA = 1.0\nB = 1.0\nC = 10.0\n[effects.fast_decay]\n"
                    "coast_decel_rpm_per_s = 100.0\n[effects.braking_limit]\n"
                    "braking_limit_rpm_per_s = 50.0\n")
    with pytest.raises(ConfigError, match=r"both\.toml: \[effects\]: fast_decay and "
                                          r"braking_limit are not used together"):
        load_calibration(path)
