"""diagnose on campaigns with hidden effects: it names them, recovers them, shrinks the gap.

Every campaign is recorded from the simulated controller (``sim-robot``'s firmware and robot,
in simulated time: :func:`~mecanum_hil.link.lockstep.record_lockstep`) whose effects file hides
the effect: the file is written and read back as ``sim-robot --effects`` reads it. A, B, C are
fitted on the campaign as a user would (``fit``), and ``diagnose`` is run without being told
anything. The campaign is the paper's kind (small and large steps, the 5 rpm/s ramp to 130 rpm,
a turn, a strafe, a diagonal): commands at 50 Hz, telemetry at 100 Hz with 0.25 rpm of wheel
noise, a camera's pose with 3 mm / 0.3 deg of noise; steps held 1.5 s to keep it short.

The link adds a latency of its own: a command reaches the controller one link delay (0.15 ms,
a pseudo-terminal's) after it is sent and acts from the controller's next 1 ms tick (commands
at 50 Hz arrive just after a tick: a whole tick later), and its telemetry reaches the host one
link delay after it is measured: the host sees about 1 ms more dead time than the robot has.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from mecanum_hil.identify.campaign import SHORT_CAMPAIGN, campaign_profiles, paper_campaign
from mecanum_hil.identify.diagnose import (
    Diagnosis,
    diagnose,
    initial_pose_at_rest,
    lag1_autocorrelation,
)
from mecanum_hil.identify.diagnose_report import write_report
from mecanum_hil.identify.fit import fit
from mecanum_hil.identify.regimes import localise, noise_sd, pooled_noise_sd
from mecanum_hil.link.effects_file import load_sim_effects, save_sim_effects, sim_effects_for
from mecanum_hil.model import Calibration, Effects, RobotProfile
from mecanum_hil.prediction import predict

ROBOT = RobotProfile()
PROFILES = campaign_profiles(**SHORT_CAMPAIGN)
NOISE_RPM = 0.25
#: The latency the link adds to the robot's own dead time as the host sees it [s].
LINK_LATENCY_S = 0.001


def _campaign(tmp_path, effects: Effects, *, unmodelled=None, seed: int = 1,
              profiles=PROFILES):
    fx = sim_effects_for(effects, wheel_rpm_std=NOISE_RPM, seed=seed, unmodelled=unmodelled)
    path = save_sim_effects(fx, tmp_path / f"robot-effects-{seed}.toml")
    assert load_sim_effects(path).effects == fx.effects
    return paper_campaign(path, ROBOT, profiles=profiles, seed=seed)


def _diagnose(recs) -> Diagnosis:
    user = fit(recs, ROBOT).calibration  # A, B, C as a user would
    return diagnose(recs, user, ROBOT)


# hidden effect -> (its parameters, what diagnose should find, absolute tolerance of each)
HIDDEN = {
    "dead_time": (Effects(dead_time_s=0.045),
                  {"dead_time_s": (0.045 + LINK_LATENCY_S, 0.003)}),
    "saturation": (Effects(top_speed_rpm=110.0), {"top_speed_rpm": (110.0, 1.0)}),
    # the same clamp without anti-windup: named as such, not as saturation
    "windup": (Effects(windup_top_speed_rpm=110.0), {"windup_top_speed_rpm": (110.0, 1.0)}),
    "rate_limit": (Effects(rate_limit_rpm_per_s=150.0),
                   {"rate_limit_rpm_per_s": (150.0, 5.0)}),
    "deadband": (Effects(deadband_rpm=6.0), {"deadband_rpm": (6.0, 0.3)}),
    "wheel_gain": (Effects(gains=(1.0, 0.85, 1.0, 1.1)),
                   {"gains": ((1.0, 0.85, 1.0, 1.1), 0.01)}),
    "slip": (Effects(efficiency=(0.9, 0.75, 0.85)), {"efficiency": ((0.9, 0.75, 0.85), 0.02)}),
}


# the drive's own dynamics: controller period within 1 ms, lag, breakaway and braking
# limit 20 %.
# (A 20 ms period on the paper's slow loop is fitted to the noise floor by a 20 ms dead time as
# well: the two cannot be told apart there; at 50 ms the held output's steps show.)
HIDDEN_DRIVE = {
    "controller_period": (Effects(controller_period_s=0.05),
                          {"controller_period_s": (0.05, 0.001)}),
    # a lag the campaign shows (fit alone is 2x the noise); 50 ms on this slow loop changes
    # nothing A, B, C cannot absorb. Named up to its exact twin (lag <-> motor pole, below).
    "drive_lag": (Effects(drive_lag_s=0.12), {"drive_lag_s": (0.12, 0.024)}),
    "breakaway": (Effects(breakaway_rpm_per_s=1500.0), {"breakaway_rpm_per_s": (1500.0, 300.0)}),
    # a drive that coasts: the paper's loop stops a wheel at up to ~3000 rpm/s
    "braking_limit": (Effects(braking_limit_rpm_per_s=800.0),
                      {"braking_limit_rpm_per_s": (800.0, 160.0)}),
    # a Coulomb friction the PI's integral overcomes: it shows in every start and stop
    "friction": (Effects(friction_rpm_per_s=600.0), {"friction_rpm_per_s": (600.0, 120.0)}),
    # a drive switched off below 6 rpm: every stop coasts on the motor's pole
    "drive_deadband": (Effects(drive_deadband_rpm=6.0), {"drive_deadband_rpm": (6.0, 0.3)}),
}


@pytest.mark.slow
@pytest.mark.parametrize("effect", [*HIDDEN, *HIDDEN_DRIVE])
def test_names_and_recovers_each_hidden_effect(effect, tmp_path):
    hidden, expect = {**HIDDEN, **HIDDEN_DRIVE}[effect]
    recs = _campaign(tmp_path, hidden)
    d = _diagnose(recs)
    assert d.effects == [effect], d.to_json()
    assert not d.unexplained
    step = d.steps[0]
    for name, (value, atol) in expect.items():
        if effect == "drive_lag":
            # wheel speeds cannot tell the drive's lag from the motor's time constant: the
            # lag named or its twin (exchange_drive_lag, reported as "equivalent") is the truth
            found = (step.parameters[name], step.equivalent[name])
            assert min(abs(f - value) for f in found) <= atol, (found, d.to_json())
            assert d.to_json()["effects"][0]["equivalent"][name] in found
            continue
        np.testing.assert_allclose(step.parameters[name], value, atol=atol)
    if effect == "slip":
        # slip changes no wheel speed: its gap is in the pose, which must shrink by half
        before = math.hypot(*step.pose_rmse_before[:2])
        after = math.hypot(*step.pose_rmse_after[:2])
        assert after <= 0.5 * before
        # and the JSON reports it: position [m] and heading [deg]
        entry = d.to_json()["effects"][0]
        assert entry["pose_rmse_after"]["position_m"] <= 0.5 * entry["pose_rmse_before"][
            "position_m"]
    else:
        assert d.rmse_final <= 0.5 * d.rmse_initial
        # a held controller output sees a command one link latency later than the host sent
        # it (docs/diagnose.md): a little structure remains with the drive's own dynamics
        assert d.rmse_final < (1.5 if effect in HIDDEN_DRIVE else 1.1) * NOISE_RPM
    # the extended calibration simulates the robot: RMSE at the noise level
    assert d.calibration.effects.active().keys() == {effect}


@pytest.mark.slow
def test_a_fast_decay_drive_is_named_with_its_friction_and_no_load_speed(tmp_path):
    # a coasting drive's friction shows only where the loop asks to brake harder than it: on
    # the paper's slow loop the reversal, not the stops (on a campaign without a reversal the
    # friction and the motor pole trade exactly: B + u0 / Y0 is what the driven wheels see)
    fx = sim_effects_for(Effects(coast_decel_rpm_per_s=200.0, no_load_rpm=300.0),
                         wheel_rpm_std=NOISE_RPM, seed=1)
    path = save_sim_effects(fx, tmp_path / "robot-effects.toml")
    recs = paper_campaign(path, ROBOT, profiles=campaign_profiles(
        **{**SHORT_CAMPAIGN, "reverse": True}), seed=1)
    d = _diagnose(recs)
    assert d.effects == ["fast_decay"], d.to_json()
    found = d.steps[0].parameters
    assert found["coast_decel_rpm_per_s"] == pytest.approx(200.0, rel=0.2)
    assert found["no_load_rpm"] == pytest.approx(300.0, rel=0.2)
    assert d.rmse_final < 1.5 * NOISE_RPM and not d.unexplained


@pytest.mark.slow
def test_no_hidden_effect_names_nothing(tmp_path):
    d = _diagnose(_campaign(tmp_path, Effects(), seed=2))
    assert d.effects == []
    assert not d.unexplained
    assert d.to_json()["effects"] == []
    assert d.rmse_final == pytest.approx(d.rmse_initial, rel=0.02)


@pytest.mark.slow
def test_two_hidden_effects_are_both_named(tmp_path):
    hidden = Effects(dead_time_s=0.035, top_speed_rpm=110.0)
    d = _diagnose(_campaign(tmp_path, hidden, seed=3))
    assert sorted(d.effects) == ["dead_time", "saturation"], d.to_json()
    assert not d.unexplained
    assert d.calibration.effects.dead_time_s == pytest.approx(0.035 + LINK_LATENCY_S, abs=0.003)
    assert d.calibration.effects.top_speed_rpm == pytest.approx(110.0, abs=1.5)
    assert d.rmse_final <= 0.5 * d.rmse_initial
    # the JSON document of docs/diagnose.md, key for key
    doc = d.to_json()
    assert list(doc) == ["effects", "unexplained", "rmse_initial", "rmse_final",
                         "rmse_baseline", "noise_rpm", "rmse_reference", "explained_share",
                         "pose_rmse_before", "pose_rmse_after", "residual"]
    assert [list(e) for e in doc["effects"]] == [
        ["effect", "parameters", "rmse_before", "rmse_after", "share", "pose_rmse_before",
         "pose_rmse_after"]] * 2
    assert doc["effects"][0]["rmse_before"] == pytest.approx(d.steps[0].rmse_before)


@pytest.mark.slow
def test_effect_outside_the_library_is_unexplained_not_mislabelled(tmp_path):
    # the rollers' periodic speed ripple: nothing in the library is periodic in wheel angle
    recs = _campaign(tmp_path, Effects(), seed=4,
                     unmodelled={"roller_ripple": {"amplitude": 0.05, "per_turn": 8.0}})
    d = _diagnose(recs)
    assert d.unexplained
    # an effect that stands in for part of it may be kept (it helps held out), but it cannot
    # take the residual to the noise: the rest is reported with its shape
    assert all(d.share(s) < 0.9 for s in d.steps), d.to_json()
    assert d.check.structured
    assert d.to_json()["residual"]["shares"]
    text = write_report(d, recs, tmp_path, ROBOT).read_text()
    assert "**Unexplained:**" in text
    assert (tmp_path / "unexplained.png").stat().st_size > 10_000


@pytest.mark.slow
def test_resonance_outside_the_library_is_unexplained_not_mislabelled(tmp_path):
    # a lightly damped 3 Hz mode: effects of the library may each mimic part of its lag and are
    # kept where they help held out, but the residual stays structured and rings near 3 Hz
    d = _diagnose(_campaign(tmp_path, Effects(), seed=5,
                            unmodelled={"resonance": {"natural_hz": 3.0, "damping": 0.15}}))
    assert d.unexplained
    assert d.shape is not None


@pytest.mark.slow
def test_localisation_points_at_the_regime_where_the_model_fails(tmp_path):
    recs = _campaign(tmp_path, Effects(top_speed_rpm=110.0), seed=6)
    cal = Calibration()
    loc = localise(recs, [predict(r, cal, ROBOT) for r in recs], ROBOT,
                   [r.metadata["profile"] for r in recs])
    assert loc.worst_regimes()[0] == "high speed"
    by_name = {r.name: r for r in loc.recordings}
    assert by_name["step-120rpm"].rmse_rpm > 5 * by_name["step-30rpm"].rmse_rpm
    assert loc.noise_rpm == pytest.approx(NOISE_RPM, rel=0.1)
    recs = _campaign(tmp_path, Effects(dead_time_s=0.05), seed=6)
    loc = localise(recs, [predict(r, cal, ROBOT) for r in recs], ROBOT)
    assert loc.worst_regimes()[0] == "transient"


def test_noise_level_from_differences():
    rng = np.random.default_rng(0)
    t = np.linspace(0, 10, 2000)
    smooth = 50 * np.sin(t)[:, None] * np.ones((1, 4))
    assert noise_sd(smooth + rng.normal(0, 0.7, smooth.shape)) == pytest.approx(0.7, rel=0.05)
    # quantised counts: MAD of the differences is zero, the trimmed RMS is not
    quant = np.round(rng.normal(0, 0.3, (500, 2)))
    assert pooled_noise_sd([quant]) > 0
    white = rng.normal(0, 1, (3000, 4))
    assert abs(lag1_autocorrelation([white])) < 0.05


def test_initial_pose_is_averaged_over_the_rest(tmp_path):
    recs = _campaign(tmp_path, Effects(), seed=7, profiles=PROFILES[:1])
    rec = initial_pose_at_rest(recs[0])
    # 0.3 s at rest: 30 samples, so the first pose is 5 times closer to the truth
    assert abs(rec.pose[0, 2] - 90.0) < 0.2
    np.testing.assert_array_equal(rec.pose[1:], recs[0].pose[1:])


def test_bad_input_is_a_diagnose_error(tmp_path):
    from mecanum_hil.errors import DiagnoseError

    recs = _campaign(tmp_path, Effects(), seed=8, profiles=PROFILES[:2])
    with pytest.raises(DiagnoseError, match="no recordings"):
        diagnose([], Calibration(), ROBOT)
    with pytest.raises(DiagnoseError, match="unknown effect"):
        diagnose(recs, Calibration(), ROBOT, candidates=("backlash",))
    empty = [r.with_values(wheel_rpm=np.full_like(r.wheel_rpm, np.nan)) for r in recs]
    with pytest.raises(DiagnoseError, match="no measured wheel speeds"):
        diagnose(empty, Calibration(), ROBOT)


def _profiles_ramp_ceiling():
    from mecanum_hil.profiles import ramp, step

    # the steps stay below the 110 rpm ceiling: only the ramp reaches it
    return [step(30.0, duration_s=1.5, rest_s=0.3, stop_s=1.0),
            step(60.0, duration_s=1.5, rest_s=0.3, stop_s=1.0),
            step(90.0, duration_s=1.5, rest_s=0.3, stop_s=1.0),
            ramp(130.0, 40.0, hold_s=0.5, rest_s=0.3, stop_s=1.0)]


@pytest.mark.slow
def test_dead_time_and_a_ceiling_only_the_ramp_reaches_are_both_named(tmp_path):
    fx = sim_effects_for(Effects(dead_time_s=0.035, top_speed_rpm=110.0),
                         wheel_rpm_std=NOISE_RPM, seed=12)
    path = save_sim_effects(fx, tmp_path / "truth.toml")
    recs = paper_campaign(path, ROBOT, profiles=_profiles_ramp_ceiling(), seed=12)
    d = _diagnose(recs)
    assert sorted(d.effects) == ["dead_time", "saturation"], d.to_json()
    assert d.calibration.effects.top_speed_rpm == pytest.approx(110.0, abs=2.0)
    assert d.calibration.effects.dead_time_s == pytest.approx(0.035 + LINK_LATENCY_S, abs=0.004)


@pytest.mark.slow
def test_a_ceiling_one_recording_of_four_reaches_is_named(tmp_path):
    from mecanum_hil.profiles import step

    profiles = [step(v, duration_s=1.5, rest_s=0.3, stop_s=1.0) for v in (20.0, 50.0, 80.0)]
    profiles.append(step(125.0, duration_s=2.5, rest_s=0.3, stop_s=1.0))
    fx = sim_effects_for(Effects(top_speed_rpm=110.0), wheel_rpm_std=NOISE_RPM, seed=13)
    path = save_sim_effects(fx, tmp_path / "truth.toml")
    d = _diagnose(paper_campaign(path, ROBOT, profiles=profiles, seed=13))
    assert d.effects == ["saturation"], d.to_json()
    assert d.calibration.effects.top_speed_rpm == pytest.approx(110.0, abs=2.0)
    assert d.rmse_final <= 0.5 * d.rmse_initial


@pytest.mark.slow
def test_a_ceiling_is_named_from_the_corner_fit_lands_in(tmp_path):
    # The quick demo's two experiments (a 120 rpm step, a turn) on a drive with a 115 rpm
    # ceiling and a noisy encoder (2 rpm): fit lands in its C -> 0 corner, whose lower
    # steady-state gain mimics the ceiling. The ceiling's start 2 % above the fastest smoothed
    # speed (120.8 rpm here) lay above the target: the grid restart from the corner offered
    # only corners, where the ceiling never engages, and diagnose named nothing (the demo
    # did so once in CI). It is also held at that speed itself now.
    from mecanum_hil.identify.diagnose.candidates import degenerate
    from mecanum_hil.profiles import resolve_profile

    fx = sim_effects_for(Effects(top_speed_rpm=115.0), wheel_rpm_std=2.0, seed=12)
    path = save_sim_effects(fx, tmp_path / "truth.toml")
    recs = paper_campaign(path, ROBOT, profiles=[resolve_profile(n) for n in (
        "paper-step-120", "paper-turn")], pose_noise=None, seed=12)
    user = fit(recs, ROBOT).calibration
    assert degenerate(user), user
    d = diagnose(recs, user, ROBOT)
    assert d.effects == ["saturation"], d.to_json()
    assert d.calibration.effects.top_speed_rpm == pytest.approx(115.0, abs=1.0)


def test_one_recording_is_enough(tmp_path):
    # one recording: models are compared on held-out time blocks inside it
    from mecanum_hil.identify.diagnose.heldout import heldout_units
    from mecanum_hil.identify.diagnose.localise import _Evaluator

    fx = sim_effects_for(Effects(dead_time_s=0.04), wheel_rpm_std=NOISE_RPM, seed=14)
    path = save_sim_effects(fx, tmp_path / "truth.toml")
    from mecanum_hil.profiles import step

    rec = paper_campaign(path, ROBOT, profiles=[step(60.0, duration_s=1.5, rest_s=0.3,
                                                     stop_s=1.0)], seed=14)[0]
    units = heldout_units(_Evaluator([rec], ROBOT), {0: 400})
    assert len(units) >= 4 and not np.logical_and.reduce([u[1] for u in units]).any()
    d = _diagnose([rec])
    assert d.effects == ["dead_time"], d.to_json()
    assert d.calibration.effects.dead_time_s == pytest.approx(0.04 + LINK_LATENCY_S, abs=0.004)
    doc = d.to_json()
    assert doc["rmse_reference"] is not None and doc["explained_share"] is not None
