"""Diagnose: find where model and robot disagree, name the missing physical effects, keep what
helps, and say how much of the gap is explainable at all.

The method, one file per step (``docs/diagnose-method.md`` has the details and the reasons):

1. :mod:`.localise` -- the model on every recording (:class:`_Evaluator`), the residual
   broken down by recording, wheel and regime (:mod:`mecanum_hil.identify.regimes`), the noise
   level ``sigma`` from the residual's differences, and the final residual's shape (onset,
   overshoot, settling; dominant frequency and damping if it rings).
2. :mod:`.candidates` -- the effect library (:data:`CANDIDATES`: dead time, saturation, windup,
   rate limit, deadband, wheel gain, controller period, drive lag, breakaway, friction, drive
   deadband, braking limit, fast decay, slip),
   each fitted *together with* A, B, C and the effects already kept, from start values read
   off the data (latency, rise time, steepest slope, peak, steady-state ratio, the drive at
   breakaway, the steepest deceleration).
3. :mod:`.heldout` -- the held-out score: approximate leave-one-recording-out (one
   Gauss-Newton step from the full fit without the recording, then the recording simulated
   exactly), or held-out time blocks inside the recordings when there are too few recordings.
   Score = held-out mean square / ``sigma^2`` (1 = noise floor).
4. :mod:`.selection` -- rounds: after refitting A, B, C alone (no candidate gets credit for a
   refit), the best candidate is kept when it lowers the held-out score by
   :data:`~.selection.MIN_RELATIVE` and removes :data:`~.selection.MIN_EXPLAINED` of the
   in-sample excess; rounds repeat until none qualifies or the residual is at the noise floor.
   Slip is scored on the pose channels. What helps is kept even when structured residual
   remains; the diagnosis then says ``unexplained`` and describes what remains.
5. :mod:`.reference` -- a generic output-error model of higher order fitted to the same data:
   ``rmse_reference`` and ``explained_share``, the share of the explainable gap the named
   effects close.
6. :mod:`.report` -- the markdown report with plots, and the demo's story.
"""

from __future__ import annotations

from .candidates import (
    CANDIDATES,
    CandidateScore,
    candidate_pool,
    effect_parameters,
    fit_candidate,
)
from .heldout import HeldOut, heldout_score
from .localise import (
    ResidualCheck,
    _Evaluator,
    initial_pose_at_rest,
    lag1_autocorrelation,
    residual_check,
)
from .selection import DiagnoseStep, Diagnosis, diagnose

__all__ = [
    "CANDIDATES", "CandidateScore", "DiagnoseStep", "Diagnosis", "HeldOut", "ResidualCheck",
    "_Evaluator", "candidate_pool", "diagnose", "effect_parameters", "fit_candidate",
    "heldout_score", "initial_pose_at_rest", "lag1_autocorrelation", "residual_check",
]
