"""The parameters a fit can estimate: their names, bounds, values and reported intervals.

:data:`PARAMETER_NAMES` names every parameter of a :class:`~mecanum_hil.model.Calibration` the
least squares of :mod:`mecanum_hil.identify.fit` can estimate (the coefficients ``A``, ``B``,
``C`` and the effects' parameters, one name per element of a tuple: ``gains[2]``);
:data:`DEFAULT_BOUNDS` their admissible ranges. :func:`parameter_value` reads a named value,
:func:`with_parameters` substitutes named values, and :func:`bounded_interval` /
:func:`unbounded` say how a parameter's 95 % interval is reported.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from ..errors import FitError
from ..model.calibration import Calibration, Effects, check_model_coefficients

#: Every parameter :func:`~mecanum_hil.identify.fit.fit_parameters` can estimate: the
#: coefficients, then the effects'.
PARAMETER_NAMES: tuple[str, ...] = (
    "A", "B", "C", "dead_time_s", "top_speed_rpm", "rate_limit_rpm_per_s", "deadband_rpm",
    "gains[0]", "gains[1]", "gains[2]", "gains[3]",
    "efficiency[0]", "efficiency[1]", "efficiency[2]",
    "controller_period_s", "drive_lag_s", "breakaway_rpm_per_s", "braking_limit_rpm_per_s",
    "coast_decel_rpm_per_s", "no_load_rpm", "windup_top_speed_rpm", "friction_rpm_per_s",
    "drive_deadband_rpm",
)

#: An element of a tuple-valued effect: ``gains[2]`` -> (``gains``, ``2``).
INDEXED = re.compile(r"^(gains|efficiency)\[(\d)\]$")
#: The model's coefficients, in their order.
COEFFICIENTS = ("A", "B", "C")
#: The paper's model: no effect present.
NO_EFFECTS = Effects()

#: Default bounds: the model stays stable (A, B >= 0, C > 0) and effects physical.
DEFAULT_BOUNDS: dict[str, tuple[float, float]] = {
    # unbounded above: finite bounds change the solver's scaling (trf) on every fit; a model
    # beyond calibration.MAX_COEFFICIENT is refused when the result is made
    "A": (0.0, math.inf),
    "B": (0.0, math.inf),
    "C": (1e-6, math.inf),
    "dead_time_s": (0.0, 5.0),
    "top_speed_rpm": (1e-6, math.inf),
    "rate_limit_rpm_per_s": (1e-6, math.inf),
    "deadband_rpm": (0.0, math.inf),
    **{f"gains[{i}]": (0.0, math.inf) for i in range(4)},
    **{f"efficiency[{i}]": (0.0, math.inf) for i in range(3)},
    "controller_period_s": (0.0, 1.0),
    "drive_lag_s": (0.0, 5.0),
    "breakaway_rpm_per_s": (0.0, math.inf),
    "braking_limit_rpm_per_s": (1e-6, math.inf),
    "coast_decel_rpm_per_s": (0.0, math.inf),
    "no_load_rpm": (1.0, math.inf),
    "windup_top_speed_rpm": (1e-6, math.inf),
    "friction_rpm_per_s": (0.0, math.inf),
    "drive_deadband_rpm": (0.0, math.inf),
}

#: Typical magnitude [the parameter's unit] below which a finite-difference step stops
#: shrinking with the value; 1 for a parameter not named.
FD_FLOOR = {"dead_time_s": 0.01, "drive_lag_s": 0.01, "controller_period_s": 0.01}

#: The data do not bound a parameter whose 95 % half-width exceeds this many times its
#: magnitude (:func:`bounded_interval`): the interval then reaches far past the parameter's
#: bound, and the data cannot tell the value from that bound (a dead time of 0.5 +- 4672 s).
UNBOUNDED_FACTOR = 10.0


def check_name(name: str) -> None:
    """Refuse a name not in :data:`PARAMETER_NAMES` (:class:`~mecanum_hil.errors.FitError`)."""
    if name not in PARAMETER_NAMES:
        raise FitError(f"unknown parameter {name!r}; choose from {', '.join(PARAMETER_NAMES)}")


def effect_slot(name: str) -> tuple[str, int | None]:
    """The ``Effects`` field of an effect parameter's name and its index in that field's tuple
    (None for a scalar): ``gains[2]`` -> ``("gains", 2)``."""
    check_name(name)
    m = INDEXED.match(name)
    return (m.group(1), int(m.group(2))) if m else (name, None)


def effects_with(effects: Effects, slots: Sequence[tuple[int, str, int | None]],
                 values: Sequence[float]) -> Effects:
    """``effects`` with ``values[i]`` in each slot ``(i, field, index)``
    (:func:`effect_slot`), as :func:`with_parameters` substitutes them."""
    changes: dict[str, Any] = {}
    for i, field_name, index in slots:
        if index is None:
            changes[field_name] = values[i]
        else:
            seq = changes.setdefault(field_name, list(getattr(effects, field_name)))
            seq[index] = values[i]
    return replace(effects, **{n: tuple(v) if isinstance(v, list) else v
                               for n, v in changes.items()}) if changes else effects


def parameter_value(calibration: Calibration, name: str) -> float:
    """The current value of a named parameter (see :data:`PARAMETER_NAMES`)."""
    check_name(name)
    if name in COEFFICIENTS:
        return float(getattr(calibration, name))
    m = INDEXED.match(name)
    if m:
        return float(getattr(calibration.effects, m.group(1))[int(m.group(2))])
    return float(getattr(calibration.effects, name))


def with_parameters(calibration: Calibration, values: Mapping[str, float],
                    what: str | None = None) -> Calibration:
    """Substitute named parameters (coefficients or effect parameters) into a calibration.

    Parameters
    ----------
    calibration : Calibration
        The calibration to start from; parameters not named keep their values.
    values : Mapping[str, float]
        Name (one of :data:`PARAMETER_NAMES`) -> value, in the parameter's unit.
    what : str, optional
        Names the new model in an error (default: "the model with new values of A, B, ...").

    Returns
    -------
    Calibration
        A copy with the values substituted. Its intervals and fit metrics are dropped when any
        value changed, since they described the old values.

    Raises
    ------
    FitError
        For an unknown name.
    ConfigError
        For coefficients of an unstable model; the message starts with ``what``.
    """
    if not values:
        return calibration
    coeffs: dict[str, float] = {}
    effects: dict[str, Any] = {}
    indexed: dict[str, list[float]] = {}
    for name, value in values.items():
        check_name(name)
        v = float(value)
        if name in COEFFICIENTS:
            coeffs[name] = v
            continue
        m = INDEXED.match(name)
        if m:
            field_name = m.group(1)
            seq = indexed.setdefault(field_name, list(getattr(calibration.effects, field_name)))
            seq[int(m.group(2))] = v
        else:
            effects[name] = v
    for field_name, seq in indexed.items():
        effects[field_name] = tuple(seq)
    if coeffs:
        check_model_coefficients(
            *(coeffs.get(n, getattr(calibration, n)) for n in COEFFICIENTS),
            what or f"the model with new values of {', '.join(values)}")
    eff = replace(calibration.effects, **effects) if effects else calibration.effects
    return replace(calibration, **coeffs, effects=eff, ci95={}, info={})


def toml_key(name: str) -> str:
    """A parameter name as a bare TOML key for ``[ci95]`` (``gains[1]`` -> ``gains_1``)."""
    m = INDEXED.match(name)
    return f"{m.group(1)}_{m.group(2)}" if m else name


def calibration_intervals(ci95: Mapping[str, tuple[float, float]]
                          ) -> dict[str, tuple[float, float] | None]:
    """Engine intervals (NaN where unidentifiable) as :attr:`Calibration.ci95` holds them:
    bare TOML keys (:func:`toml_key`), ``None`` for an unidentifiable parameter."""
    return {toml_key(k): (float(v[0]), float(v[1])) if all(map(math.isfinite, v)) else None
            for k, v in ci95.items()}


def bounded_interval(name: str, value: float, lo: float, hi: float
                     ) -> tuple[float, float] | None:
    """A 95 % interval as it is reported: clipped to the parameter's admissible range
    (:data:`DEFAULT_BOUNDS`), or None where the data cannot bound the parameter.

    The data cannot bound it when the interval is not finite (the data do not depend on the
    parameter, the parameters are not jointly identifiable, too few residuals), when its
    half-width ``h`` (the larger distance from ``value`` to an end) is at least the width of a
    finite admissible range (``dead_time_s``: 5 s), or when ``h`` exceeds
    :data:`UNBOUNDED_FACTOR` times the value's magnitude, at least the parameter's typical
    scale (0.01 s for ``dead_time_s``, ``drive_lag_s`` and ``controller_period_s``, 1 in the
    parameter's unit otherwise).

    Parameters
    ----------
    name : str
        One of :data:`PARAMETER_NAMES`.
    value : float
        The fitted value, in the parameter's unit.
    lo, hi : float
        The interval as computed (``value -+ h`` for a Wald interval; a grid's span).
    """
    if unbounded(name, value, lo, hi) is not None:
        return None
    low, high = DEFAULT_BOUNDS[name]
    return (max(lo, low), min(hi, high))


def unbounded(name: str, value: float, lo: float, hi: float) -> str | None:
    """Why the data cannot bound parameter ``name`` with 95 % interval ``[lo, hi]`` around
    ``value`` (the rule of :func:`bounded_interval`); None when they bound it."""
    low, high = DEFAULT_BOUNDS[name]
    if not (math.isfinite(value) and math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
        return "its 95 % interval is not finite"
    half = max(value - lo, hi - value)
    if math.isfinite(high - low) and half >= high - low:
        return (f"its 95 % half-width {half:.4g} is at least its whole admissible range "
                f"{low:g}..{high:g}")
    scale = max(abs(value), FD_FLOOR.get(name, 1.0))
    if half > UNBOUNDED_FACTOR * scale:
        return (f"its 95 % half-width {half:.4g} exceeds {UNBOUNDED_FACTOR:g} times its "
                f"magnitude {scale:.4g}")
    return None


def checked_bounds(free: Sequence[str], bounds: Mapping[str, tuple[float, float]] | None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper bounds of the ``free`` parameters, in their units: ``bounds`` where
    given, else :data:`DEFAULT_BOUNDS`.

    Raises
    ------
    FitError
        For an unknown name, or bounds outside the default range or with lower >= upper.
    """
    given = dict(bounds or {})
    for n in given:
        check_name(n)
    lo = np.array([float(given.get(n, DEFAULT_BOUNDS[n])[0]) for n in free])
    hi = np.array([float(given.get(n, DEFAULT_BOUNDS[n])[1]) for n in free])
    d_lo = np.array([DEFAULT_BOUNDS[n][0] for n in free])
    d_hi = np.array([DEFAULT_BOUNDS[n][1] for n in free])
    if (lo < d_lo).any() or (hi > d_hi).any() or (lo >= hi).any():
        raise FitError("bounds must lie within the stable, physical range "
                       f"{ {n: DEFAULT_BOUNDS[n] for n in free} } and have lower < upper")
    return lo, hi
