"""Least-squares identification of the wheel model (and of effect parameters) from recordings.

The engine of ``mecanum-hil fit`` and ``diagnose``: any subset of the named parameters
(:data:`PARAMETER_NAMES`) is estimated jointly by continuous least squares on every measured wheel
sample of every recording, the other parameters held at the calibration's values. The model is the
project's simulator (:func:`mecanum_hil.model.simulate_batch`) driven by the recorded commands,
from rest, exactly as :func:`mecanum_hil.prediction.predict` runs it; one batch call evaluates the
base point and all finite-difference perturbations of a Jacobian together.

Methods (see ``docs/fit.md``):

* ``lsq`` -- :func:`scipy.optimize.least_squares` (trust-region reflective, bounds that keep the
  model stable) from the best points of a logarithmic grid (for the paper's model alone, whose
  cost is smooth: the same bounded least squares by Levenberg-Marquardt without SciPy,
  :mod:`mecanum_hil.identify.lsq`, and on a short recording the model in numpy,
  :mod:`mecanum_hil.model.linear`: numba and SciPy cost more to load than such a fit takes),
  then 95 % Wald intervals
  ``x +- t_{0.975, n-p} sqrt(diag(s^2 (J^T J)^-1))`` with ``s^2 = SSE / (n - p)``.
* ``paper-grid`` -- the paper's three-pass grid search (:mod:`mecanum_hil.identify.grid`).
"""

from __future__ import annotations

import functools
import math
import re
import threading
from collections.abc import Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from .. import __version__
from ..errors import ConfigError, FitError
from ..io.recording import Recording
from ..model.calibration import Calibration, Effects, check_model_coefficients, coefficient_problem
from ..model.kinematics import command_to_wheels
from ..model.robot import RobotProfile
from ..model.simulate import simulate_batch, steady_state, unchanging
from ..prediction import (
    controller_clock_s,
    initial_state,
    initial_wheel_rpm,
    require_commands,
    start_pose,
    with_tick_phase,
    without_frozen_start,
)
from ..units import RPM_TO_RAD_S

#: Every parameter :func:`fit_parameters` can estimate: the coefficients, then the effects'.
PARAMETER_NAMES: tuple[str, ...] = (
    "A", "B", "C", "dead_time_s", "top_speed_rpm", "rate_limit_rpm_per_s", "deadband_rpm",
    "gains[0]", "gains[1]", "gains[2]", "gains[3]",
    "efficiency[0]", "efficiency[1]", "efficiency[2]",
    "controller_period_s", "drive_lag_s", "breakaway_rpm_per_s", "braking_limit_rpm_per_s",
    "coast_decel_rpm_per_s", "no_load_rpm", "windup_top_speed_rpm",
)

_INDEXED = re.compile(r"^(gains|efficiency)\[(\d)\]$")
_COEFFICIENTS = ("A", "B", "C")
#: The paper's model: no effect present.
_NO_EFFECTS = Effects()

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
}

# Typical magnitude below which a finite-difference step stops shrinking with the value.
_FD_FLOOR = {"dead_time_s": 0.01, "drive_lag_s": 0.01, "controller_period_s": 0.01}
_FD_RELATIVE = 1e-6

#: Coarse starting grid for the coefficients (log-spaced, covers slow drives to fast micro-motors).
START_GRID: dict[str, tuple[float, ...]] = {
    "A": (0.0, 0.3, 1.0, 3.0, 10.0, 30.0, 100.0, 300.0, 1000.0, 3000.0),
    "B": (0.3, 1.0, 3.0, 10.0, 30.0, 100.0, 300.0),
    "C": (1.0, 10.0, 100.0, 1e3, 1e4, 1e5, 1e6),
}

#: Finer logarithmic grid used when the compiled grid kernel applies (linear model).
FINE_START_GRID: dict[str, np.ndarray] = {
    "A": np.concatenate([[0.0], np.logspace(-1, 3.5, 19)]),
    "B": np.concatenate([[0.0], np.logspace(-1, 3, 13)]),
    "C": np.logspace(0, 6, 19),
}

#: Number of grid minima least squares starts from (the best result is kept), and how far
#: above the best grid point's SSE a further minimum may lie to be used.
START_COUNT = 3
START_SSE_RATIO = 1.25
#: Restarts of a least-squares search that stopped on its step test, and the least relative
#: decrease of the cost for which one more is tried.
MAX_RESTARTS = 8
RESTART_GAIN = 1e-4
#: A search whose best cost fell by less than ``RESTART_GAIN`` (relative) over its last
#: ``max(STALL_MIN_EVALUATIONS, STALL_EVALUATIONS_PER_PARAMETER x free parameters)``
#: evaluations is stopped at its best point (status 5, not restarted): in a corner of the model
#: (C -> 0) a trust-region search can creep along a valley, each step lowering the cost by more
#: than ``ftol`` and all of them together by less than 1e-4, until its evaluations run out
#: (800 evaluations, 23 s of a 59-s campaign diagnosis, for 6e-5 of the cost).
STALL_EVALUATIONS_PER_PARAMETER = 15
STALL_MIN_EVALUATIONS = 40

#: Largest condition number of the column-scaled Jacobian for which intervals are trusted.
MAX_CONDITION = 1e8
#: The data do not bound a parameter whose 95 % half-width exceeds this many times its
#: magnitude (:func:`bounded_interval`): the interval then reaches far past the parameter's
#: bound, and the data cannot tell the value from that bound (a dead time of 0.5 +- 4672 s).
UNBOUNDED_FACTOR = 10.0


def _check_name(name: str) -> None:
    if name not in PARAMETER_NAMES:
        raise FitError(f"unknown parameter {name!r}; choose from {', '.join(PARAMETER_NAMES)}")


def _effect_slot(name: str) -> tuple[str, int | None]:
    """The ``Effects`` field of an effect parameter's name and its index in that field's tuple
    (None for a scalar): ``gains[2]`` -> ``("gains", 2)``."""
    _check_name(name)
    m = _INDEXED.match(name)
    return (m.group(1), int(m.group(2))) if m else (name, None)


def _effects_with(effects: Effects, slots: Sequence[tuple[int, str, int | None]],
                  values: Sequence[float]) -> Effects:
    """``effects`` with ``values[i]`` in each slot ``(i, field, index)``
    (:func:`_effect_slot`), as :func:`with_parameters` substitutes them."""
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
    _check_name(name)
    if name in _COEFFICIENTS:
        return float(getattr(calibration, name))
    m = _INDEXED.match(name)
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
        _check_name(name)
        v = float(value)
        if name in _COEFFICIENTS:
            coeffs[name] = v
            continue
        m = _INDEXED.match(name)
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
            *(coeffs.get(n, getattr(calibration, n)) for n in _COEFFICIENTS),
            what or f"the model with new values of {', '.join(values)}")
    eff = replace(calibration.effects, **effects) if effects else calibration.effects
    return replace(calibration, **coeffs, effects=eff, ci95={}, info={})


def toml_key(name: str) -> str:
    """A parameter name as a bare TOML key for ``[ci95]`` (``gains[1]`` -> ``gains_1``)."""
    m = _INDEXED.match(name)
    return f"{m.group(1)}_{m.group(2)}" if m else name


def calibration_intervals(ci95: Mapping[str, tuple[float, float]]
                          ) -> dict[str, tuple[float, float] | None]:
    """Engine intervals (NaN where unidentifiable) as :attr:`Calibration.ci95` holds them:
    bare TOML keys (:func:`toml_key`), ``None`` for an unidentifiable parameter."""
    return {toml_key(k): (float(v[0]), float(v[1])) if all(map(math.isfinite, v)) else None
            for k, v in ci95.items()}


@dataclass(frozen=True)
class FitResult:
    """Outcome of a fit.

    Attributes
    ----------
    calibration : Calibration
        The input calibration with the fitted values substituted and ``ci95`` (bare TOML keys, see
        :func:`toml_key`; ``None`` where unidentifiable) and ``info`` (metrics, method, data
        sources) filled in.
    parameters : dict[str, float]
        Fitted free parameters, in their units.
    ci95 : dict[str, tuple[float, float]]
        95 % confidence intervals of the free parameters, clipped to their admissible ranges;
        ``(nan, nan)`` where the data cannot bound the parameter (:func:`bounded_interval`).
    rmse_rpm : float
        Root mean square wheel-speed error over all measured wheel samples used [rpm].
    fit_percent : float
        ``100 (1 - ||y - y_model|| / ||y - mean(y)||)`` over the same samples [%].
    sse : float
        Sum of squared wheel-speed errors [rpm^2] (the pose channels are not included).
    n_samples : int
        Number of measured wheel samples used.
    method : str
        ``"lsq"`` or ``"paper-grid"``.
    warnings : tuple of str
        Problems the caller should see (a coefficient not identifiable, a bound reached ...).
    """

    calibration: Calibration
    parameters: dict[str, float]
    ci95: dict[str, tuple[float, float]]
    rmse_rpm: float
    fit_percent: float
    sse: float
    n_samples: int
    method: str
    warnings: tuple[str, ...] = ()


@dataclass(frozen=True)
class _Prepared:
    """One recording ready for the model: commands, times, measured channels and masks."""

    t_s: np.ndarray
    commands: np.ndarray
    wheel_rpm: np.ndarray         # (T, 4) measured, NaN where not
    wheel_mask: np.ndarray        # (T, 4) bool
    pose: np.ndarray              # (T, 3) measured, NaN where not
    pose_mask: np.ndarray         # (T, 3) bool
    pose0: tuple[float, float, float]
    pose_scale: np.ndarray        # (3,) pose residual -> wheel-rpm equivalent
    source: str
    start_rpm: np.ndarray         # (4,) wheel speeds at the start (0: at rest)
    start_target: np.ndarray      # (4,) wheel targets of the first command [rpm]
    clock_s: float | None = None  # the controller's clock at the first sample [s]

    @functools.cached_property
    def wheel_measured(self) -> np.ndarray:
        """The wheels measured somewhere in the recording, (4,) bool."""
        return self.wheel_mask.any(axis=0)

    @functools.cached_property
    def wheel_index(self) -> np.ndarray:
        """Flat indices of the measured wheel samples in a (T, 4) array (C order)."""
        return np.flatnonzero(self.wheel_mask.ravel())

    @functools.cached_property
    def wheel_values(self) -> np.ndarray:
        """The measured wheel speeds [rpm], in the order of :attr:`wheel_index`."""
        return self.wheel_rpm.ravel()[self.wheel_index]

    def wheel_residuals(self, wheels: np.ndarray) -> np.ndarray:
        """Measured minus model wheel speeds at the measured samples, one row per model:
        ``wheels`` (M, T, 4) [rpm] -> (M, measured samples)."""
        flat = wheels.reshape(wheels.shape[0], -1)
        # laid out as a boolean mask's result (Fortran order): sums over it then run in the
        # same order, and a fit follows the same path to the last bit
        return (self.wheel_values[:, None] - flat.T[self.wheel_index]).T

    def initial_states(self, calibs: Sequence[Calibration]) -> np.ndarray | None:
        """Steady states at the measured start speeds, with the controller's tick phase, one per
        calibration; None for the default (at rest, first tick at the first sample)."""
        phased = self.clock_s is not None and any(
            c.effects.controller_period_s > 0 for c in calibs)
        if not self.start_rpm.any() and not phased:
            return None
        return np.stack([with_tick_phase(steady_state(c, self.start_rpm, self.start_target),
                                         c, self.clock_s) for c in calibs])


def pose_scale(duration_s: float, robot: RobotProfile) -> np.ndarray:
    """Factors turning pose residuals ``(x [m], y [m], phi [deg])`` into wheel-rpm equivalents.

    A position error ``e`` [m] accumulated over the recording's duration ``T`` is what a constant
    wheel-speed error of ``e / (T r 2 pi / 60)`` [rpm] would cause; a heading error ``e`` [deg]
    likewise corresponds to a turning-speed error ``e / T`` [deg/s], which the kinematics turns
    into ``k e / (6 T)`` [rpm] at the wheels.
    """
    T = max(float(duration_s), 1e-9)
    pos = 1.0 / (T * RPM_TO_RAD_S * robot.wheel_radius_m)
    return np.array([pos, pos, robot.k / (6.0 * T)])


def _source(i: int, rec: Recording, sources: Sequence[str] | None) -> str:
    if sources is not None and i < len(sources):
        return str(sources[i])
    return str(rec.metadata.get("source_file", f"recording {i + 1}"))


def prepare(recordings: Sequence[Recording], robot: RobotProfile,
            sources: Sequence[str] | None = None) -> list[_Prepared]:
    """Check recordings and keep what a fit needs.

    Raises
    ------
    FitError
        Without recordings, without any measured wheel speed, or without excitation (every wheel
        target zero: the model at rest explains nothing).
    RecordingError
        For a recording whose command columns are not all filled.
    """
    if not recordings:
        raise FitError("no recordings given")
    out: list[_Prepared] = []
    for i, rec in enumerate(recordings):
        src = _source(i, rec, sources)
        require_commands(rec, src)
        start = initial_wheel_rpm(rec)
        rec = without_frozen_start(rec)
        wheel = np.asarray(rec.wheel_rpm, dtype=float)
        pose = np.asarray(rec.pose, dtype=float)
        pose0 = start_pose(rec)
        out.append(_Prepared(
            _unchanging(rec.t_s), _unchanging(rec.commands), wheel,
            np.isfinite(wheel), pose, np.isfinite(pose), pose0,
            pose_scale(rec.t_s[-1] - rec.t_s[0], robot), src, start,
            command_to_wheels(rec.commands[:1, 0], rec.commands[:1, 1], rec.commands[:1, 2],
                              robot.k)[0], controller_clock_s(rec)))
    n = sum(int(p.wheel_mask.sum()) for p in out)
    if n == 0:
        raise FitError("no measured wheel speed in the recordings (wheel1_rpm..wheel4_rpm are "
                       "all empty); fit needs wheel speeds from telemetry or video")
    targets = [command_to_wheels(p.commands[:, 0], p.commands[:, 1], p.commands[:, 2], robot.k)
               for p in out]
    if all(np.all(np.abs(w[:-1]) < 1e-12) for w in targets):
        raise FitError("no excitation: every wheel target is zero (the robot was never commanded "
                       "to move), so the data cannot identify the model")
    measured = np.concatenate([p.wheel_rpm[p.wheel_mask] for p in out])
    if np.ptp(measured) == 0.0:
        raise FitError("no excitation: every measured wheel speed has the same value")
    return out


def _unchanging(a) -> np.ndarray:
    """A private copy of ``a`` (float) that nothing changes: the simulator remembers what it
    learnt about it (its bytes, its checks) instead of redoing it on every simulation. (Not
    made read-only: numba compiles its kernels again for read-only arguments.)"""
    return unchanging(np.array(a, dtype=float))


@contextmanager
def few_threads(work: float):
    """Run numba's parallel loops on one thread when the work is small.

    ``work`` is roughly the number of wheel-steps to simulate. Waking a thread pool costs more
    than a few thousand steps take, and on a loaded machine a parallel launch waits for the
    busiest core, so small batches (a Jacobian) run faster serially.
    """
    import sys

    numba = sys.modules.get("numba")
    if numba is None or work >= 200_000:
        # numba not loaded: the job runs interpreted (mecanum_hil._jit), or compiles now and
        # pays far more for loading numba than its threads could cost
        yield
        return
    before = numba.get_num_threads()
    if before == 1:  # already (beside a helper: mecanum_hil._jit.kernel_threads)
        yield
        return
    numba.set_num_threads(1)
    try:
        yield
    finally:
        numba.set_num_threads(before)


#: ``openblas_set_num_threads`` / ``..._get_...`` under the names OpenBLAS builds export.
_BLAS_SYMBOLS = (("openblas_set_num_threads", "openblas_get_num_threads"),
                 ("openblas_set_num_threads64_", "openblas_get_num_threads64_"),
                 ("scipy_openblas_set_num_threads64_", "scipy_openblas_get_num_threads64_"),
                 ("scipy_openblas_set_num_threads", "scipy_openblas_get_num_threads"))
_blas_lock = threading.Lock()
_blas_depth = 0
_blas_saved: list[tuple[Any, int]] = []


def _openblas_controls() -> list[tuple[Any, Any]]:
    """(set, get) thread-count functions of every OpenBLAS loaded in this process (numpy's and
    scipy's are separate libraries); none where ``/proc/self/maps`` is not there."""
    import ctypes

    try:
        with open("/proc/self/maps") as f:
            paths = sorted({line.split()[-1] for line in f if ".so" in line
                            and "openblas" in line.rsplit("/", 1)[-1].lower()})
    except OSError:
        return []
    out = []
    for path in paths:
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for set_name, get_name in _BLAS_SYMBOLS:
            if hasattr(lib, set_name) and hasattr(lib, get_name):
                out.append((getattr(lib, set_name), getattr(lib, get_name)))
                break
    return out


@contextmanager
def one_blas_thread():
    """Run OpenBLAS on one thread inside (re-entrant; the counts are restored after).

    A fit's linear algebra is many small products of a tall Jacobian; OpenBLAS spreads each
    over its threads, whose waiting spins take the cores the simulator needs: on the 2-core
    machine of ``docs/benchmarks/diagnose.md`` a campaign's diagnosis took 2.7 x the CPU time
    with OpenBLAS's default threads. One thread also makes the sums' order, and so the fitted
    values, the same on every machine.
    """
    global _blas_depth
    with _blas_lock:
        if _blas_depth == 0:
            _blas_saved.clear()
            for set_threads, get_threads in _openblas_controls():
                try:
                    _blas_saved.append((set_threads, int(get_threads())))
                    set_threads(1)
                except (OSError, ValueError, TypeError):  # pragma: no cover - odd builds
                    continue
        _blas_depth += 1
    try:
        yield
    finally:
        with _blas_lock:
            _blas_depth -= 1
            if _blas_depth == 0:
                for set_threads, count in _blas_saved:
                    set_threads(count)
                _blas_saved.clear()


def _simulate(p: _Prepared, calibs: Sequence[Calibration], robot: RobotProfile, pose: bool):
    state = p.initial_states(calibs)
    with few_threads(len(calibs) * p.t_s.size * 4):
        traj = simulate_batch(p.commands, p.t_s, list(calibs), robot, initial_pose=p.pose0,
                              initial_state=state,
                              initial_command=p.commands[0] if p.start_rpm.any() else None,
                              **_outputs([p], pose))
    return traj.wheel_rpm, traj.pose


def _outputs(members: Sequence[_Prepared], pose: bool) -> dict:
    """What a fit simulates of recordings run as one batch: with the pose, everything; else
    the wheels measured in any of them, and no pose (NaN; see :func:`simulate_batch`)."""
    if pose:
        return {}
    wheels = np.zeros(4, dtype=bool)
    for p in members:
        wheels |= p.wheel_measured
    return {"wheels": wheels, "pose": False}


def _simulate_all(data: Sequence[_Prepared], calibs: Sequence[Calibration],
                  robot: RobotProfile, pose: bool = True) -> list[tuple[np.ndarray, np.ndarray]]:
    """Wheel speeds and poses, shape (len(calibs), T, .), of every recording: recordings on the
    same time grid run as one batch (a campaign's steps: one call instead of one per
    recording; each robot's result does not depend on its batch). Without ``pose`` only the
    measured wheels are simulated, and the poses are NaN."""
    groups: dict[bytes, list[int]] = {}
    for i, p in enumerate(data):
        groups.setdefault(p.t_s.tobytes(), []).append(i)
    out: list[tuple[np.ndarray, np.ndarray]] = [None] * len(data)  # type: ignore[list-item]
    k = len(calibs)
    for idx in groups.values():
        if len(idx) == 1:
            out[idx[0]] = _simulate(data[idx[0]], calibs, robot, pose)
            continue
        m = len(idx)
        members = [data[i] for i in idx]
        # robot k * m + j: calibration k on recording j of the group
        cmds = np.tile(np.stack([p.commands for p in members]), (k, 1, 1))
        pose0 = np.tile(np.array([p.pose0 for p in members], dtype=float), (k, 1))
        states = [p.initial_states(calibs) for p in members]
        state = None
        if any(s is not None for s in states):
            width = next(s for s in states if s is not None).shape[1]
            per = [s if s is not None else np.zeros((k, width)) for s in states]
            state = np.stack(per, axis=1).reshape(k * m, width)
        cmd0 = None
        if any(p.start_rpm.any() for p in members):
            cmd0 = np.tile(np.array([p.commands[0] if p.start_rpm.any() else np.zeros(3)
                                     for p in members]), (k, 1))
        per_robot = [c for c in calibs for _ in range(m)]
        with few_threads(k * m * members[0].t_s.size * 4):
            traj = simulate_batch(cmds, members[0].t_s, per_robot, robot, initial_pose=pose0,
                                  initial_state=state, initial_command=cmd0,
                                  **_outputs(members, pose))
        wheels = traj.wheel_rpm.reshape(k, m, *traj.wheel_rpm.shape[1:])
        poses = traj.pose.reshape(k, m, *traj.pose.shape[1:])
        for j, i in enumerate(idx):
            out[i] = (wheels[:, j], poses[:, j])
    return out


def _paper_rows(data: Sequence[_Prepared], calibs: Sequence[Calibration],
                robot: RobotProfile) -> np.ndarray | None:
    """Wheel residual rows of the paper's model (every calibration without effects) through
    :mod:`mecanum_hil.model.linear`, when that costs less than loading numba; else None."""
    from .._jit import interpret
    from ..model.linear import step_lengths, wheel_speeds, work_units

    if any(c.effects != _NO_EFFECTS for c in calibs):
        return None
    grids = [step_lengths(p.t_s) for p in data]
    if not interpret(work_units(sum(p.t_s.size for p in data), 4 * len(calibs),
                                len(calibs) * sum(h.size for h, _ in grids))):
        return None
    co = np.array([c.coefficients for c in calibs])
    parts = []
    for p, (h_s, h_idx) in zip(data, grids, strict=True):
        targets = command_to_wheels(p.commands[:, 0], p.commands[:, 1], p.commands[:, 2],
                                    robot.k)
        y0 = z0 = None
        if p.start_rpm.any():
            # the simulator's start in motion: steady state at the measured speeds
            state = np.stack([steady_state(c, p.start_rpm, p.start_target) for c in calibs])
            y0, z0 = state[:, :4], state[:, 4:8]
        wheels = wheel_speeds(co, h_s, h_idx, targets.T, y0, z0).transpose(0, 2, 1)
        parts.append(p.wheel_residuals(wheels))
    return np.concatenate(parts, axis=1)


def _residual_rows(data: Sequence[_Prepared], calibs: Sequence[Calibration], robot: RobotProfile,
                   pose_weight: float) -> np.ndarray:
    """Residual vectors ``measured - model``, one row per calibration (wheels, then poses)."""
    if not _fits_pose(data, pose_weight):
        rows = _paper_rows(data, calibs, robot)
        if rows is not None:
            return rows
    parts = []
    fitted = _simulate_all(data, calibs, robot, _fits_pose(data, pose_weight))
    for p, (wheels, pose) in zip(data, fitted, strict=True):
        parts.append(p.wheel_residuals(wheels))
        if pose_weight > 0 and p.pose_mask.any():
            d = p.pose[None] - pose
            d[..., 2] = (d[..., 2] + 180.0) % 360.0 - 180.0  # headings compare modulo a turn
            d *= pose_weight * p.pose_scale
            parts.append(d[:, p.pose_mask])
    return np.concatenate(parts, axis=1)


def _fits_pose(data: Sequence[_Prepared], pose_weight: float) -> bool:
    """Whether the residuals include pose channels (a weight, and a pose measured somewhere)."""
    return pose_weight > 0 and any(p.pose_mask.any() for p in data)


def _wheel_count(data: Sequence[_Prepared]) -> int:
    return sum(int(p.wheel_mask.sum()) for p in data)


def residuals(recordings: Sequence[Recording], calibration: Calibration,
              robot: RobotProfile) -> list[np.ndarray]:
    """Measured minus model wheel speeds, per recording.

    The model runs on each recording's commands and times as in
    :func:`mecanum_hil.prediction.predict` (from rest, or in steady state at the measured
    speeds when the recording starts in motion).

    Returns
    -------
    list of ndarray, shape (T, 4)
        ``wheel_rpm - model`` [rpm]; NaN where the wheel speed was not measured.
    """
    out = []
    for rec in recordings:
        require_commands(rec)
        state = initial_state(rec, calibration, robot)
        traj = simulate_batch(rec.commands, rec.t_s, calibration, robot,
                              initial_pose=start_pose(rec), initial_state=state,
                              initial_command=rec.commands[0] if initial_wheel_rpm(rec).any()
                              else None)
        out.append(np.asarray(rec.wheel_rpm, dtype=float) - traj.wheel_rpm[0])
    return out


class _SearchStalledError(Exception):
    """A watched search stalled (:data:`STALL_EVALUATIONS_PER_PARAMETER`); carries its best
    point as a :class:`~mecanum_hil.identify.lsq.Solution` with status 5."""

    def __init__(self, solution) -> None:
        super().__init__(solution.message)
        self.solution = solution


class _Problem:
    """Residuals and their Jacobian for a set of free parameters.

    The residuals at a point are one simulation; its Jacobian (forward differences) is one
    batch call for the perturbed points, made only when the solver asks for it. A trust-region
    search evaluates many trial points it rejects (about a third in ``diagnose``), whose
    Jacobian it never uses. A point whose Jacobian is asked for first gets both in one batch,
    and so does every point when not ``lazy``: the paper's model on a short recording runs in
    numpy (:func:`_paper_rows`), whose cost per call is mostly per time step, not per point.
    """

    def __init__(self, data, calibration, robot, free, lower, upper, pose_weight,
                 lazy: bool = True):
        self.data = data
        self.lazy = lazy
        self.calibration = calibration
        self.robot = robot
        self.free = list(free)
        self.lower = lower
        self.upper = upper
        self.pose_weight = pose_weight
        self.nfev = 0
        self._x: np.ndarray | None = None
        self._r: np.ndarray | None = None
        self._J: np.ndarray | None = None
        # a watched search: its best cost after each evaluation, and its best point
        self._trace: list[float] | None = None
        self._best: tuple[float, np.ndarray] | None = None
        # the effects of recent points by their values: a Jacobian's perturbations of A, B, C
        # share them, and building them (checked dataclasses) costs as much as a short kernel
        self._coefficients = [(n, i) for i, n in enumerate(self.free) if n in _COEFFICIENTS]
        self._effect_slots = [(i, *_effect_slot(n)) for i, n in enumerate(self.free)
                              if n not in _COEFFICIENTS]
        self._effects: dict[tuple[float, ...], Effects] = {}

    def watch(self, x0: np.ndarray) -> None:
        """Start watching a search from ``x0`` for a stall
        (:data:`STALL_EVALUATIONS_PER_PARAMETER`); a start already evaluated (a restart from
        where the last search ended) counts as the search's first evaluation."""
        self._trace, self._best = [], None
        if self._x is not None and np.array_equal(self._x, np.asarray(x0, dtype=float)):
            self._watched(self._x, self._r)

    def unwatch(self) -> None:
        self._trace = self._best = None

    def _watched(self, x: np.ndarray, r: np.ndarray) -> None:
        """Record an evaluation of a watched search; raise on a stall."""
        if self._trace is None:
            return
        cost = 0.5 * float(r @ r)
        if math.isfinite(cost) and (self._best is None or cost < self._best[0]):
            self._best = (cost, x.copy())
        self._trace.append(self._best[0] if self._best is not None else math.inf)
        window = max(STALL_MIN_EVALUATIONS, STALL_EVALUATIONS_PER_PARAMETER * len(self.free))
        if len(self._trace) > window:
            before = self._trace[-1 - window]
            if math.isfinite(before) and self._trace[-1] > (1.0 - RESTART_GAIN) * before:
                from .lsq import solution

                cost, x_best = self._best
                raise _SearchStalledError(solution(x_best, cost, 5, len(self._trace)))

    def calibration_at(self, x) -> Calibration:
        """The calibration at point ``x``: :func:`with_parameters` of the free parameters."""
        values = np.asarray(x, dtype=float).tolist()
        if len(values) != len(self.free):
            raise ValueError(f"{len(values)} values for {len(self.free)} free parameters")
        key = tuple(values[i] for i, _, _ in self._effect_slots)
        effects = self._effects.get(key)
        if effects is None:
            effects = _effects_with(self.calibration.effects, self._effect_slots, values)
            if len(self._effects) >= 64:
                self._effects.clear()
            self._effects[key] = effects
        coefficients = {n: values[i] for n, i in self._coefficients}
        try:
            return replace(self.calibration, **coefficients, effects=effects, ci95={}, info={})
        except ConfigError:
            # said as the point's problem (the caller says it is the fit's), not the
            # calibration's in memory
            A, B, C = (coefficients.get(n, getattr(self.calibration, n)) for n in _COEFFICIENTS)
            problem = coefficient_problem(A, B, C)
            if problem is None:
                raise
            raise ConfigError(problem) from None

    def steps(self, x: np.ndarray) -> np.ndarray:
        floor = np.array([_FD_FLOOR.get(n, 1.0) for n in self.free])
        h = _FD_RELATIVE * np.maximum(np.abs(x), floor)
        # step into the feasible region (a parameter on its bound is differentiated one-sidedly)
        return np.where(x + h > self.upper, -h, h)

    def _rows(self, points: Sequence[np.ndarray]) -> np.ndarray:
        try:
            calibs = [self.calibration_at(pt) for pt in points]
        except ConfigError as err:
            raise FitError(f"the fit reached an invalid model: {err}") from err
        return _residual_rows(self.data, calibs, self.robot, self.pose_weight)

    def evaluate(self, x: np.ndarray, jacobian: bool = True) -> None:
        """Residuals at ``x`` and, with ``jacobian``, their Jacobian (one batch call)."""
        x = np.array(x, dtype=float)
        h = self.steps(x)
        rows = self._rows([x] + (self._perturbed(x, h) if jacobian else []))
        self.nfev += 1
        self._x, self._r, self._J = x, rows[0], None
        if jacobian:
            self._J = self._jacobian(rows[1:], h)
        self._watched(x, self._r)

    @staticmethod
    def _perturbed(x: np.ndarray, h: np.ndarray) -> list[np.ndarray]:
        return [x + h[j] * np.eye(x.size)[j] for j in range(x.size)]

    def _jacobian(self, perturbed: np.ndarray, h: np.ndarray) -> np.ndarray:
        # residuals are measured - model, so d(residual)/dx = (r(x + h) - r(x)) / h
        return ((perturbed - self._r) / h[:, None]).T

    def fun(self, x) -> np.ndarray:
        if self._x is None or not np.array_equal(self._x, x):
            self.evaluate(x, jacobian=not self.lazy)
        return self._r

    def jac(self, x) -> np.ndarray:
        if self._x is None or not np.array_equal(self._x, x):
            self.evaluate(x)
        elif self._J is None:
            h = self.steps(self._x)
            self._J = self._jacobian(self._rows(self._perturbed(self._x, h)), h)
        return self._J


def _sse_of(data, calibs, robot) -> np.ndarray:
    rows = _residual_rows(data, calibs, robot, 0.0)
    with np.errstate(over="ignore", invalid="ignore"):
        s = np.einsum("ij,ij->i", rows, rows)
    return np.where(np.isfinite(s), s, np.inf)


def _data_start_values(data: Sequence[_Prepared]) -> dict[str, float]:
    """Starting values of effect parameters whose "absent" value cannot start a search."""
    measured = np.concatenate([p.wheel_rpm[p.wheel_mask] for p in data])
    peak = float(np.max(np.abs(measured)))
    from .regimes import measured_differences

    slopes = []
    for p in data:
        # between consecutive measurements of each wheel (a recorded run's command rows,
        # without one, are skipped)
        d = np.abs(measured_differences(p.wheel_rpm, p.t_s))
        slopes.append(d[np.isfinite(d)])
    slope = float(np.percentile(np.concatenate(slopes), 95)) if any(s.size for s in slopes) else 1.0
    top = max(1.25 * peak, 1.0)
    return {"top_speed_rpm": top, "windup_top_speed_rpm": top,
            "rate_limit_rpm_per_s": max(slope, 1.0)}


def _local_minima(sse: np.ndarray, count: int) -> np.ndarray:
    """Flat indices of up to ``count`` grid points lower than their axis neighbours, best first."""
    is_min = np.isfinite(sse)
    for ax in range(sse.ndim):
        if sse.shape[ax] == 1:
            continue
        pad = [(0, 0)] * sse.ndim
        pad[ax] = (1, 1)
        padded = np.pad(sse, pad, constant_values=np.inf)
        lo = np.take(padded, np.arange(0, sse.shape[ax]), axis=ax)
        hi = np.take(padded, np.arange(2, sse.shape[ax] + 2), axis=ax)
        is_min &= (sse <= lo) & (sse <= hi)
    idx = np.flatnonzero(is_min.ravel())
    if idx.size == 0:
        idx = np.array([int(np.argmin(np.where(np.isfinite(sse), sse, np.inf)))])
    return idx[np.argsort(sse.ravel()[idx], kind="stable")][:count]


def _median_period_s(data: Sequence[_Prepared]) -> float:
    """Median period of the wheel measurements [s] (a recorded run's command rows, without
    one, are not samples)."""
    steps = np.concatenate([np.diff(p.t_s[p.wheel_mask.any(axis=1)]) for p in data])
    return float(np.median(steps)) if steps.size else 0.0


def _grid_axis(name: str, axis, period_s: float) -> np.ndarray:
    """A start grid axis extended, at its own log spacing, up to the fastest time scale the
    samples resolve: ``A`` and ``B`` up to ``2 / period_s`` [1/s], ``C`` up to its square.
    (The default axes already reach 1000 1/s; a 1 kHz log of a fast motor needs more.)"""
    axis = np.asarray(axis, dtype=float)
    if not period_s > 0 or axis.size < 2 or axis[-2] <= 0:
        return axis
    fastest = 2.0 / period_s
    top = fastest ** 2 if name == "C" else fastest
    ratio = axis[-1] / axis[-2]
    extra = []
    v = axis[-1]
    while v < top and ratio > 1.0 and len(extra) < 20:
        v *= ratio
        extra.append(v)
    return np.concatenate([axis, extra]) if extra else axis


def _starts(data, calibration, robot, free, x0, lower, upper) -> list[dict[str, float]]:
    """Starting points: given values, else the best local minima of a logarithmic grid over the
    free coefficients (the compiled grid kernel for a linear model), a scan for dead time, and
    data-based values for top speed and rate limit."""
    given = dict(x0 or {})
    start = {n: given.get(n, parameter_value(calibration, n)) for n in free}
    missing = [n for n in free if n not in given and not math.isfinite(start[n])]
    if missing:  # read off the data only when needed (a refit gives every start)
        defaults = _data_start_values(data)
        for n in missing:
            start[n] = defaults.get(n, 1.0)
    base = with_parameters(calibration, {n: v for n, v in start.items() if n not in _COEFFICIENTS})
    grid_names = [n for n in _COEFFICIENTS if n in free and n not in given]
    starts = [dict(start)]
    if grid_names:
        linear = not base.effects.nonlinear
        spec = FINE_START_GRID if linear else START_GRID
        period = _median_period_s(data)
        axes = [_grid_axis(n, spec[n], period) if n in grid_names else
                np.asarray((getattr(base, n),), dtype=float) for n in _COEFFICIENTS]
        pts = np.array(np.meshgrid(*axes, indexing="ij")).reshape(3, -1).T
        ok = (pts[:, 0] + pts[:, 1] > 0) & (pts[:, 2] > 0)
        sse = np.full(pts.shape[0], np.inf)
        if linear:
            from .grid import evaluate_points, grid_data

            g = grid_data(data, base, robot)
            with few_threads(pts.shape[0] * g.target_rpm.size):
                sse[ok] = evaluate_points(g, pts[ok])
        else:
            sse[ok] = _sse_of(data, [base.with_coefficients(*pt) for pt in pts[ok]], robot)
        starts = []
        minima = _local_minima(sse.reshape([a.size for a in axes]), START_COUNT)
        # a minimum far above the best rarely leads least squares to a better optimum
        minima = [f for f in minima if sse[f] <= START_SSE_RATIO * sse[minima[0]]]
        for flat in minima:
            s = dict(start)
            for i, n in enumerate(_COEFFICIENTS):
                if n in grid_names:
                    s[n] = float(pts[flat, i])
            starts.append(s)
    if "dead_time_s" in free and "dead_time_s" not in given:
        base = with_parameters(base, {n: starts[0][n] for n in _COEFFICIENTS if n in free})
        span = min(float(np.median([p.t_s[-1] - p.t_s[0] for p in data])) / 4.0, 0.5)
        # a coarse scan of the span, and every sample period up to 20 samples (a fast drive's
        # dead time is a few samples, finer than the coarse scan)
        period = _median_period_s(data)
        cands = np.unique(np.concatenate([[start["dead_time_s"]], np.linspace(0.0, span, 26),
                                          np.arange(0.0, min(span, 20.0 * period), period)]))
        calibs = [with_parameters(base, {"dead_time_s": c}) for c in cands]
        best = float(cands[int(np.argmin(_sse_of(data, calibs, robot)))])
        for s in starts:
            s["dead_time_s"] = best
    return [{n: float(np.clip(s[n], lower[i], upper[i])) for i, n in enumerate(free)}
            for s in starts]


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
    scale = max(abs(value), _FD_FLOOR.get(name, 1.0))
    if half > UNBOUNDED_FACTOR * scale:
        return (f"its 95 % half-width {half:.4g} exceeds {UNBOUNDED_FACTOR:g} times its "
                f"magnitude {scale:.4g}")
    return None


def _intervals(J: np.ndarray, r_wheel_and_pose: np.ndarray, x: np.ndarray, free: Sequence[str],
               on_bound: np.ndarray):
    """95 % Wald intervals from the Jacobian; warnings for parameters the data cannot pin down."""
    # the t quantile without scipy.stats (~0.2 s to import) or scipy.special: exact to rounding
    from .lsq import t_quantile

    n, p = J.shape
    warnings: list[str] = []
    half = np.full(p, np.nan)
    dof = n - p
    if dof <= 0:
        warnings.append(f"{n} residuals for {p} parameters: no confidence intervals")
        return half, warnings
    s2 = float(r_wheel_and_pose @ r_wheel_and_pose) / dof
    norms = np.linalg.norm(J, axis=0)
    dead = norms == 0.0
    Js = J[:, ~dead] / norms[~dead]
    if Js.size:
        S, Vt = np.linalg.svd(Js, full_matrices=False)[1:]
        cond = S[0] / S[-1] if S[-1] > 0 else math.inf
        if math.isfinite(cond) and cond <= MAX_CONDITION:
            cov = (Vt.T / S**2) @ Vt / np.outer(norms[~dead], norms[~dead])
            half[~dead] = t_quantile(0.975, dof) * np.sqrt(s2 * np.diag(cov))
        else:
            names = ", ".join(n for n, d in zip(free, dead, strict=True) if not d)
            warnings.append(f"parameters {names} are not jointly identifiable from these data "
                            f"(condition number {cond:.3g}); intervals not computed")
    for name, d in zip(free, dead, strict=True):
        if d:
            warnings.append(f"{name} is not identifiable: the data do not depend on it")
    for i, name in enumerate(free):
        if not math.isfinite(half[i]):
            continue
        why = unbounded(name, x[i], x[i] - half[i], x[i] + half[i])
        if why is not None:
            warnings.append(
                f"{name} is not identifiable from these data: {why}, so no interval is given "
                "(the data may lack a transient, or a change of command)")
        elif not on_bound[i] and half[i] > max(abs(x[i]), 1e-12):
            warnings.append(
                f"{name} is poorly identified: 95 % interval +-{half[i]:.4g} exceeds its value "
                f"{x[i]:.4g} (the data may lack a transient, e.g. a step too short)")
    return half, warnings


def _metrics(data, calibration, robot, rows=None) -> tuple[float, float, float, int, list[float]]:
    # rows: the wheel residuals of ``calibration`` when the caller has them
    if rows is None:
        rows = _residual_rows(data, [calibration], robot, 0.0)[0]
    measured = np.concatenate([p.wheel_rpm[p.wheel_mask] for p in data])
    sse = float(rows @ rows)
    n = measured.size
    spread = float(np.linalg.norm(measured - measured.mean()))
    fit_pct = 100.0 * (1.0 - math.sqrt(sse) / spread) if spread > 0 else -math.inf
    per = []
    start = 0
    for p in data:
        m = p.wheel_rpm[p.wheel_mask]
        r = rows[start:start + m.size]
        start += m.size
        sp = float(np.linalg.norm(m - m.mean()))
        per.append(100.0 * (1.0 - float(np.linalg.norm(r)) / sp) if sp > 0 else math.nan)
    return sse, math.sqrt(sse / n), fit_pct, n, per


def finish(data, calibration, robot, free, x, method, *, J=None, r=None, pose_weight=0.0,
           lower=None, upper=None, extra_warnings=(), info_extra=None) -> FitResult:
    """Metrics, intervals and provenance for parameters ``x`` of ``free`` (shared by methods)."""
    x = np.asarray(x, dtype=float)
    if J is None or r is None:
        # residuals and Jacobian at one point: one batch
        problem = _Problem(data, calibration, robot, free,
                           np.array([DEFAULT_BOUNDS[n][0] for n in free]),
                           np.array([DEFAULT_BOUNDS[n][1] for n in free]), pose_weight,
                           lazy=False)
        r, J = problem.fun(x), problem.jac(x)
    if lower is None or upper is None:
        lower = np.array([DEFAULT_BOUNDS[n][0] for n in free])
        upper = np.array([DEFAULT_BOUNDS[n][1] for n in free])
    tol = 1e-6 * np.maximum(1.0, np.abs(x))
    on_bound = (x <= lower + tol) | (x >= upper - tol)
    half, warnings = _intervals(J, r, x, free, on_bound)
    warnings = list(extra_warnings) + warnings
    for i, name in enumerate(free):
        if on_bound[i]:
            edge = lower[i] if x[i] <= lower[i] + tol[i] else upper[i]
            why = ""
            if name == "C" and edge == lower[i]:
                # the commonest corner: the paper's model has no other way to settle short
                why = ("; no integral action is how this model follows a level that settles "
                       "short of the target (a ceiling, a proportional-only loop, a gain): "
                       "`mecanum-hil diagnose` tells which")
            warnings.append(f"{name} = {x[i]:.4g} is at its bound {edge:g}: the data favour the "
                            "edge of the allowed range, and its interval (which assumes an "
                            f"interior optimum) is only indicative{why}")
    params = {n: float(v) for n, v in zip(free, x, strict=True)}
    cal = with_parameters(calibration, params, "the fitted model")
    # without pose channels the search's last residual is the wheels' at x: no new simulation
    # (contiguous, as a fresh simulation's: the sums then run in the same order)
    sse, rmse, fit_pct, n, per = _metrics(data, cal, robot,
                                          np.ascontiguousarray(r) if pose_weight == 0 else None)
    ci = {n: bounded_interval(n, float(x[i]), float(x[i] - half[i]), float(x[i] + half[i]))
          or (math.nan, math.nan) for i, n in enumerate(free)}
    info: dict[str, Any] = {
        "method": method,
        "rmse_rpm": rmse,
        "fit_percent": fit_pct,
        "sse": sse,
        "n_samples": n,
        "free": list(free),
        "sources": [p.source for p in data],
        "fit_percent_per_recording": per,
        "tool_version": __version__,
    }
    if pose_weight > 0:
        info["pose_weight"] = float(pose_weight)
    info.update(info_extra or {})
    if warnings:
        info["warnings"] = list(warnings)
    cal = replace(cal, ci95=calibration_intervals(ci), info=info)
    return FitResult(cal, params, ci, rmse, fit_pct, sse, n, method, tuple(warnings))


def _bounds(free, bounds) -> tuple[np.ndarray, np.ndarray]:
    given = dict(bounds or {})
    for n in given:
        _check_name(n)
    lo = np.array([float(given.get(n, DEFAULT_BOUNDS[n])[0]) for n in free])
    hi = np.array([float(given.get(n, DEFAULT_BOUNDS[n])[1]) for n in free])
    d_lo = np.array([DEFAULT_BOUNDS[n][0] for n in free])
    d_hi = np.array([DEFAULT_BOUNDS[n][1] for n in free])
    if (lo < d_lo).any() or (hi > d_hi).any() or (lo >= hi).any():
        raise FitError("bounds must lie within the stable, physical range "
                       f"{ {n: DEFAULT_BOUNDS[n] for n in free} } and have lower < upper")
    return lo, hi


def fit_parameters(
    recordings: Sequence[Recording],
    calibration: Calibration,
    robot: RobotProfile,
    free: Sequence[str] = ("A", "B", "C"),
    *,
    x0: Mapping[str, float] | None = None,
    bounds: Mapping[str, tuple[float, float]] | None = None,
    pose_weight: float = 0.0,
    sources: Sequence[str] | None = None,
    max_evaluations: int | None = None,
) -> FitResult:
    """Joint continuous least squares of free parameters on all measured samples.

    Parameters
    ----------
    recordings : sequence of Recording
        Any commands (steps, ramps, turns, mixed); wheel speeds from telemetry or video, empty
        values skipped. The model starts each recording from rest.
    calibration : Calibration
        Values of the parameters that are not free (and effects present).
    robot : RobotProfile
        Geometry for the kinematics.
    free : sequence of str
        Names from :data:`PARAMETER_NAMES` to estimate.
    x0 : Mapping[str, float], optional
        Starting values; parameters without one start from a coarse grid (A, B, C), a scan
        (dead time), the data (top speed, rate limit) or the calibration's value.
    bounds : Mapping[str, (float, float)], optional
        Narrower bounds than :data:`DEFAULT_BOUNDS`.
    pose_weight : float
        Weight of the pose channels ``(x_m, y_m, phi_deg)`` where measured, whose residuals enter
        as wheel-rpm equivalents (see :func:`pose_scale`); 0 fits wheel speeds only.
    sources : sequence of str, optional
        Names of the recordings for the provenance (default: ``recording 1`` ...).
    max_evaluations : int, optional
        At most this many residual evaluations per search and no restarts: a quick refit from
        a start near the optimum (``diagnose``'s held-out folds). Default: converge.

    Returns
    -------
    FitResult

    Raises
    ------
    FitError
        Bad input (see :func:`prepare`), an unknown parameter, or no convergence.
    """
    with one_blas_thread():
        return _fit_parameters(recordings, calibration, robot, free, x0, bounds, pose_weight,
                               sources, max_evaluations)


def _fit_parameters(recordings, calibration, robot, free, x0, bounds, pose_weight, sources,
                    max_evaluations) -> FitResult:
    free = list(dict.fromkeys(free))
    if not free:
        raise FitError("no free parameters to fit")
    for n in free:
        _check_name(n)
    if not (pose_weight >= 0 and math.isfinite(pose_weight)):
        raise FitError(f"pose_weight must be a finite number >= 0, got {pose_weight!r}")
    data = prepare(recordings, robot, sources)
    lo, hi = _bounds(free, bounds)
    # parameters the fitted channels cannot depend on (the gain of a wheel never measured, on
    # wheel speeds alone) stay where they start: searching them only costs evaluations
    held = _unseen(data, free, pose_weight)
    fixed = {n: float(np.clip((x0 or {}).get(n, parameter_value(calibration, n)),
                              lo[free.index(n)], hi[free.index(n)])) for n in held}
    live = [n for n in free if n not in fixed]
    idx = [free.index(n) for n in live]
    base = with_parameters(calibration, fixed)
    pose = _fits_pose(data, pose_weight)
    problem = _Problem(data, base, robot, live, lo[idx], hi[idx], pose_weight,
                       lazy=not _smooth(base, live, pose))
    solve = _solver(base, live, pose)
    best = None
    failures = []
    for start in _starts(data, base, robot, live, x0, lo[idx], hi[idx]):
        x_start = np.array([start[n] for n in live])
        budget = max_evaluations or 200 * len(free)
        try:
            sol = solve(problem, x_start, lo[idx], hi[idx], budget)
        except (ValueError, np.linalg.LinAlgError) as err:
            failures.append(f"least squares failed: {err}")
            continue
        if (sol.status < 0 or (sol.status == 0 and max_evaluations is None)
                or not np.isfinite(sol.cost)):
            failures.append(f"least squares did not converge: {sol.message}")
            continue
        if max_evaluations is None:
            sol = _restarted(problem, sol, lo[idx], hi[idx], budget, solve)
        if best is None or sol.cost < best.cost:
            best = sol
    if best is None:
        raise FitError(failures[0] if failures else "least squares did not converge")
    r, J_live = problem.fun(best.x), problem.jac(best.x)
    # the held parameters' Jacobian columns are zero: finish reports them not identifiable
    x = np.array([fixed[n] if n in fixed else 0.0 for n in free])
    x[idx] = best.x
    J = np.zeros((J_live.shape[0], len(free)))
    J[:, idx] = J_live
    return finish(data, calibration, robot, free, x, "lsq", J=J, r=r, pose_weight=pose_weight,
                  lower=lo, upper=hi, info_extra={"evaluations": problem.nfev})


def _unseen(data: Sequence[_Prepared], free: Sequence[str], pose_weight: float) -> list[str]:
    """Free parameters no fitted residual depends on: with the pose channels unused (no weight
    or no pose measured), a wheel gain of a wheel measured in no recording, and the slip
    efficiencies. Empty when every free parameter would be held (nothing left to fit)."""
    pose = _fits_pose(data, pose_weight)
    if pose:
        return []
    seen = np.zeros(4, bool)
    for p in data:
        seen |= p.wheel_mask.any(axis=0)
    out = []
    for n in free:
        m = _INDEXED.match(n)
        if m and (m.group(1) == "efficiency" or not seen[int(m.group(2))]):
            out.append(n)
    return out if len(out) < len(free) else []


def _smooth(calibration: Calibration, live: Sequence[str], pose: bool) -> bool:
    """Whether a problem is the paper's model alone (no effect, only A, B, C free, wheel speeds
    only): a smooth cost."""
    return calibration.effects == _NO_EFFECTS and set(live) <= set(_COEFFICIENTS) and not pose


def _solver(calibration: Calibration, live: Sequence[str], pose: bool):
    """The least-squares method for a problem: ``solve(problem, x0, lower, upper, max_nfev)``.

    The paper's model (no effect, only A, B, C free, wheel speeds only) has a smooth cost:
    :func:`mecanum_hil.identify.lsq.levenberg_marquardt`, which needs no SciPy (its import
    costs more than such a fit). Everything else: SciPy's trust-region reflective method,
    whose handling of the kinks an effect's limit puts in the cost ``diagnose`` relies on.
    """
    if _smooth(calibration, live, pose):
        from .lsq import levenberg_marquardt

        @_stall_stopped
        def solve(problem, x0, lo, hi, max_nfev):
            size = problem.fun(x0).size

            def fun(x):
                # a step projected onto the bounds can land on A = B = 0 (no stable model):
                # an infinite cost, so the step is refused and the damping grows
                try:
                    return problem.fun(x)
                except FitError:
                    return np.full(size, np.inf)
            return levenberg_marquardt(fun, problem.jac, x0, lo, hi, max_nfev=max_nfev)
        return solve

    @_stall_stopped
    def solve(problem, x0, lo, hi, max_nfev):
        from scipy.optimize import least_squares

        # a trial step far out (a candidate's corner) overflows in the trust region's own
        # arithmetic, which refuses that step and shrinks the region: scipy's warning about
        # it is not the user's (it printed six lines on a diagnose of a campaign)
        with np.errstate(over="ignore", invalid="ignore"):
            return least_squares(problem.fun, x0, jac=problem.jac, bounds=(lo, hi),
                                 x_scale="jac", method="trf", max_nfev=max_nfev)
    return solve


def _stall_stopped(solve):
    """``solve`` that watches its problem and ends a stalled search at its best point."""
    @functools.wraps(solve)
    def run(problem, x0, lo, hi, max_nfev):
        problem.watch(x0)
        try:
            return solve(problem, x0, lo, hi, max_nfev)
        except _SearchStalledError as stop:
            return stop.solution
        finally:
            problem.unwatch()
    return run


def _restarted(problem, sol, lo, hi, max_nfev: int, solve):
    """``sol`` improved by fresh searches from where it stopped on its step test.

    Where a drive limit switches on, the cost is not smooth: the finite-difference Jacobian
    misleads the trust region, which shrinks until the step test (``xtol``, ``ftol``: status
    2, 3, 4) ends the search well before the minimum. A fresh trust region from there goes on;
    restart while that lowers the cost by ``RESTART_GAIN``. A restart that runs out of
    evaluations still counts when it is lower (it stops the restarts); one that fails is
    dropped, keeping the converged result.
    """
    for _ in range(MAX_RESTARTS):
        if sol.status not in (2, 3, 4):
            break
        try:
            again = solve(problem, sol.x, lo, hi, max_nfev)
        except (ValueError, np.linalg.LinAlgError):
            break
        if not (np.isfinite(again.cost) and again.cost < (1.0 - RESTART_GAIN) * sol.cost):
            break
        sol = again
    return sol


def fit(
    recordings: Sequence[Recording],
    robot: RobotProfile,
    method: str = "lsq",
    calibration: Calibration | None = None,
    *,
    sources: Sequence[str] | None = None,
    **grid_options,
) -> FitResult:
    """Estimate A, B, C from recordings (``mecanum-hil fit``).

    Parameters
    ----------
    recordings : sequence of Recording
        Recordings with commands and measured wheel speeds.
    robot : RobotProfile
        Geometry for the kinematics.
    method : {"lsq", "paper-grid"}
        Continuous least squares, or the paper's three-pass grid search.
    calibration : Calibration, optional
        Effects to keep fixed during the fit (default: none, the paper's linear model).
    sources : sequence of str, optional
        Names of the recordings for the provenance.
    **grid_options
        For ``paper-grid``: see :func:`mecanum_hil.identify.grid.paper_grid`.

    Returns
    -------
    FitResult
    """
    cal = calibration if calibration is not None else Calibration(source="<fit>")
    if method == "paper-grid":
        # the paper's grid simulates from rest; lsq starts a moving recording in steady state
        for i, rec in enumerate(recordings):
            _require_start_at_rest(rec, robot, _source(i, rec, sources))
    if method == "lsq":
        if grid_options:
            raise FitError(f"grid options {sorted(grid_options)} apply to --method paper-grid only")
        result = fit_parameters(recordings, cal, robot, sources=sources)
    elif method == "paper-grid":
        from .grid import paper_grid

        data = prepare(recordings, robot, sources)
        res = paper_grid(data, cal, robot, **grid_options)
        x = np.array([res.A, res.B, res.C])
        result = finish(data, cal, robot, list(_COEFFICIENTS), x, "paper-grid",
                        extra_warnings=res.warnings, info_extra=res.info)
    else:
        raise FitError(f"unknown method {method!r}; choose lsq or paper-grid")
    if not result.fit_percent > 0.0:
        raise FitError(
            f"the best model explains the data worse than their mean (fit "
            f"{result.fit_percent:.1f} %): no trustworthy coefficients (is there a transient, "
            "and do the commands belong to these wheel speeds?)")
    return result


def _require_start_at_rest(rec: Recording, robot: RobotProfile, src: str) -> None:
    """The model starts every recording from rest: refuse one that starts in motion."""
    wheels = np.asarray(rec.wheel_rpm, dtype=float)
    rows = np.flatnonzero(np.isfinite(wheels).any(axis=1))
    if rows.size == 0 or not np.isfinite(rec.commands).all():
        return  # reported by the engine's own checks
    first = np.nanmax(np.abs(wheels[rows[0]]))
    targets = command_to_wheels(rec.commands[:, 0], rec.commands[:, 1], rec.commands[:, 2],
                                robot.k)
    # a noisy sample at rest is not motion: 2 sigma of 1 rpm of encoder noise is 2 rpm
    from .regimes import noise_sd

    sigma = noise_sd(wheels[rows])
    if first > max(2.0, 0.05 * float(np.abs(targets).max()),
                   4.0 * sigma if np.isfinite(sigma) else 0.0):
        raise FitError(
            f"{src}: starts in motion (a wheel at {first:.1f} rpm at t_s={rec.t_s[rows[0]]:g}); "
            "the paper's grid search starts every recording from rest: use --method lsq "
            "(which starts it in steady state at the measured speeds) or trim the recording "
            "to begin at standstill")
