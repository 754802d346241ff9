"""Command profiles: steps, ramps, holds, their sequences, TOML files, the paper's experiments.

A profile is a sequence of segments, each lasting ``duration_s``:

* ``step``: jump to the given commands at the segment's start and hold them;
* ``ramp``: go linearly from the commands in force to the given ones over the segment;
* ``hold``: keep the commands in force.

Commands not named in a segment keep their value. Profile files (TOML)::

    [profile]
    name = "my-steps"
    initial = { n_rpm = 0.0, omega_dps = 0.0, theta_deg = 90.0 }   # optional

    [[segments]]
    kind = "hold"
    duration_s = 0.5

    [[segments]]
    kind = "ramp"
    duration_s = 26.0          # or rate_rpm_per_s = 5.0 (for n)
    n_rpm = 130.0
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import ConfigError, UsageError
from .io.toml_config import TableReader, load_toml

#: The most samples a profile is sampled into (an hour at 10 kHz is 3.6e7) [-].
MAX_SAMPLES = 1e8

_KINDS = ("step", "ramp", "hold")
_FIELDS = ("n_rpm", "omega_dps", "theta_deg")


@dataclass(frozen=True)
class Segment:
    """One piece of a profile; ``None`` commands keep the value in force.

    Attributes
    ----------
    kind : str
        ``"step"``, ``"ramp"`` or ``"hold"``.
    duration_s : float
        Length of the segment [s].
    n_rpm, omega_dps, theta_deg : float or None
        Target commands [rpm], [deg/s], [deg].
    """

    kind: str
    duration_s: float
    n_rpm: float | None = None
    omega_dps: float | None = None
    theta_deg: float | None = None

    def target(self, current: np.ndarray) -> np.ndarray:
        """The commands at the end of the segment, given those in force at its start."""
        if self.kind == "hold":
            return current.copy()
        return np.array([c if v is None else float(v)
                         for c, v in zip(current, (self.n_rpm, self.omega_dps, self.theta_deg),
                                         strict=True)])


@dataclass(frozen=True)
class CommandProfile:
    """A named sequence of segments starting from ``initial`` commands.

    Attributes
    ----------
    name : str
        Name shown in recordings' metadata.
    segments : tuple of Segment
    initial : tuple of 3 float
        ``(n [rpm], omega [deg/s], theta [deg])`` before the first segment.
    """

    name: str
    segments: tuple[Segment, ...]
    initial: tuple[float, float, float] = (0.0, 0.0, 90.0)
    description: str = field(default="", compare=False)

    @property
    def duration_s(self) -> float:
        """Total length [s]."""
        return float(sum(s.duration_s for s in self.segments))

    def command_at(self, t_s) -> np.ndarray:
        """Commands in force at times ``t_s`` [s]; shape ``(len(t_s), 3)``.

        After the last segment the final commands stay in force.
        """
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        out = np.empty((t.size, 3))
        out[:] = self.initial
        current = np.array(self.initial, dtype=float)
        start = 0.0
        for seg in self.segments:
            end = start + seg.duration_s
            target = seg.target(current)
            inside = (t >= start) & (t < end) if seg is not self.segments[-1] else (t >= start)
            if seg.kind == "ramp":
                frac = np.clip((t[inside] - start) / seg.duration_s, 0.0, 1.0)[:, None]
                out[inside] = current + frac * (target - current)
            else:
                out[inside] = target
            current = target
            start = end
        return out

    def sample(self, rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
        """Sample times and commands at ``rate_hz``, from 0 to the profile's end inclusive."""
        if not (rate_hz > 0 and math.isfinite(rate_hz)):
            raise ConfigError(f"sample rate must be a finite number > 0 Hz, got {rate_hz}")
        samples = self.duration_s * rate_hz
        if not samples <= MAX_SAMPLES:
            raise ConfigError(f"{self.name}: {self.duration_s:g} s at {rate_hz:g} Hz would be "
                              f"{samples:.3g} samples (at most {MAX_SAMPLES:.0e}): lower the rate")
        n = int(np.floor(samples + 1e-9))
        t = np.arange(n + 1) / float(rate_hz)
        return t, self.command_at(t)


def step(n_rpm: float, *, duration_s: float = 3.0, rest_s: float = 0.5, stop_s: float = 1.5,
         theta_deg: float = 90.0, omega_dps: float = 0.0, name: str | None = None
         ) -> CommandProfile:
    """Rest, a step of the commands held for ``duration_s``, then a step back to rest."""
    segs = [Segment("hold", rest_s)] if rest_s > 0 else []
    segs.append(Segment("step", duration_s, n_rpm, omega_dps, theta_deg))
    if stop_s > 0:
        segs.append(Segment("step", stop_s, 0.0, 0.0))
    return CommandProfile(name or f"step-{n_rpm:g}rpm", tuple(segs), (0.0, 0.0, theta_deg))


def ramp(top_rpm: float, rate_rpm_per_s: float, *, hold_s: float = 2.0, rest_s: float = 0.5,
         stop_s: float = 1.5, theta_deg: float = 90.0, name: str | None = None
         ) -> CommandProfile:
    """Rest, a ramp of ``n`` at ``rate_rpm_per_s`` up to ``top_rpm``, a hold, a stop."""
    segs = [Segment("hold", rest_s)] if rest_s > 0 else []
    segs.append(Segment("ramp", top_rpm / rate_rpm_per_s, n_rpm=top_rpm, theta_deg=theta_deg))
    segs.append(Segment("hold", hold_s))
    if stop_s > 0:
        segs.append(Segment("step", stop_s, 0.0, 0.0))
    return CommandProfile(name or f"ramp-{rate_rpm_per_s:g}rpm-per-s", tuple(segs),
                          (0.0, 0.0, theta_deg))


def _paper() -> dict[str, CommandProfile]:
    exps = {f"paper-step-{n}": step(n, name=f"paper-step-{n}") for n in (30, 60, 90, 100, 120)}
    exps["paper-ramp"] = ramp(130.0, 5.0, name="paper-ramp")
    exps["paper-turn"] = step(0.0, omega_dps=60.0, name="paper-turn")
    return exps


#: The paper's experiments by name: steps of n = 30/60/90/100/120 rpm straight ahead, the
#: 5 rpm/s ramp to the 130 rpm limit, and the 60 deg/s turn on the spot.
PAPER_EXPERIMENTS: dict[str, CommandProfile] = _paper()


def load_profile(path: str | Path) -> CommandProfile:
    """Read a profile TOML file (layout in the module docstring)."""
    p = Path(path)
    doc = TableReader(load_toml(p), str(p))
    doc.reject_unknown({"profile", "segments"})
    head = doc.sub("profile", required=False)
    name = p.stem
    initial = (0.0, 0.0, 90.0)
    description = ""
    if head is not None:
        head.reject_unknown({"name", "description", "initial"})
        name = head.string("name", p.stem)
        description = head.string("description", "")
        init = head.sub("initial", required=False)
        if init is not None:
            init.reject_unknown(set(_FIELDS))
            initial = (init.number("n_rpm", 0.0), init.number("omega_dps", 0.0),
                       init.number("theta_deg", 90.0))
    raw = doc.table.get("segments")
    if not isinstance(raw, list) or not raw:
        raise ConfigError(f"{p}: needs at least one [[segments]] entry")
    segments = []
    current = np.array(initial)
    for i, table in enumerate(raw):
        seg = TableReader(table, str(p), f"segments[{i}]")
        seg.reject_unknown({"kind", "duration_s", "rate_rpm_per_s", *_FIELDS})
        kind = seg.string("kind")
        if kind not in _KINDS:
            raise seg.fail("kind", f"must be one of {', '.join(_KINDS)}, got {kind!r}")
        values = {f: (seg.number(f) if f in seg.table else None) for f in _FIELDS}
        if kind == "hold" and any(v is not None for v in values.values()):
            raise seg.fail("kind", "'hold' keeps the commands in force; give no targets")
        if "rate_rpm_per_s" in seg.table:
            if kind != "ramp" or values["n_rpm"] is None or "duration_s" in seg.table:
                raise seg.fail("rate_rpm_per_s", "goes with a ramp of n_rpm instead of duration_s")
            rate = seg.number("rate_rpm_per_s", minimum=0, strict_minimum=True)
            duration = abs(values["n_rpm"] - current[0]) / rate
            if duration <= 0:
                raise seg.fail("rate_rpm_per_s", "ramp has nothing to do: n_rpm is in force")
        else:
            duration = seg.number("duration_s", minimum=0, strict_minimum=True)
        segment = Segment(kind, duration, **values)
        current = segment.target(current)
        segments.append(segment)
    return CommandProfile(name, tuple(segments), initial, description)


def resolve_profile(name_or_path: str | Path) -> CommandProfile:
    """A built-in profile by name (see :data:`PAPER_EXPERIMENTS`) or a profile TOML file."""
    key = str(name_or_path)
    if key in PAPER_EXPERIMENTS:
        return PAPER_EXPERIMENTS[key]
    p = Path(key)
    if p.suffix.lower() == ".toml" or p.exists():
        return load_profile(p)
    raise UsageError(
        f"unknown profile '{key}': not a file, and not one of {', '.join(PAPER_EXPERIMENTS)}")
