"""Domain randomisation: coefficients drawn within a calibration's fitted confidence intervals.

``fit`` writes 95 % intervals to the calibration's ``[ci95]`` table. At every reset a randomised
environment draws each of ``A``, ``B``, ``C`` independently and uniformly from its interval
(clipped to the physical region ``A >= 0``, ``B >= 0``, ``C > 0``; ``B > 0`` when the
``saturation`` effect is present), so a controller trained on it must cope with every model the
data cannot rule out. A coefficient without an interval keeps its fitted value. A coefficient
the data cannot bound (``unidentifiable`` in ``[ci95]``) is refused: no interval can be drawn
from, and its fitted value is no better than any other. A calibration with
no interval for any of them (the shipped ``paper.toml``: the paper gives none) is refused with a
:class:`~mecanum_hil.errors.ConfigError` rather than randomised by an invented spread; pass
``coefficient_ranges`` to give intervals yourself. Intervals ``[ci95]`` holds for the effects'
parameters (``dead_time_s``, ``gains_0`` ...) are not drawn from: the effects stay at their
fitted values (listed in :attr:`CoefficientRanges.ignored`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from ..model import Calibration

_NAMES = ("A", "B", "C")


@dataclass(frozen=True)
class CoefficientRanges:
    """Intervals the coefficients are drawn from, uniformly and independently.

    Attributes
    ----------
    low, high : tuple of 3 float
        Bounds for ``(A [1/s], B [1/s], C [1/s^2])``; ``low == high`` holds one fixed.
    ignored : tuple of str
        ``[ci95]`` keys of the calibration that are not randomised (effect parameters).
    """

    low: tuple[float, float, float]
    high: tuple[float, float, float]
    ignored: tuple[str, ...] = ()

    @classmethod
    def from_calibration(cls, calibration: Calibration,
                         overrides: Mapping[str, tuple[float, float]] | None = None
                         ) -> CoefficientRanges:
        """The ranges from ``calibration.ci95``, with ``overrides`` taking precedence.

        Raises
        ------
        ConfigError
            If no coefficient has an interval, one is unidentifiable (and not overridden), or
            an interval is empty after clipping to the physical region.
        """
        given = dict(calibration.ci95)
        given.update(overrides or {})
        loose = [name for name in _NAMES if name in given and given[name] is None]
        if loose:
            raise ConfigError(
                f"{calibration.source}: the data cannot bound {', '.join(loose)} (unidentifiable "
                "in [ci95]): no interval to draw from. Fit on recordings with a transient, or "
                "pass coefficient_ranges={'" + loose[0] + "': (lo, hi), ...}")
        unknown = sorted(set(overrides or {}) - set(_NAMES))
        if unknown:
            raise ConfigError(f"coefficient_ranges: unknown coefficient(s) {', '.join(unknown)} "
                              "(A, B, C can be randomised)")
        if not any(name in given for name in _NAMES):
            raise ConfigError(
                f"{calibration.source}: domain randomisation needs 95 % intervals of A, B or C "
                "([ci95], written by `mecanum-hil fit`); this calibration has none. Fit one, or "
                "pass coefficient_ranges={'A': (lo, hi), ...}")
        saturating = math.isfinite(calibration.effects.output_limit_rpm)
        floors = (0.0, 1e-9 if saturating else 0.0, 1e-9)
        low, high = [], []
        for name, value, floor in zip(_NAMES, calibration.coefficients, floors, strict=True):
            lo, hi = (float(v) for v in given.get(name, (value, value)))
            if not (math.isfinite(lo) and math.isfinite(hi)) or hi < lo:
                raise ConfigError(f"{calibration.source}: interval of {name} [{lo:g}, {hi:g}] is "
                                  "not a finite interval")
            lo = max(lo, floor)
            if hi < lo:
                raise ConfigError(f"{calibration.source}: interval of {name} lies outside the "
                                  f"physical region ({name} >= {floor:g})")
            low.append(lo)
            high.append(hi)
        ignored = tuple(sorted(k for k in calibration.ci95 if k not in _NAMES))
        return cls(tuple(low), tuple(high), ignored)

    def draw(self, rng: np.random.Generator) -> np.ndarray:
        """One coefficient set ``(A, B, C)`` (three uniform variates from ``rng``)."""
        lo = np.asarray(self.low)
        return lo + rng.random(3) * (np.asarray(self.high) - lo)
