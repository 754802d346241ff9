"""Step 4, selection: rounds of candidates, the best one kept while it helps held out."""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ..._jit import kernel_threads, load_compiled
from ...errors import ConfigError, DiagnoseError, FitError, SessionTerminated
from ...io.recording import Recording
from ...model.calibration import EFFECTS, Calibration, exchange_drive_lag
from ...model.robot import RobotProfile
from ...prediction import require_commands
from ..fit import (
    bounded_interval,
    calibration_intervals,
    fit_parameters,
    one_blas_thread,
    parameter_value,
    with_parameters,
)
from ..regimes import Localisation, localise, pooled_noise_sd
from .candidates import (
    CANDIDATES,
    GRID_FITTED,
    CandidateScore,
    _effect_values,
    _Fitted,
    candidate_pool,
    compatible,
    effect_parameters,
    fit_candidate,
)
from .heldout import HeldOut, heldout_score, in_sample_ms
from .helper import Helper, helpers_for, release, warm_up
from .localise import (
    Finding,
    ResidualCheck,
    ResidualShape,
    _Evaluator,
    _predictions,
    _rmse_per_recording,
    creeping_levels,
    initial_pose_at_rest,
    proportional_only,
    residual_check,
    residual_shape,
    typical_step_s,
)
from .reference import explained_share, fit_reference, reference_comparison

#: A candidate must remove at least this fraction of the in-sample excess over the noise floor
#: and lower the held-out score (a ceiling that one recording alone reaches may explain only a
#: small part held out: it is kept as long as it helps)...
MIN_EXPLAINED = 0.15
#: ... and at least this fraction of the held-out score itself.
MIN_RELATIVE = 0.05
#: Smallest in-sample excess over the noise floor, as a share of the in-sample score, for which
#: a candidate's in-sample share is computed (below it there is nothing to explain: 0).
MIN_EXCESS = 0.02
#: ... and lower the in-sample mean square itself by at least this fraction: below it the change
#: is smaller than the uncertainty of the noise estimate the scores are divided by (about
#: sqrt(2 / N) of the variance: 1.3 % for 12 000 samples), and invisible in any plot (a wheel
#: gain of 1.00005 after a ceiling had brought a staircase to its noise floor).
MIN_DROP = 0.01
#: Rounds in which a longer search, not the winning effect, earned the gain (the model is then
#: refitted and the round repeated) before the selection stops trying.
MAX_SEARCHES_ON = 2
#: Held-out score (mean square / sigma^2) at or below which nothing significant is left.
NOISE_FLOOR_SCORE = 1.1
#: Remaining residual is "structured" above this RMSE / noise ratio ...
_COEFFICIENTS = ("A", "B", "C")

@dataclass(frozen=True)
class DiagnoseStep:
    """One effect added to the model.

    Attributes
    ----------
    effect : str
    parameters : dict
        As in :class:`~mecanum_hil.model.Effects` (lists for ``gains`` and ``efficiency``).
    ci95 : dict of str to (float, float)
        95 % intervals of the effect's parameters (engine names such as ``gains[1]``), clipped
        to their admissible ranges; ``(nan, nan)`` where the data cannot bound the parameter
        (:func:`honest_interval`).
    rmse_before, rmse_after : float
        Wheel RMSE over all samples, before and after (in sample) [rpm].
    rmse_before_per_recording, rmse_after_per_recording : tuple of float
        The same per recording [rpm].
    pose_rmse_before, pose_rmse_after : tuple of 3 float
        Pose residual RMS over all recordings: X [m], Y [m], heading [deg] (NaN without pose).
    calibration_before, calibration_after : Calibration
    candidates : tuple of CandidateScore
        Every candidate of the round.
    warnings : tuple of str
        The engine's warnings for the accepted fit.
    explained : float
        Fraction of its round's held-out excess over the noise floor it removed [-].
    """

    effect: str
    parameters: dict[str, Any]
    ci95: dict[str, tuple[float, float]]
    rmse_before: float
    rmse_after: float
    rmse_before_per_recording: tuple[float, ...]
    rmse_after_per_recording: tuple[float, ...]
    pose_rmse_before: tuple[float, ...]
    pose_rmse_after: tuple[float, ...]
    calibration_before: Calibration
    calibration_after: Calibration
    candidates: tuple[CandidateScore, ...]
    warnings: tuple[str, ...] = ()
    explained: float = math.nan

    @property
    def equivalent(self) -> dict[str, float] | None:
        """For ``drive_lag``: the other model that gives exactly the same wheel speeds, the lag
        and the motor's time constant exchanged (:func:`~mecanum_hil.model.calibration.
        exchange_drive_lag`): ``drive_lag_s`` [s], ``A``, ``B`` [1/s], ``C`` [1/s^2]. Wheel
        speeds cannot tell the two apart. ``None`` for other effects, without a twin, or when
        the twin is degenerate (:attr:`equivalent_problem` says why)."""
        return self._exchange()[0]

    @property
    def equivalent_problem(self) -> str | None:
        """Why the drive lag's exchanged twin is degenerate (``B`` near zero makes its lag and
        its rescaled ``A`` and ``C`` absurd); None when it is a valid model or there is none."""
        return self._exchange()[1]

    def _exchange(self) -> tuple[dict[str, float] | None, str | None]:
        if self.effect != "drive_lag":
            return None, None
        try:
            twin = exchange_drive_lag(self.calibration_after,
                                      "the drive_lag exchange of the fitted model")
        except ConfigError as err:
            return None, str(err)
        if twin is None:
            return None, None
        return {"drive_lag_s": twin.effects.drive_lag_s, "A": twin.A, "B": twin.B,
                "C": twin.C}, None


@dataclass(frozen=True)
class Refit:
    """A round whose winner added nothing a longer search did not (:func:`search_credit`).

    Attributes
    ----------
    candidate : str
        The effect whose candidate fit found the better model.
    rmse_before, rmse_after : float
        Wheel RMSE of the model before and after the refit [rpm].
    """

    candidate: str
    rmse_before: float
    rmse_after: float


@dataclass(frozen=True)
class Diagnosis:
    """What ``diagnose`` found.

    Attributes
    ----------
    steps : tuple of DiagnoseStep
        Effects added, in order.
    unexplained : bool
        Structured residual remains that no candidate explains.
    rmse_initial, rmse_baseline, rmse_final : float
        Wheel RMSE [rpm] of the calibration as given, after refitting its own parameters, and
        of the final model.
    noise_rpm : float
        Wheel noise level [rpm].
    initial, baseline, calibration : Calibration
        The given, the refitted and the final (extended) calibration.
    localisation_initial, localisation_final : Localisation
    check : ResidualCheck
        Of the final residual.
    rejected : tuple of CandidateScore
        The candidates of the last round, none of which qualified.
    names : tuple of str
        Recording names.
    rmse_reference : float
        Wheel RMSE of the generic reference model (:mod:`.reference`) [rpm]; NaN when it
        could not be fitted.
    shape : ResidualShape or None
        Where the final wheel residual sits and whether it rings.
    pose_rmse_initial, pose_rmse_final : tuple of float
        Position [m] and heading [deg] RMSE of the baseline and the final model.
    """

    steps: tuple[DiagnoseStep, ...]
    unexplained: bool
    rmse_initial: float
    rmse_baseline: float
    rmse_final: float
    noise_rpm: float
    initial: Calibration
    baseline: Calibration
    calibration: Calibration
    localisation_initial: Localisation
    localisation_final: Localisation
    check: ResidualCheck
    rejected: tuple[CandidateScore, ...] = ()
    names: tuple[str, ...] = field(default=())
    rmse_reference: float = math.nan
    shape: ResidualShape | None = None
    pose_rmse_initial: tuple[float, float] = (math.nan, math.nan)
    pose_rmse_final: tuple[float, float] = (math.nan, math.nan)
    #: Named properties of the final model that add nothing to it (``proportional_only``).
    findings: tuple[Finding, ...] = ()
    #: Rounds that named nothing because a longer search, not the winning candidate's effect,
    #: earned the gain (:func:`search_credit`): the model was refitted instead. In the report
    #: and the log; not in the JSON, whose keys are pinned (its ``rmse_final`` includes them).
    refits: tuple[Refit, ...] = ()

    @property
    def explained_share(self) -> float:
        """Share of the explainable gap (baseline -> reference model) the named effects close
        [-] (mean squares)."""
        return explained_share(self.rmse_baseline, self.rmse_final, self.rmse_reference)

    def share(self, step: DiagnoseStep) -> float:
        """Share of the gap over the noise floor (baseline mean square minus noise^2) that
        ``step`` removed [-]."""
        gap = self.rmse_baseline ** 2 - self.noise_rpm ** 2
        return (step.rmse_before ** 2 - step.rmse_after ** 2) / gap if gap > 0 else math.nan

    @property
    def effects(self) -> list[str]:
        """Names of the effects added, then of the findings (``proportional_only``)."""
        return [s.effect for s in self.steps] + [f.effect for f in self.findings]

    def to_json(self) -> dict[str, Any]:
        """The ``--json`` document (its keys are listed in ``docs/diagnose.md``)."""
        def num(v: float):
            return float(v) if math.isfinite(v) else None

        def pose(v) -> dict[str, Any]:
            return {"position_m": num(v[0]), "heading_deg": num(v[1])}

        def step(s: DiagnoseStep) -> dict[str, Any]:
            out = {"effect": s.effect, "parameters": _json_parameters(s.parameters),
                   "rmse_before": num(s.rmse_before), "rmse_after": num(s.rmse_after),
                   "share": num(self.share(s)),
                   "pose_rmse_before": pose(_pose_pair(s.pose_rmse_before)),
                   "pose_rmse_after": pose(_pose_pair(s.pose_rmse_after))}
            if s.equivalent is not None:
                out["equivalent"] = s.equivalent
            return out

        return {
            "effects": [step(s) for s in self.steps] + [
                {"effect": f.effect, "parameters": {k: num(v) for k, v in f.parameters.items()},
                 "rmse_before": num(self.rmse_final), "rmse_after": num(self.rmse_final),
                 "share": None,
                 "pose_rmse_before": pose(self.pose_rmse_final),
                 "pose_rmse_after": pose(self.pose_rmse_final)} for f in self.findings],
            "unexplained": bool(self.unexplained),
            "rmse_initial": num(self.rmse_initial),
            "rmse_final": num(self.rmse_final),
            "rmse_baseline": num(self.rmse_baseline),
            "noise_rpm": num(self.noise_rpm),
            "rmse_reference": num(self.rmse_reference),
            "explained_share": num(self.explained_share),
            "pose_rmse_before": pose(self.pose_rmse_initial),
            "pose_rmse_after": pose(self.pose_rmse_final),
            "residual": self.shape.to_json() if self.shape is not None else None,
        }


def _json_parameters(parameters: dict[str, Any]) -> dict[str, Any]:
    """An effect's parameters for JSON: a number that is not finite as None (lists kept)."""
    def num(v):
        return float(v) if math.isfinite(v) else None

    return {k: [num(x) for x in v] if isinstance(v, list | tuple) else num(v)
            for k, v in parameters.items()}


def _pose_pair(p: Sequence[float]) -> tuple[float, float]:
    """``(X [m], Y [m], heading [deg])`` RMSE -> ``(position [m], heading [deg])``."""
    return (math.hypot(p[0], p[1]) if all(map(math.isfinite, p[:2])) else math.nan, p[2])



def _score(h: HeldOut, noise2: float) -> float:
    return h.heldout_ms / noise2


def search_credit(ev, fitted: Calibration, effect: str, free: Sequence[str],
                  sources: Sequence[str], scale2: float, f0: float, f1: float):
    """The model without ``effect``, refitted from the candidate's fit, when it does as well.

    A candidate is fitted with A, B, C (and the effects already named) free; where the cost is
    not smooth (a drive limit switching on) the search for the current model can stop short,
    and a candidate's longer search then finds a better model whatever the effect (a staircase
    to its ceiling: wheel gains of 1.00005 took the RMSE from 1.22 to 0.76 rpm). Remove the
    effect from the candidate's fit and refit the rest from there: if that loses less than
    ``MIN_DROP`` of the in-sample score ``f0`` against the candidate's own ``f1`` (in-sample
    mean squares over ``scale2``), the effect earned nothing.

    Returns
    -------
    (Calibration, dict) or None
        The refitted model and its 95 % intervals; None when the effect earned its gain.
    """
    plain = replace(fitted, effects=fitted.effects.without(effect))
    try:
        res = fit_parameters(ev.recs, plain, ev.robot, list(free),
                             x0={n: parameter_value(plain, n) for n in free}, sources=sources)
    except (FitError, ConfigError):
        return None
    plain = with_parameters(plain, res.parameters)
    loss = in_sample_ms(ev, plain, "wheel") / scale2 - f1
    return (plain, dict(res.ci95)) if loss < MIN_DROP * f0 else None


def diagnose(
    recordings: Sequence[Recording],
    calibration: Calibration,
    robot: RobotProfile | None = None,
    *,
    names: Sequence[str] | None = None,
    candidates: Sequence[str] = CANDIDATES,
    max_rounds: int = 4,
    echo: Callable[[str], None] | None = None,
    jobs: int | None = None,
) -> Diagnosis:
    """Find and add the effects the model lacks (method in the module docstring).

    Parameters
    ----------
    recordings : sequence of Recording
        Commands and measured wheel speeds (pose where measured); one is enough: models are
        compared on data they were not fitted to, whole recordings when there are several,
        time blocks inside the recordings otherwise.
    calibration : Calibration
        The model as the user has it (e.g. written by ``fit``); effects it already has are kept
        and refitted, the others are candidates.
    robot : RobotProfile, optional
        Geometry (default: the paper's robot).
    names : sequence of str, optional
        Recording names for the report.
    candidates : sequence of str
        Effects of the library to consider (default: all of :data:`CANDIDATES`).
    max_rounds : int
        Most effects to add.
    echo : callable, optional
        Progress lines (``print``).
    jobs : int, optional
        Processes that fit a round's candidates, this one included (:mod:`.helper`): 1 fits
        them all here; default: 2 where most of a second core is idle (1-minute load
        average, or the cores' use now: :func:`mecanum_hil._cores.idle_cores`), else 1. The
        diagnosis is the same either way.

    Returns
    -------
    Diagnosis

    Raises
    ------
    DiagnoseError
        Fewer than two recordings, no measured wheel speeds, or an unknown candidate.
    """
    # numba's kernels from the start, in this process and the helpers (warm_up): a search
    # begun in the interpreter (equal to rounding) can end elsewhere, and a recording's
    # diagnosis must not depend on what this process did before; meanwhile the helpers are
    # chosen (and started, to go on beside this one)
    helpers = _helpers_beside(jobs, lambda: load_compiled("mecanum_hil.model._kernels"))
    interrupted = False
    try:
        # many small products of tall matrices (identify/fit.py); beside a helper, a process
        # per core: a kernel's second thread would wait for the helper's core (the results
        # are the same: the robots of a batch are independent)
        with one_blas_thread(), (kernel_threads(1) if helpers else contextlib.nullcontext()):
            return _diagnose(recordings, calibration, robot, names, candidates, max_rounds,
                             echo, tuple(helpers))
    except (KeyboardInterrupt, SessionTerminated):
        interrupted = True
        raise
    finally:
        release(helpers, interrupted)


def _helpers_beside(jobs: int | None, work: Callable[[], None]) -> list[Helper]:
    """:func:`.helper.helpers_for` ``(jobs, warm_up)`` on a thread of its own while this one
    does ``work``: choosing may read how busy the cores are now, over a fifth of a second of
    waiting (:func:`mecanum_hil._cores.busy_cores_now`), which ``work`` (loading numba's
    kernels) fills. Returns the helpers; when ``work`` or the wait for the choice raises, those
    started are released (:func:`.helper.release`: all killed after Ctrl-C or SIGTERM, as
    after an interrupted diagnosis)."""
    if jobs == 1:
        work()
        return []
    chosen: list = []

    def choose() -> None:
        try:
            chosen.append(helpers_for(jobs, warm_up))
        except BaseException as err:  # handed to the caller's thread
            chosen.append(err)

    thread = threading.Thread(target=choose, name="diagnose-helpers", daemon=True)
    thread.start()
    try:
        work()
        thread.join()
    except BaseException as err:
        # the choice goes on (a helper may be starting): wait for it, then end what it started
        thread.join()
        if chosen and isinstance(chosen[0], list):
            release(chosen[0], isinstance(err, (KeyboardInterrupt, SessionTerminated)))
        raise
    if isinstance(chosen[0], BaseException):
        raise chosen[0]
    return chosen[0]


@dataclass(frozen=True)
class _Context:
    """What every step of :func:`_diagnose` reads and none changes.

    Attributes
    ----------
    ev : _Evaluator
        The model on every recording (frozen starts dropped).
    recs : list of Recording
        The recordings, initial pose at rest, as the engine's fits take them.
    robot : RobotProfile
    names : tuple of str
        Recording names.
    say : callable
        Progress lines.
    helpers : tuple of Helper
        Processes that fit candidates beside this one (:mod:`.helper`; none: all here).
    cost_s : dict of str to float
        Seconds each candidate's job took last (the order in which jobs are handed out).
    """

    ev: _Evaluator
    recs: list[Recording]
    robot: RobotProfile
    names: tuple[str, ...]
    say: Callable[[str], None]
    helpers: tuple[Helper, ...] = ()
    cost_s: dict[str, float] = field(default_factory=dict)


@dataclass
class _Model:
    """The model as the rounds leave it and what they found; each round updates it.

    Attributes
    ----------
    current : Calibration
        The model so far.
    free : list of str
        Its free parameters: A, B, C and those of its effects.
    ci95 : dict of str to (float, float)
        95 % intervals of the parameters, from the fit that last moved each.
    steps : list of DiagnoseStep
        Effects named, in order.
    refits : list of Refit
        Rounds whose gain a longer search earned (:func:`search_credit`).
    rejected : tuple of CandidateScore
        The candidates of the last round when none qualified.
    carried : (Calibration, (str, tuple of str), HeldOut) or None
        The last winner's held-out score with its model and (channel, moving parameters):
        the next round's starting score when neither changed.
    """

    current: Calibration
    free: list[str]
    ci95: dict[str, tuple[float, float]]
    steps: list[DiagnoseStep] = field(default_factory=list)
    refits: list[Refit] = field(default_factory=list)
    rejected: tuple[CandidateScore, ...] = ()
    carried: tuple[Calibration, tuple, HeldOut] | None = None


def _diagnose(recordings, calibration, robot, names, candidates, max_rounds, echo,
              helpers=()) -> Diagnosis:
    """The method: localise the model as given, refit its own parameters (the baseline), add
    candidates round by round while one qualifies, then describe what remains."""
    say = echo or (lambda _msg: None)
    rob = robot or RobotProfile()
    candidates = candidate_pool(candidates)
    recs, names = _checked_recordings(recordings, names)
    ctx = _Context(_Evaluator(recs, rob), recs, rob, names, say, helpers)
    # the reference model does not depend on the model: a helper fits it while this process
    # starts the rounds (it is the helper's first job, after its warm-up)
    reference = helpers[0].submit(fit_reference, recs, rob) if helpers else None
    loc0 = _localise_given(ctx, calibration)
    accepted = [e for e in EFFECTS if e in calibration.effects.active()]
    baseline, free, ci95 = _refit_own_parameters(ctx, calibration, accepted)
    rmse_base = _rmse_per_recording(ctx.ev, baseline)[0]
    say(f"refit of {', '.join(free)}: wheel RMSE {rmse_base:.3f} rpm")
    noise = _noise_level(ctx.ev, baseline)
    model = _Model(baseline, [n for n in free if n not in GRID_FITTED], dict(ci95))
    _candidate_rounds(ctx, model, candidates, accepted, noise, max_rounds)
    return _conclude(ctx, model, calibration, baseline, loc0, rmse_base, noise, reference)


def _checked_recordings(recordings, names) -> tuple[list[Recording], tuple[str, ...]]:
    """Check the inputs; return the recordings (initial pose at rest) and their names."""
    recs = [initial_pose_at_rest(r) for r in recordings]
    if not recs:
        raise DiagnoseError("no recordings given")
    names = tuple(names) if names is not None else tuple(
        str(r.metadata.get("profile", f"recording {i + 1}")) for i, r in enumerate(recs))
    for rec, name in zip(recs, names, strict=True):
        require_commands(rec, name)
    if not any(np.isfinite(r.wheel_rpm).any() for r in recs):
        raise DiagnoseError("no measured wheel speeds in the recordings: diagnose compares the "
                            "model's wheel speeds with measured ones")
    return recs, names


def _localise_given(ctx: _Context, initial: Calibration) -> Localisation:
    """Where the model as given fails (logged)."""
    loc0 = localise(ctx.recs, _predictions(ctx.ev, initial), ctx.robot, ctx.names)
    ctx.say(f"initial model: wheel RMSE {loc0.rmse_rpm:.3f} rpm, noise about "
            f"{loc0.noise_rpm:.3f} rpm")
    for line in loc0.lines():
        ctx.say("  " + line)
    return loc0


def _refit_own_parameters(ctx: _Context, initial: Calibration, accepted: Sequence[str]
                          ) -> tuple[Calibration, list[str], dict[str, tuple[float, float]]]:
    """The baseline: A, B, C and the parameters of the effects the model has (``accepted``)
    refitted; returns it, the parameters freed and their 95 % intervals."""
    # an infinite parameter (a fast-decay drive without droop) stays as it is
    free = list(_COEFFICIENTS) + [p for e in accepted for p in effect_parameters(e)
                                  if effect_parameters(e)[0] not in GRID_FITTED
                                  and math.isfinite(parameter_value(initial, p))]
    try:
        res = fit_parameters(ctx.recs, initial, ctx.robot, free,
                             x0={n: parameter_value(initial, n) for n in free},
                             pose_weight=1.0 if "slip" in accepted else 0.0, sources=ctx.names)
    except FitError as err:
        raise DiagnoseError(f"cannot refit the model on these recordings: {err}") from err
    return with_parameters(initial, res.parameters), free, res.ci95


def _noise_level(ev: _Evaluator, baseline: Calibration) -> float:
    """Wheel noise level [rpm], pooled from the baseline's residuals."""
    noise = pooled_noise_sd(ev.wheel_residuals(ev.predict([baseline])[0]).values())
    if not noise > 0:
        raise DiagnoseError("cannot estimate the measurement noise (constant wheel speeds?)")
    return noise


def _moving(free: Sequence[str], channel: str) -> Sequence[str]:
    """The parameters a channel moves: the wheels pin A, B, C; on the pose channels only slip's
    parameters move."""
    return free if channel == "wheel" else [n for n in free if n.startswith("efficiency")]


def _candidate_rounds(ctx: _Context, model: _Model, candidates: Sequence[str],
                      accepted: Sequence[str], noise: float, max_rounds: int) -> None:
    """Rounds of candidates not yet in the model: first on the wheel speeds (scores in units
    of the noise variance), then slip on the pose (in units of the pose noise); updates
    ``model``."""
    wanted = [c for c in candidates if c != "slip" and c not in accepted]
    wheel_cands = compatible(wanted, accepted)
    if len(wheel_cands) < len(wanted):
        ctx.say(f"not tried: {', '.join(c for c in wanted if c not in wheel_cands)} (not in one "
                f"model with {', '.join(accepted)}, which the model has)")
    pose_cands = [c for c in candidates if c == "slip" and c not in accepted]
    for channel, pool in (("wheel", wheel_cands), ("pose", pose_cands)):
        if channel == "pose":
            if not pool or not ctx.ev.has_pose() or not ctx.ev.set_pose_noise(model.current):
                continue
            scale2 = 1.0
        else:
            scale2 = noise * noise
        _rounds_on_channel(ctx, model, channel, pool, noise, scale2, max_rounds)


def _rounds_on_channel(ctx: _Context, model: _Model, channel: str, pool: list[str],
                       noise: float, scale2: float, max_rounds: int) -> None:
    """Rounds on one channel until the residual is at the noise floor, no candidate qualifies,
    the pool is empty or ``max_rounds`` effects are named; updates ``model``."""
    while pool and len(model.steps) < max_rounds:
        h0, s0 = _score_current(ctx, model, channel, scale2)
        ctx.say(f"round {len(model.steps) + 1} ({channel}): held-out score {s0:.3f} "
                "(mean square / noise^2; 1 = noise floor)")
        if s0 <= NOISE_FLOOR_SCORE:
            ctx.say("  the residual is at the noise floor: nothing significant is left")
            model.rejected = ()
            return
        f0 = h0.fit_ms / scale2
        if not f0 - 1.0 > MIN_EXCESS * f0:
            # a candidate must remove MIN_EXPLAINED of the in-sample excess, and there is
            # none: no candidate can qualify, so none is fitted
            ctx.say(f"  in sample the residual is at the noise floor (score {f0:.3f}): no "
                    "candidate can explain a significant part")
            model.rejected = ()
            return
        first = [c for c in pool if FOLLOW_UP.get(c) not in pool]
        scores, fits, held = _score_candidates(ctx, model, first, channel, noise, scale2, s0,
                                               f0)
        later = [c for c in pool if c not in first and _shows(scores, FOLLOW_UP[c])]
        if later:
            more = _score_candidates(ctx, model, later, channel, noise, scale2, s0, f0)
            scores, fits, held = scores + more[0], {**fits, **more[1]}, {**held, **more[2]}
        ok = _qualifying(scores, f0)
        if not ok:
            model.rejected = tuple(scores)
            ctx.say("  no candidate explains a significant part of the gap")
            return
        win = max(ok, key=lambda s: s.relative)
        if channel == "wheel" and _search_earned_gain(ctx, model, win, fits[win.effect],
                                                      scale2, f0):
            continue
        _add_winner(ctx, model, channel, win, fits[win.effect], held[win.effect], scores)
        pool = compatible([c for c in pool if c != win.effect], [win.effect])


#: Candidates tried only in a round where another's fit changes the model at all: a drive
#: output clamped without anti-windup differs from one with it only where the clamp holds,
#: so ``windup`` is fitted where the fit of ``saturation`` finds a clamp that binds (lowers
#: the in-sample error at all). Trying it in every round would cost every diagnosis a
#: candidate as dear as ``saturation``.
FOLLOW_UP: dict[str, str] = {"windup": "saturation"}


def _shows(scores: Sequence[CandidateScore], effect: str) -> bool:
    """Whether ``effect``'s candidate lowers the in-sample error at all."""
    return any(s.effect == effect and s.in_sample > 0.0 for s in scores)


def _score_current(ctx: _Context, model: _Model, channel: str, scale2: float
                   ) -> tuple[HeldOut, float]:
    """The round's starting point: the model so far scored held out, and its score over
    ``scale2`` (after resuming a search that stopped short, :func:`_resume_search`)."""
    moving = _moving(model.free, channel)
    # the last winner's own score is this model's (same calibration, parameters, channel)
    carried = model.carried
    h0 = carried[2] if carried and carried[0] is model.current and carried[1] == (
        channel, tuple(moving)) else heldout_score(ctx.ev, model.current, moving, channel)
    s0 = _score(h0, scale2)
    if (model.steps and channel == "wheel" and s0 > NOISE_FLOOR_SCORE
            and _resume_search(ctx, model)):
        h0 = heldout_score(ctx.ev, model.current, moving, channel)
        s0 = _score(h0, scale2)
    return h0, s0


def _resume_search(ctx: _Context, model: _Model) -> bool:
    """Refit the model just extended from where its fit stopped; True when that moved it.

    So a candidate of this round gets no credit for a search that merely went on further (the
    cost is not smooth where a drive limit switches on, so a search may stop early; restart it
    while it still gains 1 %, as a candidate's two stages would).
    """
    start = model.current
    for _ in range(3):
        try:
            more = fit_parameters(
                ctx.recs, model.current, ctx.robot, model.free,
                x0={n: parameter_value(model.current, n) for n in model.free},
                sources=ctx.names)
        except (FitError, ConfigError):
            break
        sse_now = _rmse_per_recording(ctx.ev, model.current)[0] ** 2 * more.n_samples
        if not more.sse < sse_now:
            break
        model.current = with_parameters(model.current, more.parameters)
        model.ci95 = {**model.ci95, **more.ci95}
        if more.sse > 0.99 * sse_now:
            break
    return model.current is not start


def _score_candidates(ctx: _Context, model: _Model, pool: Sequence[str], channel: str,
                      noise: float, scale2: float, s0: float, f0: float
                      ) -> tuple[list[CandidateScore], dict[str, _Fitted], dict[str, HeldOut]]:
    """Fit and score every candidate of the round; returns the scores, the fits and the
    held-out scores of those scored held out, by effect.

    The candidates are independent jobs: where :mod:`.helper` processes are ready, each takes
    the costliest job left (by the time each took last round) as soon as it is idle, while this
    process works through the rest; the lines are said in the pool's order, and the results
    are the same either way."""
    jobs = _CandidateJobs(ctx, model, pool, (channel, noise, scale2, s0, f0))
    for h in ctx.helpers:
        # a helper still busy with another job (the reference model) is fed when it answers
        for fut in h.pending():
            fut.add_done_callback(lambda f, h=h: jobs.fed_on(f, h))
    done = jobs.done
    said = 0
    while True:
        for h in ctx.helpers:
            jobs.feed(h)
        with jobs.lock:
            if not (jobs.order or jobs.away):
                break
            effect = jobs.order.pop(0) if jobs.order else None
        if effect is not None:
            jobs.run_here(effect)
        jobs.collect(block=not jobs.order)
        while said < len(pool) and pool[said] in done:
            ctx.say(done[pool[said]][3])
            said += 1
    scores = [done[e][0] for e in pool]
    fits = {e: done[e][1] for e in pool if done[e][1] is not None}
    held = {e: done[e][2] for e in pool if done[e][2] is not None}
    return scores, fits, held


class _CandidateJobs:
    """The candidate jobs of one round of :func:`_score_candidates`: those left (``order``,
    costliest first), those with a helper (``away``: future, helper, time sent [s]) and the
    results (``done``: score, fit, held-out score, line, time taken [s]), by effect.

    ``order`` and ``away`` are shared with the helpers' reader threads (:meth:`feed`), under
    ``lock``.
    """

    def __init__(self, ctx: _Context, model: _Model, pool: Sequence[str], rest: tuple):
        self.ctx = ctx
        self.model = model
        self.rest = rest  # (channel, noise, scale2, s0, f0)
        self.order = sorted(pool, key=lambda e: -self.expected_s(e))
        self.done: dict[str, tuple[CandidateScore, _Fitted | None, HeldOut | None, str,
                                   float]] = {}
        self.away: dict[str, tuple[Future, Helper, float]] = {}
        self.lock = threading.Lock()

    def expected_s(self, effect: str) -> float:
        """What ``effect``'s job is expected to take [s]: what it took last round, or a
        prior."""
        return self.ctx.cost_s.get(effect, _COST_PRIOR.get(effect, 0.0))

    def args(self, effect: str) -> tuple:
        """The arguments of :func:`_timed_candidate` for ``effect``."""
        return (self.ctx.ev, effect, self.model.current, tuple(self.model.free),
                self.ctx.names, *self.rest)

    def run_here(self, effect: str) -> None:
        """Run ``effect``'s job in this process."""
        self.done[effect] = _timed_candidate(*self.args(effect))
        self.ctx.cost_s[effect] = self.done[effect][4]

    def feed(self, h: Helper) -> None:
        """Hand ``h`` the costliest job left if it is idle; called again (from its reader
        thread) when it answers, so a helper never waits for this process to end a job of
        its own before it gets the next (a third of a second a round, measured)."""
        with self.lock:
            if not (self.order and h.idle()):
                return
            effect = self.order.pop(0)
            fut = h.submit(_timed_candidate, *self.args(effect))
            self.away[effect] = (fut, h, time.perf_counter())
        fut.add_done_callback(lambda f: self.fed_on(f, h))

    def fed_on(self, f: Future, h: Helper) -> None:
        """Feed ``h`` again once its job ``f`` is answered."""
        # an answer, not a failure: a helper fails its jobs while it holds its own lock (stop)
        if not f.cancelled() and f.exception() is None:
            self.feed(h)

    def collect(self, block: bool) -> None:
        """Take the helpers' answers (waiting for each when ``block``); a job that fails or is
        late runs here instead."""
        with self.lock:
            jobs = list(self.away.items())
        for effect, (fut, h, sent) in jobs:
            if not (block or fut.done()):
                continue
            late = sent + HELPER_LATE_FACTOR * self.expected_s(effect) + HELPER_LATE_S
            result = None
            try:
                result = fut.result(timeout=max(0.0, late - time.perf_counter()))
            except TimeoutError:
                pass  # late: the job runs here; the helper gets no job until it answers
            except Exception as err:  # it failed (helper.py): not used again
                h.stop(err)
            with self.lock:
                del self.away[effect]
            self.done[effect] = result or _timed_candidate(*self.args(effect))
            self.ctx.cost_s[effect] = self.done[effect][4]


#: A helper's job is late (and is run here instead) once the diagnosing process has nothing
#: else to do and the job has taken this many times what it took last round ...
HELPER_LATE_FACTOR = 3.0
#: ... plus this many seconds [s]: a helper that stalls costs a bounded wait, never a hang.
HELPER_LATE_S = 1.0

#: Seconds each candidate took on ``controllerDelayImpact1ms`` (docs/benchmarks/diagnose.md,
#: per round): the order of the first round's jobs, costliest first, before any is timed.
_COST_PRIOR = {"saturation": 1.0, "windup": 1.0, "fast_decay": 0.9, "controller_period": 0.8,
               "drive_lag": 0.5, "rate_limit": 0.25, "braking_limit": 0.25, "breakaway": 0.2,
               "dead_time": 0.1}


def _timed_candidate(ev: _Evaluator, effect: str, current: Calibration, free: Sequence[str],
                     names: Sequence[str], channel: str, noise: float, scale2: float,
                     s0: float, f0: float
                     ) -> tuple[CandidateScore, _Fitted | None, HeldOut | None, str, float]:
    """:func:`_score_candidate` and the seconds it took (a job a helper process can run:
    module level, its inputs and outputs pickle)."""
    t0 = time.perf_counter()
    return (*_score_candidate(ev, effect, current, list(free), names, channel, noise, scale2,
                              s0, f0), time.perf_counter() - t0)


def _score_candidate(ev: _Evaluator, effect: str, current: Calibration, free: list[str],
                     names: Sequence[str], channel: str, noise: float, scale2: float,
                     s0: float, f0: float
                     ) -> tuple[CandidateScore, _Fitted | None, HeldOut | None, str]:
    """One candidate fitted with the model's parameters and scored in sample, then held out
    when it can qualify; returns its score, its fit, its held-out score (None where missing)
    and the line that says it."""
    try:
        f = fit_candidate(ev, effect, current, free, names, noise)
        f1 = in_sample_ms(ev, f.calibration, channel) / scale2
        in_sample = (f0 - f1) / (f0 - 1.0)
        # held out only what can qualify: one that removes too little of the
        # in-sample excess is rejected whatever its held-out score
        h1 = heldout_score(ev, f.calibration, _moving(f.free, channel), channel) \
            if in_sample >= MIN_EXPLAINED else None
    except (FitError, ConfigError) as err:
        score = CandidateScore(effect, {}, {}, math.nan, math.nan, -math.inf, -math.inf,
                               note=str(err), in_sample=-math.inf)
        return score, None, None, f"  {effect:11s} failed: {err}"
    ci = {n: honest_interval(f.calibration, n, f.ci95[n])
          for n in effect_parameters(effect) if n in f.ci95}
    if f.absent:
        score = CandidateScore(effect, {}, {}, math.sqrt(f1 * scale2), math.nan, math.nan,
                               math.nan,
                               note=f.absent, in_sample=0.0)
        return score, f, None, f"  {effect:11s} explains    0.0 %: {f.absent}"
    if h1 is None:
        score = CandidateScore(effect, _effect_values(f.calibration, effect), ci,
                               math.sqrt(f1 * scale2), math.nan, math.nan, math.nan,
                               in_sample=in_sample)
        return score, f, None, (
            f"  {effect:11s} explains {100 * in_sample:6.1f} % of the excess in "
            f"sample (< {100 * MIN_EXPLAINED:.0f} %: not scored held out)  "
            f"{_effect_values(f.calibration, effect)}")
    s1 = _score(h1, scale2)
    explained = (s0 - s1) / max(s0 - 1.0, 1e-12)
    relative = (s0 - s1) / s0
    score = CandidateScore(effect, _effect_values(f.calibration, effect), ci,
                           math.sqrt(h1.fit_ms), math.sqrt(h1.heldout_ms), explained, relative,
                           in_sample=in_sample)
    return score, f, h1, (
        f"  {effect:11s} held-out score {s1:8.3f}  explains {100 * explained:6.1f} % "
        f"of the excess ({100 * in_sample:6.1f} % in sample)  "
        f"{_effect_values(f.calibration, effect)}")


def _qualifying(scores: Sequence[CandidateScore], f0: float) -> list[CandidateScore]:
    """The selection rules: the candidates that lower the held-out score by ``MIN_RELATIVE``,
    remove ``MIN_EXPLAINED`` of the in-sample excess and ``MIN_DROP`` of the in-sample score
    ``f0``."""
    # explaining the gap held out AND in sample: the approximate held-out score of a
    # misspecified model is itself noisy, and a candidate that fits no better than
    # the baseline must not win on that noise
    # kept when it lowers the held-out score significantly and explains a real part
    # of the in-sample excess: a partial explanation stays and the rest is
    # reported as the residual's shape
    return [s for s in scores if s.explained > 0.0
            and s.in_sample >= MIN_EXPLAINED and s.relative >= MIN_RELATIVE
            and s.in_sample * (f0 - 1.0) >= MIN_DROP * f0]


def _search_earned_gain(ctx: _Context, model: _Model, win: CandidateScore, fitted: _Fitted,
                        scale2: float, f0: float) -> bool:
    """The ``search_credit`` rule: True, and the model refitted without the winner's effect,
    when a longer search rather than the effect earned the gain (at most
    ``MAX_SEARCHES_ON`` times)."""
    if len(model.refits) >= MAX_SEARCHES_ON:
        return False
    # the winner's in-sample score, as its share was computed from it
    f1 = f0 - win.in_sample * (f0 - 1.0)
    plain = search_credit(ctx.ev, fitted.calibration, win.effect, model.free, ctx.names,
                          scale2, f0, f1)
    if plain is None:
        return False
    # the model without the effect, refitted from where the candidate's search
    # ended, fits as well: the search earned the gain, not the effect
    model.refits.append(Refit(win.effect, _rmse_per_recording(ctx.ev, model.current)[0],
                              _rmse_per_recording(ctx.ev, plain[0])[0]))
    ctx.say(f"  -> {win.effect} adds nothing a longer search did not: refitted without "
            f"it from its fit, wheel RMSE {model.refits[-1].rmse_before:.3f} -> "
            f"{model.refits[-1].rmse_after:.3f} rpm; nothing named this round")
    model.current = plain[0]
    model.ci95 = {**model.ci95, **plain[1]}
    return True


def _add_winner(ctx: _Context, model: _Model, channel: str, win: CandidateScore,
                fitted: _Fitted, held: HeldOut, scores: Sequence[CandidateScore]) -> None:
    """Name the round's winner: a :class:`DiagnoseStep`, and the model moved to its fit."""
    scores = [CandidateScore(**{**s.__dict__, "accepted": s is win}) for s in scores]
    before = _rmse_per_recording(ctx.ev, model.current)
    after = _rmse_per_recording(ctx.ev, fitted.calibration)
    model.steps.append(DiagnoseStep(
        win.effect, win.parameters, win.ci95, before[0], after[0], before[1], after[1],
        before[2], after[2], model.current, fitted.calibration, tuple(scores),
        fitted.warnings, win.explained))
    ctx.say(f"  -> {win.effect} added: wheel RMSE {before[0]:.3f} -> {after[0]:.3f} rpm")
    model.current = fitted.calibration
    model.free = list(fitted.free)
    model.carried = (model.current, (channel, tuple(_moving(model.free, channel))), held)
    model.ci95 = {**model.ci95, **fitted.ci95}
    model.rejected = ()


def _conclude(ctx: _Context, model: _Model, initial: Calibration, baseline: Calibration,
              loc0: Localisation, rmse_base: float, noise: float,
              reference: Future | None = None) -> Diagnosis:
    """What remains of the final model's residual, described and compared with the reference
    model (fitted by a helper when ``reference`` holds its job), and the
    :class:`Diagnosis`."""
    final = _rmse_per_recording(ctx.ev, model.current)
    check = residual_check(final[3], noise)
    loc1 = localise(ctx.recs, _predictions(ctx.ev, model.current), ctx.robot, ctx.names)
    unexplained = check.structured
    shape = residual_shape(ctx.recs, final[3], ctx.robot)
    rmse_ref, base_rm = _compare_with_reference(ctx, baseline, final[0], reference)
    ctx.say("what remains: " + shape.describe())
    ctx.say(f"final model: wheel RMSE {final[0]:.3f} rpm = {check.ratio:.2f} x noise, lag-1 "
            f"autocorrelation {check.lag1_autocorrelation:.2f} -> "
            + ("structured residual no effect of the library explains (unexplained)"
               if unexplained else "what remains looks like noise"))
    final_cal = _final_calibration(model, final[0], unexplained)
    return Diagnosis(tuple(model.steps), unexplained, loc0.rmse_rpm, rmse_base, final[0], noise,
                     initial, baseline, final_cal, loc0, loc1, check, model.rejected, ctx.names,
                     rmse_ref, shape, _pose_pair(base_rm[2]), _pose_pair(final[2]),
                     _findings(final_cal, ctx.recs, ctx.robot, ctx.say), tuple(model.refits))


def _compare_with_reference(ctx: _Context, baseline: Calibration, rmse_final: float,
                            job: Future | None = None) -> tuple[float, tuple]:
    """Fit the generic reference model (:mod:`.reference`) and log the share of its gap the
    named effects close; returns its wheel RMSE [rpm] (NaN without one) and the baseline's
    :func:`_rmse_per_recording`. ``job``: a helper's fit of it, used when it has answered by
    now (else, or when it failed, the fit runs here)."""
    # the helper's answer when it is there (not waited for: it was one of the helper's first
    # jobs, so one still open means a stalled helper; a failed one is the same)
    if job is not None and job.done() and job.exception() is None:
        ref = job.result()
    else:
        ref = fit_reference(ctx.recs, ctx.robot)
    rmse_ref = ref.rmse_rpm if ref is not None else math.nan
    base_rm = _rmse_per_recording(ctx.ev, baseline)
    if ref is not None:
        ctx.say(f"reference model (output error, {ref.order[0]} + {ref.order[1]} coefficients, "
                f"delay {ref.delay_samples} samples): wheel RMSE {rmse_ref:.3f} rpm; "
                + reference_comparison(base_rm[0], rmse_final, rmse_ref))
    return rmse_ref, base_rm


def _final_calibration(model: _Model, rmse_final: float, unexplained: bool) -> Calibration:
    """The extended calibration: the final model with its 95 % intervals (None where the data
    cannot bound a parameter) and how it was made."""
    info = dict(model.current.info)
    info.update({"method": "diagnose", "effects_added": [s.effect for s in model.steps],
                 "rmse_rpm": rmse_final, "unexplained": unexplained})
    cis = {k: honest_interval(model.current, k, v) for k, v in model.ci95.items()}
    return replace(model.current, info=info, ci95=calibration_intervals(cis),
                   source="<diagnose>")


def honest_interval(cal: Calibration, name: str, interval: tuple[float, float]
                    ) -> tuple[float, float]:
    """A 95 % interval of parameter ``name`` of ``cal`` as reported
    (:func:`~mecanum_hil.identify.fit.bounded_interval`: clipped to the admissible range), or
    ``(nan, nan)`` where the data cannot bound it. The engine's intervals already are; a
    grid's span (deadband, controller period) is judged the same way."""
    lo, hi = (float(v) for v in interval)
    out = bounded_interval(name, parameter_value(cal, name), lo, hi)
    return out if out is not None else (math.nan, math.nan)


def _findings(cal: Calibration, recs: Sequence[Recording], robot: RobotProfile,
              say: Callable[[str], None]) -> tuple[Finding, ...]:
    """Named properties of the final model (:func:`.localise.proportional_only`,
    :func:`.localise.creeping_levels`)."""
    wheels = [w for w in range(4) if any(np.isfinite(r.wheel_rpm[:, w]).any() for r in recs)]
    found = [proportional_only(cal, typical_step_s(recs, robot), wheels)]
    found += creeping_levels(cal, recs, robot, wheels)
    for f in found:
        if f is not None:
            say(f"named: {f.effect}: {f.description}")
    return tuple(f for f in found if f is not None)

