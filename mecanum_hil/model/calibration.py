"""Model coefficients and physical effects: the calibration file (``calibration/*.toml``).

A calibration holds the motor coefficients A, B, C of the paper's wheel model::

    W(s) / U(s) = (A s + C) / (s^2 + (A + B) s + C)

(a PI controller ``Kp + Ki / s`` around a first-order motor ``K / (s + B)``: ``A = K Kp``,
``C = K Ki``), optionally the physical effects that ``diagnose`` added, and where the numbers came
from. The same file format is written by ``fit`` and ``diagnose`` and read by every command's
``--calibration``.

File layout::

    [motor]
    A = 14.7          # [1/s]
    B = 16.1          # [1/s]
    C = 303.0         # [1/s^2]

    [ci95]            # optional, written by fit and diagnose: 95 % intervals
    A = [lo, hi]
    ...
    unidentifiable = ["dead_time_s"]   # fitted, but the data cannot bound them: no interval

    [fit]             # optional, free-form metrics and provenance (rmse_rpm, fit_percent, ...)

    [effects.dead_time]
    dead_time_s = 0.03
    [effects.saturation]
    top_speed_rpm = 130.0
    [effects.rate_limit]
    rate_limit_rpm_per_s = 200.0
    [effects.deadband]
    deadband_rpm = 5.0
    [effects.wheel_gain]
    gains = [1.0, 0.8, 1.0, 1.0]
    [effects.slip]
    efficiency = [0.95, 0.8, 0.9]
    [effects.controller_period]
    controller_period_s = 0.01
    [effects.drive_lag]
    drive_lag_s = 0.02
    [effects.breakaway]
    breakaway_rpm_per_s = 3000.0
    [effects.braking_limit]
    braking_limit_rpm_per_s = 2000.0

or, in place of ``braking_limit`` and ``fast_decay`` (not in one model with either), a Coulomb
friction on the turning wheel::

    [effects.friction]
    friction_rpm_per_s = 400.0

or, in place of ``deadband`` and ``braking_limit``, a firmware that switches its drive off for
small targets::

    [effects.drive_deadband]
    drive_deadband_rpm = 25.0

or, in place of ``saturation`` (the two are not in one model), a clamped output that keeps
integrating::

    [effects.windup]
    windup_top_speed_rpm = 400.0

or, in place of ``braking_limit`` (the two are not in one model), a fast-decay drive::

    [effects.fast_decay]
    coast_decel_rpm_per_s = 2900.0
    no_load_rpm = 700.0              # optional (absent: no droop)
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from ..errors import ConfigError
from ..io.resources import DEFAULT_CALIBRATION, resolve
from ..io.toml_config import TableReader, load_toml, toml_value, write_toml


@dataclass(frozen=True)
class Effects:
    """Physical effects beyond the paper's linear model; defaults mean "absent".

    The signal path of one wheel, in this order: wheel target from the inverse kinematics ->
    ``deadband`` (targets with ``|u| < deadband_rpm`` become 0) -> ``wheel_gain`` (times
    ``gains[i]``) -> ``dead_time`` (delayed by ``dead_time_s``) -> ``rate_limit`` (the drive's
    set-point ramp, at most ``rate_limit_rpm_per_s``) -> PI + motor, whose drive output is limited
    by ``saturation`` to ``B * top_speed_rpm`` so the wheel accelerates ever more slowly towards
    ``top_speed_rpm`` (the integrator is frozen while the limit holds it back: anti-windup) ->
    wheel speed. The drive's own dynamics: with ``controller_period`` the PI output is computed
    every ``controller_period_s`` seconds from the sampled speed and held in between (the
    integral summed per period); with ``drive_lag`` the drive output reaches the motor through
    a first-order lag of ``drive_lag_s`` (winding inductance, an output filter); with
    ``breakaway`` a wheel at rest stays at rest until the drive output exceeds
    ``breakaway_rpm_per_s`` (static friction; the integrator keeps winding up meanwhile), and a
    wheel that comes to rest while the drive is below it sticks; with ``braking_limit`` the
    drive slows a turning wheel by at most ``braking_limit_rpm_per_s`` (where the loop asks for
    a steeper deceleration, ``c - B y`` beyond it towards rest, the wheel slows at exactly that
    rate: a drive that coasts instead of braking, as fast-decay (coasting) PWM or a bridge
    without active braking does; acceleration is not limited); with ``fast_decay`` the drive
    is a fast-decay (coasting) PWM bridge: the loop's output ``c`` is the duty's push ``d``
    less a Coulomb friction ``coast_decel_rpm_per_s`` (``u0``); the push acts only in the
    wheel's direction of motion (a duty that would oppose it is off: the wheel coasts, slowed
    by ``u0 + B |y|``) and falls with speed as the back-EMF rises, to nothing at
    ``no_load_rpm`` (``Y0``): ``s y' = max(s c + u0, 0) (1 - |y| / Y0) - u0 - B |y|``, ``s``
    the sign of the motion. ``Y0`` infinite is a braking limit of ``u0 + B |y|``; the two
    effects are not used together. ``windup`` limits the drive output as ``saturation`` does,
    to ``B * windup_top_speed_rpm``, but the integrator keeps integrating the error while the
    output is clamped (a firmware PI that clamps its duty without anti-windup): after a large
    step the wheel overshoots until the integral has unwound. It is not used together with
    ``saturation``. ``friction`` is a Coulomb friction: a turning wheel is slowed by
    ``friction_rpm_per_s`` against its motion (``y' = c - B y - F sign(y)``), and a wheel at
    rest moves only once the drive output exceeds it (or ``breakaway_rpm_per_s``, the larger).
    A proportional-only loop then settles below its target by an offset that does not scale
    with the target, and a PI loop's integral winds up to overcome it. It is not used together
    with ``braking_limit`` or ``fast_decay`` (whose coasting friction it would double).
    ``drive_deadband`` switches the drive off while a wheel's target is below
    ``drive_deadband_rpm`` (a firmware's ``if |target| < d: duty = 0``): the output is 0, the
    integrator is cleared, and the wheel coasts, slowed by its pole and any friction
    (``y' = -B y - F sign(y)``, ``F`` the ``friction`` or a fast-decay drive's
    ``coast_decel_rpm_per_s``). ``deadband`` instead hands the loop a target of 0, which it
    brakes to. It is not used together with ``deadband`` or ``braking_limit``.
    ``slip`` scales the body
    twist ``(vx, vy, wz)`` by ``efficiency`` before the pose is integrated; it does not change
    wheel speeds.

    Attributes
    ----------
    dead_time_s : float
        Transport delay of the command [s].
    top_speed_rpm : float
        Wheel speed the limited drive output can hold at most [rpm]; ``inf`` when absent.
    rate_limit_rpm_per_s : float
        Largest rate of change of the drive's set-point [rpm/s]; ``inf`` when absent.
    deadband_rpm : float
        Wheel targets below this magnitude are not acted on [rpm].
    gains : tuple of 4 float
        Per-wheel gain on the target [-].
    efficiency : tuple of 3 float
        Body-velocity efficiency for ``vx``, ``vy``, ``wz`` [-].
    controller_period_s : float
        Period at which the controller computes and holds its output [s]; 0 when absent
        (continuous).
    drive_lag_s : float
        Time constant of the drive's second lag [s]; 0 when absent.
    breakaway_rpm_per_s : float
        Drive output (as an acceleration) a wheel at rest needs to start moving [rpm/s]; 0 when
        absent.
    braking_limit_rpm_per_s : float
        Largest deceleration of a turning wheel towards rest the drive can produce [rpm/s];
        ``inf`` when absent.
    coast_decel_rpm_per_s : float
        Fast-decay drive: the Coulomb friction that slows a coasting wheel, and the offset of
        the duty's push from the loop's output [rpm/s]; ``inf`` when absent.
    no_load_rpm : float
        Fast-decay drive: the speed at which the full push falls to nothing (back-EMF) [rpm];
        ``inf`` when absent or without that droop.
    windup_top_speed_rpm : float
        Wheel speed the clamped drive output can hold at most, with the integrator still
        integrating while clamped [rpm]; ``inf`` when absent.
    friction_rpm_per_s : float
        Coulomb friction of a turning wheel, as a deceleration [rpm/s]; 0 when absent.
    drive_deadband_rpm : float
        Wheel targets below this magnitude switch the drive off: the wheel coasts [rpm]; 0 when
        absent.
    """

    dead_time_s: float = 0.0
    top_speed_rpm: float = math.inf
    rate_limit_rpm_per_s: float = math.inf
    deadband_rpm: float = 0.0
    gains: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)
    efficiency: tuple[float, float, float] = (1.0, 1.0, 1.0)
    controller_period_s: float = 0.0
    drive_lag_s: float = 0.0
    breakaway_rpm_per_s: float = 0.0
    braking_limit_rpm_per_s: float = math.inf
    coast_decel_rpm_per_s: float = math.inf
    no_load_rpm: float = math.inf
    windup_top_speed_rpm: float = math.inf
    friction_rpm_per_s: float = 0.0
    drive_deadband_rpm: float = 0.0

    def __post_init__(self) -> None:
        # 0 would hold a turning wheel at its speed for ever, a negative limit or NaN is no limit
        if not self.braking_limit_rpm_per_s > 0:
            raise ConfigError("braking_limit_rpm_per_s must be > 0 (inf when absent), got "
                              f"{self.braking_limit_rpm_per_s!r}")
        if not self.coast_decel_rpm_per_s >= 0 or not self.no_load_rpm > 0:
            raise ConfigError("fast_decay needs coast_decel_rpm_per_s >= 0 and no_load_rpm > 0 "
                              f"(inf when absent), got {self.coast_decel_rpm_per_s!r} and "
                              f"{self.no_load_rpm!r}")
        if math.isinf(self.coast_decel_rpm_per_s) and math.isfinite(self.no_load_rpm):
            raise ConfigError("fast_decay's no_load_rpm needs a finite coast_decel_rpm_per_s")
        if self.fast_decay and math.isfinite(self.braking_limit_rpm_per_s):
            raise ConfigError("fast_decay and braking_limit are not used together: a fast-decay "
                              "drive already coasts (its braking limit is coast_decel_rpm_per_s "
                              "+ B |y|)")
        if not self.windup_top_speed_rpm > 0:
            raise ConfigError("windup_top_speed_rpm must be > 0 (inf when absent), got "
                              f"{self.windup_top_speed_rpm!r}")
        if self.windup and math.isfinite(self.top_speed_rpm):
            raise ConfigError("saturation and windup are not used together: both limit the "
                              "drive output, with and without anti-windup")
        if not 0.0 <= self.friction_rpm_per_s < math.inf:
            raise ConfigError("friction_rpm_per_s must be finite and >= 0 (0 when absent), got "
                              f"{self.friction_rpm_per_s!r}")
        if self.friction_rpm_per_s > 0 and (self.fast_decay
                                            or math.isfinite(self.braking_limit_rpm_per_s)):
            raise ConfigError("friction is not used together with braking_limit or fast_decay: "
                              "their coasting wheel is already slowed by a friction")
        if not 0.0 <= self.drive_deadband_rpm < math.inf:
            raise ConfigError("drive_deadband_rpm must be finite and >= 0 (0 when absent), got "
                              f"{self.drive_deadband_rpm!r}")
        if self.drive_deadband_rpm > 0 and (self.deadband_rpm > 0
                                            or math.isfinite(self.braking_limit_rpm_per_s)):
            raise ConfigError("drive_deadband is not used together with deadband or "
                              "braking_limit: small targets are either braked to or coasted "
                              "from, and a coasting wheel is not braked")

    def active(self) -> dict[str, dict[str, Any]]:
        """The effects that are present, by name, with their parameters."""
        out: dict[str, dict[str, Any]] = {}
        for name, spec in EFFECTS.items():
            params = {p: getattr(self, p) for p in spec.parameters}
            if any(params[p] != spec.absent[p] for p in spec.parameters):
                # an infinite parameter of an effect that is present (a fast-decay drive
                # without droop) is left out, as the files and JSON leave it
                out[name] = {p: (list(v) if isinstance(v, tuple) else v) for p, v in params.items()
                             if not (isinstance(v, float) and math.isinf(v))}
        return out

    @property
    def nonlinear(self) -> bool:
        """Whether an effect needs the sub-stepped (not closed-form) simulation."""
        return (math.isfinite(self.top_speed_rpm) or math.isfinite(self.rate_limit_rpm_per_s)
                or self.windup or self.drive_dynamics)

    @property
    def windup(self) -> bool:
        """Whether the drive output is clamped without anti-windup."""
        return math.isfinite(self.windup_top_speed_rpm)

    @property
    def output_limit_rpm(self) -> float:
        """The top speed the limited drive output holds, with or without anti-windup [rpm];
        ``inf`` without either."""
        return min(self.top_speed_rpm, self.windup_top_speed_rpm)

    @property
    def fast_decay(self) -> bool:
        """Whether the drive is a fast-decay (coasting) PWM bridge."""
        return math.isfinite(self.coast_decel_rpm_per_s)

    @property
    def drive_dynamics(self) -> bool:
        """Whether an effect of the drive's own dynamics (period, lag, breakaway, braking limit,
        fast decay, friction, drive deadband) is present."""
        return (self.controller_period_s > 0 or self.drive_lag_s > 0
                or self.breakaway_rpm_per_s > 0 or math.isfinite(self.braking_limit_rpm_per_s)
                or self.fast_decay or self.friction_rpm_per_s > 0
                or self.drive_deadband_rpm > 0)

    def without(self, name: str) -> Effects:
        """A copy with effect ``name`` removed."""
        return replace(self, **EFFECTS[name].absent)


@dataclass(frozen=True)
class EffectSpec:
    """Name, parameters and "absent" values of one effect of the library."""

    name: str
    parameters: tuple[str, ...]
    absent: dict[str, Any]
    description: str


EFFECTS: dict[str, EffectSpec] = {
    "dead_time": EffectSpec(
        "dead_time", ("dead_time_s",), {"dead_time_s": 0.0},
        "transport delay between command and drive [s]"),
    "saturation": EffectSpec(
        "saturation", ("top_speed_rpm",), {"top_speed_rpm": math.inf},
        "drive output limit: acceleration falls off towards a top wheel speed [rpm]"),
    "rate_limit": EffectSpec(
        "rate_limit", ("rate_limit_rpm_per_s",), {"rate_limit_rpm_per_s": math.inf},
        "the drive's set-point ramp [rpm/s]"),
    "deadband": EffectSpec(
        "deadband", ("deadband_rpm",), {"deadband_rpm": 0.0},
        "no motion below a wheel target [rpm]"),
    "wheel_gain": EffectSpec(
        "wheel_gain", ("gains",), {"gains": (1.0, 1.0, 1.0, 1.0)},
        "per-wheel scale of the target [-]"),
    "slip": EffectSpec(
        "slip", ("efficiency",), {"efficiency": (1.0, 1.0, 1.0)},
        "body-velocity efficiency for vx, vy, wz (needs pose data) [-]"),
    "controller_period": EffectSpec(
        "controller_period", ("controller_period_s",), {"controller_period_s": 0.0},
        "the controller computes its output every period and holds it [s]"),
    "drive_lag": EffectSpec(
        "drive_lag", ("drive_lag_s",), {"drive_lag_s": 0.0},
        "a second time constant in the drive (inductance, filter) that makes the loop ring [s]"),
    "breakaway": EffectSpec(
        "breakaway", ("breakaway_rpm_per_s",), {"breakaway_rpm_per_s": 0.0},
        "static friction: a wheel at rest moves only once the drive exceeds this [rpm/s]"),
    "braking_limit": EffectSpec(
        "braking_limit", ("braking_limit_rpm_per_s",), {"braking_limit_rpm_per_s": math.inf},
        "the drive slows a turning wheel at most this fast (it coasts, not brakes) [rpm/s]"),
    "fast_decay": EffectSpec(
        "fast_decay", ("coast_decel_rpm_per_s", "no_load_rpm"),
        {"coast_decel_rpm_per_s": math.inf, "no_load_rpm": math.inf},
        "fast-decay PWM: the drive pushes only along the motion, less as the speed nears "
        "no_load_rpm [rpm], and coasts (friction coast_decel_rpm_per_s [rpm/s]) instead of "
        "braking"),
    "windup": EffectSpec(
        "windup", ("windup_top_speed_rpm",), {"windup_top_speed_rpm": math.inf},
        "drive output clamped without anti-windup: the integrator keeps integrating while "
        "clamped, so the wheel overshoots after large steps; the clamp holds a top wheel "
        "speed [rpm]"),
    "friction": EffectSpec(
        "friction", ("friction_rpm_per_s",), {"friction_rpm_per_s": 0.0},
        "Coulomb friction: a turning wheel is slowed by this against its motion, and a wheel "
        "at rest moves once the drive exceeds it [rpm/s]"),
    "drive_deadband": EffectSpec(
        "drive_deadband", ("drive_deadband_rpm",), {"drive_deadband_rpm": 0.0},
        "the drive is off while a wheel target is below this: the wheel coasts [rpm]"),
}

#: Effects that are not in one model together: a fast-decay drive already coasts (its braking
#: limit is ``coast_decel_rpm_per_s + B |y|``; a Coulomb friction would slow its coasting wheel
#: twice), a drive output is limited either with anti-windup (``saturation``) or without
#: (``windup``), and a small target is either braked to (``deadband``) or coasted from
#: (``drive_deadband``, which no braking limit slows).
EXCLUDES: dict[str, tuple[str, ...]] = {
    "fast_decay": ("braking_limit", "friction"),
    "braking_limit": ("fast_decay", "friction", "drive_deadband"),
    "saturation": ("windup",),
    "windup": ("saturation",),
    "friction": ("braking_limit", "fast_decay"),
    "deadband": ("drive_deadband",),
    "drive_deadband": ("deadband", "braking_limit"),
}


@dataclass(frozen=True)
class Calibration:
    """Coefficients of the wheel model, effects, and provenance.

    Attributes
    ----------
    A : float
        Numerator coefficient of s, ``K Kp`` [1/s].
    B : float
        Motor pole [1/s].
    C : float
        ``K Ki`` [1/s^2].
    effects : Effects
        Physical effects beyond the linear model.
    ci95 : Mapping[str, tuple[float, float] or None]
        95 % confidence intervals of fitted parameters, by bare TOML key (``A``,
        ``dead_time_s``, ``gains_1``); ``None`` for a parameter that was fitted but whose
        interval the data cannot bound (unidentifiable).
    info : Mapping[str, Any]
        Fit metrics and provenance (``[fit]`` table of the file).
    source : str
        File the calibration came from.
    """

    A: float = 14.7
    B: float = 16.1
    C: float = 303.0
    effects: Effects = field(default_factory=Effects)
    ci95: Mapping[str, tuple[float, float] | None] = field(default_factory=dict)
    info: Mapping[str, Any] = field(default_factory=dict)
    source: str = "<defaults>"

    def __post_init__(self) -> None:
        # a file's coefficients are checked as it is read (load_calibration, whose errors
        # name the file and key); one that fails here was made in memory, and its values are
        # not the file's
        check_model_coefficients(self.A, self.B, self.C, "a calibration made in memory")

    @property
    def coefficients(self) -> tuple[float, float, float]:
        """``(A, B, C)``."""
        return (self.A, self.B, self.C)

    def with_coefficients(self, A: float, B: float, C: float,
                          what: str = "the new coefficients") -> Calibration:
        """A copy with new coefficients (intervals and metrics dropped).

        Raises
        ------
        ConfigError
            When they are not a stable, physical model; the message names ``what``.
        """
        A, B, C = float(A), float(B), float(C)
        check_model_coefficients(A, B, C, what)
        return replace(self, A=A, B=B, C=C, ci95={}, info={})


def exchange_drive_lag(calibration: Calibration,
                       what: str = "the drive_lag exchange of the model") -> Calibration | None:
    """The calibration with the drive lag and the motor's time constant exchanged.

    With a drive lag ``tau`` the motor sees ``a / ((s + a)(s + B)) c`` of the controller output
    ``c`` (``a = 1 / tau``): symmetric in ``a`` and ``B`` up to the factor ``a / B``, which the
    PI gains absorb. So ``drive_lag_s = 1 / B``, ``B = 1 / tau``, ``A`` and ``C`` times
    ``1 / (tau B)`` give exactly the same wheel speeds for every command, with every effect
    that acts on the target or on the controller output (dead time, deadband, gains, rate limit,
    saturation, controller period). Wheel speeds alone cannot tell the two apart; breakaway,
    which acts on the lagged drive, and a braking limit or a fast-decay drive, which act on
    the motor's acceleration, can.

    Parameters
    ----------
    calibration : Calibration
    what : str
        Names the twin in an error (e.g. "the drive_lag exchange of the fitted model").

    Returns
    -------
    Calibration or None
        The twin (intervals and metrics dropped); ``None`` without a drive lag, with ``B <= 0``
        or with breakaway, a braking limit or a fast-decay drive (no exact twin).

    Raises
    ------
    ConfigError
        When the twin is degenerate, no calibration a file can hold: its drive lag ``1 / B``
        beyond :data:`MAX_DRIVE_LAG_S` (``B`` near zero), or its coefficients not finite,
        beyond :data:`MAX_COEFFICIENT` or unstable. The message starts with ``what``.
    """
    fx = calibration.effects
    tau, B = fx.drive_lag_s, calibration.B
    if not (tau > 0 and B > 0) or fx.breakaway_rpm_per_s > 0 or \
            math.isfinite(fx.braking_limit_rpm_per_s) or fx.fast_decay:
        return None
    lag = 1.0 / B
    if not lag <= MAX_DRIVE_LAG_S:
        raise ConfigError(f"{what}: its drive_lag_s = 1 / B = {lag:g} s exceeds "
                          f"{MAX_DRIVE_LAG_S:g} s (B = {B:g} 1/s is near zero)")
    # a float product overflows to inf (then refused below), a quotient by 0 would raise
    prod = tau * B
    k = 1.0 / prod if prod > 0 else math.inf
    twin = calibration.with_coefficients(calibration.A * k, 1.0 / tau, calibration.C * k, what)
    return replace(twin, effects=replace(fx, drive_lag_s=lag))


#: The largest A, B [1/s] and C [1/s^2] a model may have: a time constant of a picosecond, far
#: beyond any drive, but where the discretised model's products stay finite (C = 1e300
#: overflowed into a simulation of empty values).
MAX_COEFFICIENT = 1e12


#: The longest drive lag a calibration file may hold [s] (and the fit's bound).
MAX_DRIVE_LAG_S = 5.0


def coefficient_problem(A: float, B: float, C: float, *, keys: bool = False) -> str | None:
    """What makes ``A``, ``B``, ``C`` no stable, physical wheel model; None when they are one.

    The characteristic polynomial ``s^2 + (A + B) s + C`` is stable iff ``A + B > 0`` and
    ``C > 0``; ``A = K Kp`` and ``B`` are also non-negative for a real PI drive; none may
    exceed :data:`MAX_COEFFICIENT`. The text names the coefficients (``A must be ...``), or with
    ``keys`` a file's keys (``key 'motor.A' must be ...``).
    """
    def name(k: str) -> str:
        return f"key 'motor.{k}'" if keys else k

    for k, value in (("A", A), ("B", B), ("C", C)):
        if not math.isfinite(value):
            return f"{name(k)} must be finite, got {value!r}"
        if value > MAX_COEFFICIENT:
            return (f"{name(k)} must be at most {MAX_COEFFICIENT:g} (no drive is that fast), "
                    f"got {value:g}")
    if A < 0:
        return f"{name('A')} must be >= 0, got {A:g}"
    if B < 0:
        return f"{name('B')} must be >= 0, got {B:g}"
    if C <= 0:
        return f"{name('C')} must be > 0 (stable model), got {C:g}"
    if A + B <= 0:
        return ("keys 'motor.A' + 'motor.B' must be > 0 (stable model)" if keys
                else "A + B must be > 0 (stable model)")
    return None


def check_coefficients(A: float, B: float, C: float, source: str = "<coefficients>") -> None:
    """Refuse a file's coefficients of an unstable or unphysical wheel model
    (:func:`coefficient_problem`); the error names the file ``source`` and its keys."""
    problem = coefficient_problem(A, B, C, keys=True)
    if problem is not None:
        raise ConfigError(f"{source}: {problem}")


def check_model_coefficients(A: float, B: float, C: float, what: str) -> None:
    """Refuse coefficients made in memory (fitted, exchanged, given to a stepper) of an unstable
    or unphysical wheel model (:func:`coefficient_problem`); the error starts with ``what``,
    the model's name ("the drive_lag exchange of the fitted model"), never a file's."""
    problem = coefficient_problem(A, B, C)
    if problem is not None:
        raise ConfigError(f"{what}: {problem}")


def _read_effects(reader: TableReader | None) -> Effects:
    if reader is None:
        return Effects()
    reader.reject_unknown(set(EFFECTS))
    values: dict[str, Any] = {}
    for name, spec in EFFECTS.items():
        sub = reader.sub(name, required=False)
        if sub is None:
            continue
        sub.reject_unknown(set(spec.parameters))
        if name == "dead_time":
            values["dead_time_s"] = sub.number("dead_time_s", minimum=0.0, maximum=5.0)
        elif name == "saturation":
            values["top_speed_rpm"] = sub.number("top_speed_rpm", minimum=0, strict_minimum=True)
        elif name == "rate_limit":
            values["rate_limit_rpm_per_s"] = sub.number(
                "rate_limit_rpm_per_s", minimum=0, strict_minimum=True)
        elif name == "deadband":
            values["deadband_rpm"] = sub.number("deadband_rpm", minimum=0.0)
        elif name == "wheel_gain":
            values["gains"] = sub.numbers("gains", 4, minimum=0.0)
        elif name == "slip":
            values["efficiency"] = sub.numbers("efficiency", 3, minimum=0.0)
        elif name == "controller_period":
            values["controller_period_s"] = sub.number("controller_period_s", minimum=0.0,
                                                       maximum=1.0)
        elif name == "drive_lag":
            values["drive_lag_s"] = sub.number("drive_lag_s", minimum=0.0,
                                               maximum=MAX_DRIVE_LAG_S)
        elif name == "breakaway":
            values["breakaway_rpm_per_s"] = sub.number("breakaway_rpm_per_s", minimum=0.0)
        elif name == "braking_limit":
            values["braking_limit_rpm_per_s"] = sub.number(
                "braking_limit_rpm_per_s", minimum=0, strict_minimum=True)
        elif name == "fast_decay":
            values["coast_decel_rpm_per_s"] = sub.number("coast_decel_rpm_per_s", minimum=0.0)
            values["no_load_rpm"] = sub.number("no_load_rpm", math.inf, minimum=0,
                                               strict_minimum=True)
        elif name == "windup":
            values["windup_top_speed_rpm"] = sub.number("windup_top_speed_rpm", minimum=0,
                                                        strict_minimum=True)
        elif name == "friction":
            values["friction_rpm_per_s"] = sub.number("friction_rpm_per_s", minimum=0.0)
        elif name == "drive_deadband":
            values["drive_deadband_rpm"] = sub.number("drive_deadband_rpm", minimum=0.0)
    try:
        return Effects(**values)
    except ConfigError as err:  # effects that are not in one model: name the file's tables
        raise ConfigError(f"{reader.source}: [{reader.prefix}]: {err}") from None


def read_effects_table(table: Mapping[str, Any], source: str) -> Effects:
    """Effects from an ``[effects.*]`` table (used by calibration and sim-robot effect files)."""
    return _read_effects(TableReader(table, source, "effects"))


def load_calibration(name_or_path: str | Path = DEFAULT_CALIBRATION) -> Calibration:
    """Read a calibration TOML file (a shipped name such as ``paper`` or a path)."""
    path = resolve("calibration", name_or_path)
    src = str(path)
    doc = TableReader(load_toml(path), src)
    doc.reject_unknown({"motor", "ci95", "fit", "effects", "notes"})
    motor = doc.sub("motor")
    motor.reject_unknown({"A", "B", "C"})
    ci = doc.sub("ci95", required=False)
    ci95 = _read_intervals(ci) if ci is not None else {}
    info = dict(doc.table.get("fit", {}))
    effects = _read_effects(doc.sub("effects", required=False))
    A = motor.number("A")
    B = motor.number("B")
    C = motor.number("C")
    check_coefficients(A, B, C, src)
    return Calibration(A=A, B=B, C=C, effects=effects, ci95=ci95, info=info, source=src)


#: The key of ``[ci95]`` that lists the parameters the data cannot bound.
UNIDENTIFIABLE_KEY = "unidentifiable"


def _read_intervals(ci: TableReader) -> dict[str, tuple[float, float] | None]:
    """``[ci95]``: ``key = [lo, hi]`` per parameter, and ``unidentifiable = [...]`` naming the
    parameters without one (read as ``None``)."""
    out: dict[str, tuple[float, float] | None] = {}
    for key in ci.table:
        if key != UNIDENTIFIABLE_KEY:
            lo, hi = ci.numbers(key, 2)
            out[key] = (lo, hi)
    names = ci.table.get(UNIDENTIFIABLE_KEY, [])
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise ci.fail(UNIDENTIFIABLE_KEY, f"must be a list of parameter names, got {names!r}")
    for name in names:
        if name in out:
            raise ci.fail(UNIDENTIFIABLE_KEY, f"names {name!r}, which has an interval "
                          f"(or is named twice)")
        out[name] = None
    return out


def calibration_to_toml(cal: Calibration, header: str = "") -> str:
    """The text of a calibration file for ``cal`` (see the module docstring for the layout)."""
    lines = [f"# {line}" if line else "#" for line in header.splitlines()]
    if lines:
        lines.append("")
    lines += [
        "[motor]",
        f"A = {toml_value(float(cal.A))}   # [1/s]",
        f"B = {toml_value(float(cal.B))}   # [1/s]",
        f"C = {toml_value(float(cal.C))}   # [1/s^2]",
    ]
    if cal.ci95:
        lines += ["", "[ci95]"]
        lines += [f"{k} = {toml_value(list(v))}" for k, v in cal.ci95.items() if v is not None]
        loose = [k for k, v in cal.ci95.items() if v is None]
        if loose:
            lines.append(f"{UNIDENTIFIABLE_KEY} = {toml_value(loose)}   # the data cannot "
                         "bound these")
    if cal.info:
        lines += ["", "[fit]"]
        lines += [f"{k} = {toml_value(v)}" for k, v in cal.info.items()]
    for name, params in cal.effects.active().items():
        lines += ["", f"[effects.{name}]"]
        lines += [f"{k} = {toml_value(v)}" for k, v in params.items()]
    return "\n".join(lines) + "\n"


def save_calibration(cal: Calibration, path: str | Path, header: str = "") -> Path:
    """Write ``cal`` as a calibration file; the result loads back equal."""
    return write_toml(path, calibration_to_toml(cal, header), "calibration")

