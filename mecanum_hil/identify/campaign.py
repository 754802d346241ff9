"""Identification campaigns generated with the model itself: the paper's experiments, plus noise.

A campaign is what a user would record on the robot to fit and diagnose the model: steps of
several sizes (including small ones, where a deadband shows), the paper's 5 rpm/s ramp up to the
130 rpm command limit (past a drive's ceiling), a turn on the spot, a strafe and a diagonal
run. :func:`paper_campaign` simulates it with a calibration whose effects are hidden from the
later analysis, and adds measurement noise to the wheel speeds and the pose (a camera's).

Effects outside the model's library, to check that ``diagnose`` says "unexplained" instead of
naming the closest wrong effect, are applied to a finished recording by :func:`add_resonance`
(a lightly damped mode between the drive and the encoder, e.g. a flexible coupling) and
:func:`add_roller_ripple` (the Mecanum rollers' speed ripple: a periodic gain over each wheel
turn).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from ..io.recording import Recording
from ..model.calibration import Calibration
from ..model.robot import RobotProfile
from ..model.simulate import DEFAULT_POSE, simulate
from ..prediction import trajectory_to_recording
from ..profiles import CommandProfile, Segment, ramp, step

#: Step sizes of the campaign [rpm]: small ones (a deadband shows), the paper's, past 100 rpm.
CAMPAIGN_STEPS_RPM = (4.0, 8.0, 15.0, 30.0, 60.0, 100.0, 120.0)


def campaign_profiles(*, steps_rpm: Sequence[float] = CAMPAIGN_STEPS_RPM,
                      step_hold_s: float = 2.0, ramp_rate_rpm_per_s: float = 5.0,
                      ramp_top_rpm: float = 130.0, motion_rpm: float = 60.0,
                      turn_dps: float = 60.0, reverse: bool = True) -> list[CommandProfile]:
    """The command profiles of a campaign like the paper's.

    Parameters
    ----------
    steps_rpm : sequence of float
        Sizes of the straight steps [rpm].
    step_hold_s : float
        How long each step is held [s].
    ramp_rate_rpm_per_s : float
        Slope of the ramp [rpm/s] (the paper: 5).
    ramp_top_rpm : float
        End of the ramp [rpm] (the paper: the 130 rpm command limit).
    motion_rpm : float
        ``n`` of the strafe and the diagonal run [rpm].
    turn_dps : float
        Turning speed of the turn on the spot [deg/s].
    reverse : bool
        Also a reversing step (forward, then backward).

    Returns
    -------
    list of CommandProfile
        Straight steps (:data:`CAMPAIGN_STEPS_RPM`), the ramp, a turn (omega), a strafe to the
        right (theta 0), a diagonal run (theta 45) and a reversing step (forward, then back).
    """
    kw = {"duration_s": step_hold_s, "rest_s": 0.3, "stop_s": 1.0}
    out = [step(n, name=f"step-{n:g}rpm", **kw) for n in steps_rpm]
    out.append(ramp(ramp_top_rpm, ramp_rate_rpm_per_s, hold_s=1.0, rest_s=0.3, stop_s=1.0,
                    name=f"ramp-{ramp_rate_rpm_per_s:g}rpm-per-s"))
    out.append(step(0.0, omega_dps=turn_dps, name=f"turn-{turn_dps:g}dps", **kw))
    out.append(step(motion_rpm, theta_deg=0.0, name="strafe-right", **kw))
    out.append(step(motion_rpm, theta_deg=45.0, name="diagonal-45deg", **kw))
    if reverse:
        out.append(CommandProfile("reverse-45rpm", (
            Segment("hold", 0.3), Segment("step", step_hold_s, 45.0),
            Segment("step", step_hold_s, -45.0), Segment("step", 1.0, 0.0)), (0.0, 0.0, 90.0)))
    return out


def paper_campaign(calibration: Calibration | None = None, robot: RobotProfile | None = None, *,
                   rate_hz: float = 50.0, noise_rpm: float = 1.0, pose_noise_m: float = 0.003,
                   heading_noise_deg: float = 0.3, seed: int = 0,
                   profiles: Sequence[CommandProfile] | None = None,
                   distort: Callable[[Recording, np.random.Generator], Recording] | None = None,
                   ) -> list[Recording]:
    """Simulate a campaign on a robot whose true model is ``calibration`` (effects included).

    Parameters
    ----------
    calibration : Calibration, optional
        The "true" robot: coefficients and hidden effects (default: the paper's, no effects).
    robot : RobotProfile, optional
        Geometry (default: the paper's robot).
    rate_hz : float
        Sample rate of the recordings [Hz].
    noise_rpm : float
        Standard deviation of white noise added to each wheel speed [rpm].
    pose_noise_m, heading_noise_deg : float
        Standard deviation of white noise on X, Y [m] and on the heading [deg].
    seed : int
        Seed of the noise (the campaign is reproducible).
    profiles : sequence of CommandProfile, optional
        Profiles to run (default :func:`campaign_profiles`).
    distort : callable, optional
        ``distort(recording, rng) -> recording`` applied to the noiseless simulation, for
        effects outside the model's library (:func:`add_resonance`, :func:`add_roller_ripple`).

    Returns
    -------
    list of Recording
        One recording per profile, with wheel speeds and pose; ``metadata["profile"]`` names it
        and ``metadata["true_effects"]`` holds the hidden effects.
    """
    cal = calibration or Calibration()
    rob = robot or RobotProfile()
    rng = np.random.default_rng(seed)
    out = []
    for prof in profiles if profiles is not None else campaign_profiles():
        t, cmd = prof.sample(rate_hz)
        rob.check_commands(cmd, prof.name)
        traj = simulate(cmd, t, cal, rob, initial_pose=DEFAULT_POSE)
        rec = trajectory_to_recording(traj, {
            "source": "mecanum-hil paper_campaign", "profile": prof.name,
            "true_coefficients": {"A": cal.A, "B": cal.B, "C": cal.C},
            "true_effects": cal.effects.active()})
        if distort is not None:
            rec = distort(rec, rng)
        pose_sd = np.array([pose_noise_m, pose_noise_m, heading_noise_deg])
        rec = rec.with_values(
            wheel_rpm=rec.wheel_rpm + rng.normal(0.0, noise_rpm, rec.wheel_rpm.shape),
            pose=rec.pose + rng.normal(0.0, 1.0, rec.pose.shape) * pose_sd)
        out.append(rec)
    return out


def add_resonance(natural_hz: float = 3.0, damping: float = 0.15
                  ) -> Callable[[Recording, np.random.Generator], Recording]:
    """An effect outside the library: a lightly damped mode between drive and encoder.

    The measured wheel speed is the model's wheel speed passed through
    ``wn^2 / (s^2 + 2 zeta wn s + wn^2)`` (exact zero-order-hold discretisation), as a flexible
    coupling between motor and wheel would: every change of speed rings at ``natural_hz``.
    The pose is left as simulated.

    Parameters
    ----------
    natural_hz : float
        Natural frequency of the mode [Hz].
    damping : float
        Damping ratio zeta [-].
    """
    from scipy.linalg import expm

    wn = 2.0 * np.pi * natural_hz

    def distort(rec: Recording, rng: np.random.Generator) -> Recording:
        a = np.array([[0.0, 1.0], [-wn * wn, -2.0 * damping * wn]])
        b = np.array([0.0, wn * wn])
        out = np.empty_like(rec.wheel_rpm)
        x = np.zeros((2, 4))
        x[0] = rec.wheel_rpm[0]
        out[0] = x[0]
        for i in range(1, len(rec)):
            h = rec.t_s[i] - rec.t_s[i - 1]
            # exact ZOH: augmented matrix exponential [[a, b], [0, 0]]
            m = np.zeros((3, 3))
            m[:2, :2] = a
            m[:2, 2] = b
            e = expm(m * h)
            x = e[:2, :2] @ x + np.outer(e[:2, 2], rec.wheel_rpm[i - 1])
            out[i] = x[0]
        return rec.with_values(wheel_rpm=out)

    return distort


def add_roller_ripple(amplitude: float = 0.08, per_turn: float = 8.0
                      ) -> Callable[[Recording, np.random.Generator], Recording]:
    """An effect outside the library: the rollers' periodic speed ripple.

    A Mecanum wheel rolls on ``per_turn`` rollers per turn; as each roller takes over, the
    effective radius and so the measured speed ripple by ``amplitude`` (relative). The measured
    speed of wheel i is ``w_i (1 + amplitude sin(per_turn * angle_i))`` with ``angle_i`` the
    wheel's angle integrated from its speed. No effect of the library is periodic in the wheel
    angle, so none explains it.
    """

    def distort(rec: Recording, rng: np.random.Generator) -> Recording:
        w = rec.wheel_rpm
        dt = np.diff(rec.t_s, prepend=rec.t_s[0])[:, None]
        angle = 2.0 * np.pi * np.cumsum(w / 60.0 * dt, axis=0) + rng.uniform(0, 2 * np.pi, 4)
        return rec.with_values(wheel_rpm=w * (1.0 + amplitude * np.sin(per_turn * angle)))

    return distort
