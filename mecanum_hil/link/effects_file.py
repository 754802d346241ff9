"""The simulated controller's effects file (TOML): the truth that differs from the model.

Layout (every table optional)::

    [effects.dead_time]            # the same [effects.<name>] tables as calibration files,
    dead_time_s = 0.04             # replacing the calibration's effect of that name
    [effects.wheel_gain]
    gains = [1.0, 1.0, 1.0, 0.9]
    [effects.breakaway]            # the drive's own dynamics too: controller_period, drive_lag,
    breakaway_rpm_per_s = 1500.0   # breakaway, braking_limit, fast_decay (docs/model.md)

    [unmodelled.resonance]         # effects OUTSIDE the model's library, for checking that
    natural_hz = 3.0               # diagnose reports them as unexplained: a lightly damped
    damping = 0.15                 # mode between drive and encoder (a flexible coupling)
    [unmodelled.roller_ripple]     # the rollers' periodic speed ripple: the measured speed
    amplitude = 0.05               # times (1 + amplitude sin(per_turn * wheel angle))
    per_turn = 8

    [noise]
    wheel_rpm_std = 0.5            # Gaussian measurement noise on reported wheel speeds [rpm]
    seed = 1                       # noise seed (default 0: runs are repeatable)

    [[faults]]                     # time-triggered faults, in controller time [s]
    at_s = 5.0
    [faults.effects.wheel_gain]    # effects switched on (or changed) at at_s
    gains = [1.0, 0.0, 1.0, 1.0]   # wheel 2 stalls

    [[faults]]
    at_s = 8.0
    estop = true                   # the emergency stop is pressed at 8 s

The file is read only by the simulated controller, never by fitting or diagnosis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from ..io.toml_config import TableReader, load_toml, toml_value, write_toml
from ..model.calibration import EFFECTS, EXCLUDES, Effects, read_effects_table


@dataclass(frozen=True)
class Fault:
    """A change of the simulated robot at a controller time.

    Attributes
    ----------
    at_s : float
        Controller time at which the fault appears [s] (the clock restarts at each HELLO).
    effects : Mapping[str, dict]
        Effect name -> parameters switched on at ``at_s`` (replacing that effect).
    estop : bool
        Whether the emergency stop is pressed at ``at_s`` (wheels held at zero from then on).
    """

    at_s: float
    effects: dict[str, dict[str, Any]] = field(default_factory=dict)
    estop: bool = False

    def apply(self, effects: Effects) -> Effects:
        """``effects`` with this fault's effects switched on."""
        return apply_effect_params(effects, self.effects)


@dataclass(frozen=True)
class SimEffects:
    """Everything an effects file sets.

    Attributes
    ----------
    effects : Mapping[str, dict]
        Effects that replace the calibration's from the start, by name.
    wheel_rpm_std : float
        Standard deviation of the Gaussian noise on reported wheel speeds [rpm].
    seed : int
        Seed of the noise generator.
    faults : tuple of Fault
        Time-triggered faults, sorted by ``at_s``.
    source : str
        File the settings came from.
    unmodelled : Mapping[str, dict]
        Effects outside the model's library, by name (:data:`UNMODELLED`), with their
        parameters; applied to the measured wheel speeds before the noise.
    """

    effects: dict[str, dict[str, Any]] = field(default_factory=dict)
    wheel_rpm_std: float = 0.0
    seed: int = 0
    faults: tuple[Fault, ...] = ()
    source: str = "<none>"
    unmodelled: dict[str, dict[str, float]] = field(default_factory=dict)

    def initial_effects(self, base: Effects) -> Effects:
        """The calibration's effects with this file's effects switched on."""
        return apply_effect_params(base, self.effects)


#: Effects outside the model's library the simulated controller can play: name -> parameter ->
#: (lower bound, strict lower bound?, upper bound or None).
UNMODELLED: dict[str, dict[str, tuple[float, bool, float | None]]] = {
    "resonance": {"natural_hz": (0.0, True, None), "damping": (0.0, True, None)},
    "roller_ripple": {"amplitude": (0.0, False, 0.9), "per_turn": (0.0, True, None)},
}


def _unmodelled(doc: TableReader) -> dict[str, dict[str, float]]:
    table = doc.sub("unmodelled", required=False)
    if table is None:
        return {}
    table.reject_unknown(set(UNMODELLED))
    out = {}
    for name, params in UNMODELLED.items():
        sub = table.sub(name, required=False)
        if sub is None:
            continue
        sub.reject_unknown(set(params))
        out[name] = {p: sub.number(p, minimum=lo, strict_minimum=strict, maximum=hi)
                     for p, (lo, strict, hi) in params.items()}
    return out


def apply_effect_params(effects: Effects, named: dict[str, dict[str, Any]]) -> Effects:
    """``effects`` with the named effects' parameters replaced; an effect that cannot share a
    model with a named one (:data:`~mecanum_hil.model.calibration.EXCLUDES`: a fast-decay drive
    and a braking limit) is removed, as the named one replaces it."""
    values: dict[str, Any] = {}
    for name in named:
        for other in EXCLUDES.get(name, ()):
            values.update(EFFECTS[other].absent)
    for params in named.values():
        for key, value in params.items():
            values[key] = tuple(value) if isinstance(value, list) else value
    return replace(effects, **values)


def _parameters_by_name(effects: Effects, names) -> dict[str, dict[str, Any]]:
    return {name: {p: getattr(effects, p) for p in EFFECTS[name].parameters} for name in names}


def _named_effects(table: Any, source: str, prefix: str) -> dict[str, dict[str, Any]]:
    return _parameters_by_name(read_effects_table(table, f"{source} [{prefix}]"), table)


def load_sim_effects(path: str | Path) -> SimEffects:
    """Read an effects file (layout in the module docstring).

    Raises
    ------
    ConfigError
        For a missing file, bad TOML, an unknown table or key, or a value out of range; the
        message names the file and key.
    """
    src = str(path)
    doc = TableReader(load_toml(path), src)
    doc.reject_unknown({"effects", "noise", "faults", "unmodelled"})
    effects = _named_effects(doc.table["effects"], src, "effects") if "effects" in doc.table \
        else {}
    std, seed = 0.0, 0
    noise = doc.sub("noise", required=False)
    if noise is not None:
        noise.reject_unknown({"wheel_rpm_std", "seed"})
        std = noise.number("wheel_rpm_std", 0.0, minimum=0.0)
        seed = noise.whole_number("seed", 0, minimum=0, maximum=2 ** 63 - 1)
    faults = []
    raw = doc.table.get("faults", [])
    if not isinstance(raw, list):
        raise doc.fail("faults", "must be an array of tables ([[faults]])")
    for i, table in enumerate(raw):
        f = TableReader(table, src, f"faults[{i}]")
        f.reject_unknown({"at_s", "effects", "estop"})
        at_s = f.number("at_s", minimum=0.0)
        estop = table.get("estop", False)
        if not isinstance(estop, bool):
            raise f.fail("estop", f"must be true or false, got {estop!r}")
        fx = _named_effects(table["effects"], src, f"faults[{i}].effects") \
            if "effects" in table else {}
        if not fx and not estop:
            raise f.fail("at_s", "fault changes nothing: give [faults.effects.<name>] or estop")
        faults.append(Fault(at_s, fx, estop))
    faults.sort(key=lambda fault: fault.at_s)
    return SimEffects(effects, std, seed, tuple(faults), src, _unmodelled(doc))


def sim_effects_to_toml(sim: SimEffects, header: str = "") -> str:
    """The text of an effects file for ``sim`` (layout in the module docstring); it loads
    back equal (but for :attr:`SimEffects.source`)."""
    lines = [f"# {line}" if line else "#" for line in header.splitlines()]

    def table(name: str, params: dict[str, Any]) -> None:
        lines.extend(["", f"[{name}]"] if lines else [f"[{name}]"])
        # an infinite parameter (a fast-decay drive without droop) is left out, as absent
        lines.extend(f"{k} = {toml_value(v)}" for k, v in params.items()
                     if not (isinstance(v, float) and math.isinf(v)))

    for name, params in sim.effects.items():
        table(f"effects.{name}", params)
    for name, params in sim.unmodelled.items():
        table(f"unmodelled.{name}", params)
    table("noise", {"wheel_rpm_std": float(sim.wheel_rpm_std), "seed": int(sim.seed)})
    for fault in sim.faults:
        lines.extend(["", "[[faults]]", f"at_s = {toml_value(float(fault.at_s))}"])
        if fault.estop:
            lines.append("estop = true")
        for name, params in fault.effects.items():
            table(f"faults.effects.{name}", params)
    return "\n".join(lines) + "\n"


def save_sim_effects(sim: SimEffects, path: str | Path, header: str = "") -> Path:
    """Write ``sim`` as an effects file for ``sim-robot --effects``.

    Parameters
    ----------
    sim : SimEffects
        What the file sets.
    path : str or Path
        File to write (its folder is created).
    header : str
        Comment lines at the top.

    Returns
    -------
    Path

    Raises
    ------
    ConfigError
        When the file cannot be written.
    """
    return write_toml(path, sim_effects_to_toml(sim, header), "the effects file")


def sim_effects_for(effects: Effects, *, wheel_rpm_std: float = 0.0, seed: int = 0,
                    unmodelled: dict[str, dict[str, float]] | None = None) -> SimEffects:
    """The effects file's content that hides ``effects`` in the simulated robot.

    Parameters
    ----------
    effects : Effects
        Its active effects become ``[effects.<name>]`` tables.
    wheel_rpm_std : float
        Noise on the reported wheel speeds [rpm].
    seed : int
        Seed of the noise.
    unmodelled : Mapping, optional
        Effects outside the library (``{"resonance": {"natural_hz": .., "damping": ..}}``,
        ``{"roller_ripple": {"amplitude": .., "per_turn": ..}}``).

    Returns
    -------
    SimEffects
    """
    named = _parameters_by_name(effects, effects.active())
    return SimEffects(named, float(wheel_rpm_std),
                      int(seed), (), "<in memory>", dict(unmodelled or {}))
