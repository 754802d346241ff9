"""The least-squares problem of a fit: residuals, their Jacobian, and the intervals.

:func:`residual_rows` simulates prepared recordings (:mod:`mecanum_hil.identify.prepared`) for
many calibrations in one batch and returns ``measured - model`` (wheel speeds [rpm], then pose
channels as wheel-rpm equivalents); :class:`Problem` turns that into the residuals and the
forward-difference Jacobian of a set of free parameters, as a solver asks for them;
:func:`intervals` gives the 95 % Wald intervals at the optimum and :func:`metrics` the fit's
measures. :func:`residuals` is the public per-recording residual of one calibration.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from .._jit import few_threads
from ..errors import ConfigError, FitError
from ..io.recording import Recording
from ..model.calibration import Calibration, Effects, coefficient_problem
from ..model.kinematics import command_to_wheels
from ..model.robot import RobotProfile
from ..model.simulate import simulate_batch, steady_state
from ..prediction import initial_state, initial_wheel_rpm, require_commands, start_pose
from .parameters import COEFFICIENTS, FD_FLOOR, NO_EFFECTS, effect_slot, effects_with, unbounded
from .prepared import Prepared
from .search import check_stall

#: Relative finite-difference step of a parameter (at least :data:`FD_FLOOR` times it).
FD_RELATIVE = 1e-6

#: Largest condition number of the column-scaled Jacobian for which intervals are trusted.
MAX_CONDITION = 1e8


def _simulate(p: Prepared, calibs: Sequence[Calibration], robot: RobotProfile, pose: bool):
    """Wheel speeds [rpm] and poses of one recording, shape (len(calibs), T, .)."""
    state = p.initial_states(calibs)
    with few_threads(len(calibs) * p.t_s.size * 4):
        traj = simulate_batch(p.commands, p.t_s, list(calibs), robot, initial_pose=p.pose0,
                              initial_state=state,
                              initial_command=p.commands[0] if p.start_rpm.any() else None,
                              **_outputs([p], pose))
    return traj.wheel_rpm, traj.pose


def _outputs(members: Sequence[Prepared], pose: bool) -> dict:
    """What a fit simulates of recordings run as one batch: with the pose, everything; else
    the wheels measured in any of them, and no pose (NaN; see :func:`simulate_batch`)."""
    if pose:
        return {}
    wheels = np.zeros(4, dtype=bool)
    for p in members:
        wheels |= p.wheel_measured
    return {"wheels": wheels, "pose": False}


def _simulate_all(data: Sequence[Prepared], calibs: Sequence[Calibration],
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


def _paper_rows(data: Sequence[Prepared], calibs: Sequence[Calibration],
               robot: RobotProfile) -> np.ndarray | None:
    """Wheel residual rows of the paper's model (every calibration without effects) through
    :mod:`mecanum_hil.model.linear`, when that costs less than loading numba; else None."""
    from .._jit import interpret
    from ..model.linear import step_lengths, wheel_speeds, work_units

    if any(c.effects != NO_EFFECTS for c in calibs):
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


def residual_rows(data: Sequence[Prepared], calibs: Sequence[Calibration], robot: RobotProfile,
                  pose_weight: float) -> np.ndarray:
    """Residual vectors ``measured - model``, one row per calibration (wheels, then poses)."""
    if not fits_pose(data, pose_weight):
        rows = _paper_rows(data, calibs, robot)
        if rows is not None:
            return rows
    parts = []
    fitted = _simulate_all(data, calibs, robot, fits_pose(data, pose_weight))
    for p, (wheels, pose) in zip(data, fitted, strict=True):
        parts.append(p.wheel_residuals(wheels))
        if pose_weight > 0 and p.pose_mask.any():
            d = p.pose[None] - pose
            d[..., 2] = (d[..., 2] + 180.0) % 360.0 - 180.0  # headings compare modulo a turn
            d *= pose_weight * p.pose_scale
            parts.append(d[:, p.pose_mask])
    return np.concatenate(parts, axis=1)


def fits_pose(data: Sequence[Prepared], pose_weight: float) -> bool:
    """Whether the residuals include pose channels (a weight, and a pose measured somewhere)."""
    return pose_weight > 0 and any(p.pose_mask.any() for p in data)


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


class Problem:
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
        self._coefficients = [(n, i) for i, n in enumerate(self.free) if n in COEFFICIENTS]
        self._effect_slots = [(i, *effect_slot(n)) for i, n in enumerate(self.free)
                              if n not in COEFFICIENTS]
        self._effects: dict[tuple[float, ...], Effects] = {}

    def watch(self, x0: np.ndarray) -> None:
        """Start watching a search from ``x0`` for a stall
        (:func:`~mecanum_hil.identify.search.check_stall`); a start already evaluated (a restart
        from where the last search ended) counts as the search's first evaluation."""
        self._trace, self._best = [], None
        if self._x is not None and np.array_equal(self._x, np.asarray(x0, dtype=float)):
            self._watched(self._x, self._r)

    def unwatch(self) -> None:
        """Stop watching for a stall."""
        self._trace = self._best = None

    def _watched(self, x: np.ndarray, r: np.ndarray) -> None:
        """Record an evaluation of a watched search; raise on a stall."""
        if self._trace is None:
            return
        cost = 0.5 * float(r @ r)
        if math.isfinite(cost) and (self._best is None or cost < self._best[0]):
            self._best = (cost, x.copy())
        self._trace.append(self._best[0] if self._best is not None else math.inf)
        check_stall(self._trace, self._best, len(self.free))

    def calibration_at(self, x) -> Calibration:
        """The calibration at point ``x``: :func:`with_parameters` of the free parameters."""
        values = np.asarray(x, dtype=float).tolist()
        if len(values) != len(self.free):
            raise ValueError(f"{len(values)} values for {len(self.free)} free parameters")
        key = tuple(values[i] for i, _, _ in self._effect_slots)
        effects = self._effects.get(key)
        if effects is None:
            effects = effects_with(self.calibration.effects, self._effect_slots, values)
            if len(self._effects) >= 64:
                self._effects.clear()
            self._effects[key] = effects
        coefficients = {n: values[i] for n, i in self._coefficients}
        try:
            return replace(self.calibration, **coefficients, effects=effects, ci95={}, info={})
        except ConfigError:
            # said as the point's problem (the caller says it is the fit's), not the
            # calibration's in memory
            A, B, C = (coefficients.get(n, getattr(self.calibration, n)) for n in COEFFICIENTS)
            problem = coefficient_problem(A, B, C)
            if problem is None:
                raise
            raise ConfigError(problem) from None

    def steps(self, x: np.ndarray) -> np.ndarray:
        """Forward-difference steps at ``x``, in the parameters' units (negative on an upper
        bound)."""
        floor = np.array([FD_FLOOR.get(n, 1.0) for n in self.free])
        h = FD_RELATIVE * np.maximum(np.abs(x), floor)
        # step into the feasible region (a parameter on its bound is differentiated one-sidedly)
        return np.where(x + h > self.upper, -h, h)

    def _rows(self, points: Sequence[np.ndarray]) -> np.ndarray:
        try:
            calibs = [self.calibration_at(pt) for pt in points]
        except ConfigError as err:
            raise FitError(f"the fit reached an invalid model: {err}") from err
        return residual_rows(self.data, calibs, self.robot, self.pose_weight)

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
        """Residuals at ``x`` (wheels [rpm], then pose channels as wheel-rpm equivalents)."""
        if self._x is None or not np.array_equal(self._x, x):
            self.evaluate(x, jacobian=not self.lazy)
        return self._r

    def jac(self, x) -> np.ndarray:
        """Jacobian of :meth:`fun` at ``x``, shape (residuals, free parameters)."""
        if self._x is None or not np.array_equal(self._x, x):
            self.evaluate(x)
        elif self._J is None:
            h = self.steps(self._x)
            self._J = self._jacobian(self._rows(self._perturbed(self._x, h)), h)
        return self._J


def sse_of(data: Sequence[Prepared], calibs: Sequence[Calibration],
           robot: RobotProfile) -> np.ndarray:
    """Sum of squared wheel-speed errors [rpm^2] of each calibration (inf where not finite)."""
    rows = residual_rows(data, calibs, robot, 0.0)
    with np.errstate(over="ignore", invalid="ignore"):
        s = np.einsum("ij,ij->i", rows, rows)
    return np.where(np.isfinite(s), s, np.inf)


def intervals(J: np.ndarray, r_wheel_and_pose: np.ndarray, x: np.ndarray, free: Sequence[str],
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


def metrics(data, calibration, robot, rows=None) -> tuple[float, float, float, int, list[float]]:
    """The fit's measures on the wheel speeds: SSE [rpm^2], RMSE [rpm], fit [%], the number of
    measured samples, and the fit [%] per recording (NaN for one without spread)."""
    # rows: the wheel residuals of ``calibration`` when the caller has them
    if rows is None:
        rows = residual_rows(data, [calibration], robot, 0.0)[0]
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
