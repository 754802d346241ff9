"""Identification campaigns recorded from the simulated controller: the paper's experiments.

A campaign is what a user would record on the robot to fit and diagnose the model: steps of
several sizes (including small ones, where a deadband shows), the paper's 5 rpm/s ramp up to the
130 rpm command limit (past a drive's ceiling), a turn on the spot, a strafe and a diagonal
run. :func:`paper_campaign` records it from the simulated controller (``sim-robot``'s firmware
and robot, in simulated time) whose effects file hides effects from the later analysis, with
its wheel-speed noise, and a camera's noisy pose.

The effects file can also hide effects outside the model's library (``[unmodelled]``: a
resonance between drive and encoder, the rollers' speed ripple), to check that ``diagnose``
says "unexplained" instead of naming the closest wrong effect.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

from ..io.recording import Recording
from ..link.effects_file import SimEffects
from ..model.calibration import Calibration
from ..model.robot import RobotProfile
from ..profiles import CommandProfile, Segment, ramp, step

#: Step sizes of the campaign [rpm]: small ones (a deadband shows), the paper's, past 100 rpm.
CAMPAIGN_STEPS_RPM = (4.0, 8.0, 15.0, 30.0, 60.0, 100.0, 120.0)


#: The shorter campaign of the tests: fewer step sizes, steps held 1.5 s, no reversing step.
SHORT_CAMPAIGN = {"steps_rpm": (4.0, 8.0, 30.0, 100.0, 120.0), "step_hold_s": 1.5,
                  "reverse": False}


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


def paper_campaign(effects: SimEffects | str | Path | None = None,
                   robot: RobotProfile | None = None, *,
                   calibration: Calibration | None = None, command_rate_hz: float = 50.0,
                   telemetry_rate_hz: float = 100.0, link_delay_s: float = 0.00015,
                   pose_noise: tuple[float, float, float] | None = (0.003, 0.003, 0.3),
                   seed: int = 0, profiles: Sequence[CommandProfile] | None = None,
                   retime: bool = True) -> list[Recording]:
    """Record a campaign from the simulated controller, whose effects file hides the truth.

    Each profile is recorded as ``record`` would against ``sim-robot --effects FILE``, in
    simulated time (:func:`~mecanum_hil.link.lockstep.record_lockstep`): commands at
    ``command_rate_hz`` through the wire protocol, the controller's effects, noise and faults,
    telemetry at ``telemetry_rate_hz``. The recordings come back as ``fit`` and ``diagnose``
    read them (:func:`~mecanum_hil.io.timing.read_for_analysis`: telemetry timed by the
    controller's clock).

    Parameters
    ----------
    effects : SimEffects or path, optional
        The simulated controller's effects file (or its content): hidden effects (library
        ones and ``[unmodelled]`` ones), wheel noise and its seed (recording ``i`` uses
        ``seed + i``, as a controller restarted for every recording would draw new noise).
        Default: none, no noise.
    robot : RobotProfile, optional
        Geometry and limits (default: the paper's robot).
    calibration : Calibration, optional
        The simulated truth's coefficients (default: the paper's).
    command_rate_hz, telemetry_rate_hz : float
        Rates [Hz].
    link_delay_s : float
        One-way transit time of the link [s] (default: a pseudo-terminal's); the host sees
        the round trip, plus up to one controller tick, as dead time.
    pose_noise : (float, float, float), optional
        Standard deviation of the camera's X, Y [m] and heading [deg]; ``None`` for no pose.
    seed : int
        Seed of the pose noise.
    profiles : sequence of CommandProfile, optional
        Profiles to run (default :func:`campaign_profiles`).
    retime : bool
        Return the recordings as analysis reads them (default), or exactly as ``record``
        writes them (``False``: host receive times, for writing to files).

    Returns
    -------
    list of Recording
        One per profile; ``metadata["profile"]`` names it, ``metadata["true_effects"]`` and
        ``metadata["true_unmodelled"]`` hold what was hidden.
    """
    from ..io.timing import retime_telemetry
    from ..link.effects_file import load_sim_effects
    from ..link.lockstep import record_lockstep

    fx = effects if isinstance(effects, SimEffects) or effects is None else \
        load_sim_effects(effects)
    fx = fx or SimEffects()
    cal = calibration or Calibration()
    rob = robot or RobotProfile()
    out = []
    for i, prof in enumerate(profiles if profiles is not None else campaign_profiles()):
        t, cmd = prof.sample(command_rate_hz)
        rob.check_commands(cmd, prof.name)
        rec = record_lockstep(
            t, cmd, rob, calibration=cal, sim_effects=replace(fx, seed=fx.seed + i),
            telemetry_rate_hz=telemetry_rate_hz, link_delay_s=link_delay_s,
            pose_noise=pose_noise, pose_seed=seed + i,
            metadata={"profile": prof.name, "command_rate_hz": command_rate_hz,
                      "true_coefficients": {"A": cal.A, "B": cal.B, "C": cal.C},
                      "true_effects": fx.initial_effects(cal.effects).active(),
                      "true_unmodelled": fx.unmodelled})
        out.append(retime_telemetry(rec) if retime else rec)
    return out
