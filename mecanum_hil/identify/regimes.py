"""Where model and robot disagree: residuals by recording, channel and regime (pure).

The residual is measured minus predicted. Wheel channels are in [rpm]; pose channels in [m]
(``X``, ``Y``) and [deg] (heading, wrapped to +-180). Each wheel sample is put in regimes:

* ``transient`` (within ``settle_s`` of a jump of its wheel target) or ``steady`` (the rest,
  including slow ramps);
* ``rest`` (target below 1 rpm), ``low speed`` or ``high speed`` (target at or above
  ``high_rpm``, by default half the robot's wheel speed limit);
* by the commanded motion: ``straight`` (no turning, forward/backward), ``strafing`` (no
  turning, a sideways component), ``turning`` (omega not zero), ``stopped`` (no command).

The noise level of a channel is estimated without a model from the residual's first
differences (median absolute deviation, so the few large jumps at steps do not count):
``sigma = 1.4826 * MAD(diff(r)) / sqrt(2)``, exact for white noise on a smooth model error
(for quantised data whose MAD is zero, a trimmed RMS of the differences instead).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..io.recording import Recording
from ..model.kinematics import command_to_wheels
from ..model.robot import RobotProfile

#: Pose channel names and units.
POSE_CHANNELS = (("X", "m"), ("Y", "m"), ("phi", "deg"))
_JUMP_RPM = 1.0

#: The regimes of :func:`regime_masks` in their three groupings: each puts every wheel sample
#: in exactly one of its regimes.
REGIME_GROUPS = {
    "change": ("transient", "steady"),
    "speed": ("rest", "low speed", "high speed"),
    "motion": ("straight", "strafing", "turning", "stopped"),
}


def wheel_residual(measured: Recording, predicted: Recording) -> np.ndarray:
    """Measured minus predicted wheel speeds [rpm], shape (T, 4); NaN where not measured."""
    return measured.wheel_rpm - predicted.wheel_rpm


def pose_residual(measured: Recording, predicted: Recording) -> np.ndarray:
    """Measured minus predicted pose, shape (T, 3): X, Y [m], heading [deg] wrapped to +-180."""
    r = measured.pose - predicted.pose
    r[:, 2] = (r[:, 2] + 180.0) % 360.0 - 180.0
    return r


def wheel_targets(rec: Recording, robot: RobotProfile) -> np.ndarray:
    """The wheel targets of the recording's commands [rpm], shape (T, 4)."""
    c = rec.commands
    return command_to_wheels(c[:, 0], c[:, 1], c[:, 2], robot.k)


def regime_masks(rec: Recording, robot: RobotProfile, *, settle_s: float = 0.5,
                 high_rpm: float | None = None) -> dict[str, np.ndarray]:
    """Boolean masks (T, 4) of the wheel samples in each regime (see the module docstring)."""
    tgt = wheel_targets(rec, robot)
    t = rec.t_s
    high = robot.wheel_speed_max_rpm / 2.0 if high_rpm is None else high_rpm
    jump = np.zeros_like(tgt, dtype=bool)
    jump[1:] = np.abs(np.diff(tgt, axis=0)) > _JUMP_RPM
    transient = np.zeros_like(jump)
    for i in range(4):
        for j in np.flatnonzero(jump[:, i]):
            # the target of row j - 1 is in force from t[j - 1]; the jump acts from there
            start = t[j - 1]
            transient[(t >= start) & (t < start + settle_s), i] = True
    mag = np.abs(tgt)
    n, omega, theta = rec.commands[:, 0], rec.commands[:, 1], rec.commands[:, 2]
    turning = np.abs(omega) > 1e-9
    moving = (np.abs(n) > 1e-9) & ~turning
    sideways = np.abs(np.cos(np.deg2rad(theta))) > 0.05
    col = np.ones((1, 4), dtype=bool)
    return {
        "transient": transient,
        "steady": ~transient,
        "rest": mag < 1.0,
        "low speed": (mag >= 1.0) & (mag < high),
        "high speed": mag >= high,
        "straight": (moving & ~sideways)[:, None] & col,
        "strafing": (moving & sideways)[:, None] & col,
        "turning": turning[:, None] & col,
        "stopped": (~moving & ~turning)[:, None] & col,
    }


def _sd_from_differences(d: np.ndarray) -> float:
    d = d[np.isfinite(d)]
    if d.size < 4:
        return float("nan")
    mad = 1.4826 * float(np.median(np.abs(d - np.median(d))))
    # quantised data (encoder counts) can have a MAD of zero: then the RMS of the central 90 %
    # of the differences, corrected for the trimming of a normal distribution (factor 0.623)
    a = np.abs(d)
    central = a[a <= np.quantile(a, 0.9)]
    trimmed = float(np.sqrt(np.mean(central * central) / 0.623))
    return max(mad, trimmed) / float(np.sqrt(2.0))


def measured_differences(values: np.ndarray, t_s: np.ndarray | None = None) -> np.ndarray:
    """First differences of each column over its own measured (finite) samples, concatenated:
    rows where a column is not measured (a recorded run's command rows, a camera's missing
    frames) are skipped, not counted as breaks. With the sample times ``t_s`` [s], the
    differences are divided by the time between those samples (slopes, per second)."""
    r = np.asarray(values, dtype=float)
    r = r.reshape(r.shape[0], -1)
    parts = []
    for c in range(r.shape[1]):
        ok = np.isfinite(r[:, c])
        d = np.diff(r[ok, c])
        parts.append(d if t_s is None else d / np.diff(np.asarray(t_s, dtype=float)[ok]))
    return np.concatenate(parts) if parts else np.empty(0)


def noise_sd(residual: np.ndarray) -> float:
    """Noise level of residual samples from their first differences (module docstring).

    Parameters
    ----------
    residual : ndarray, shape (T,) or (T, k)
        One recording's residual; columns are channels, NaN where not measured (differences
        are taken between a column's consecutive measured samples).
    """
    return _sd_from_differences(measured_differences(residual))


def pooled_noise_sd(residuals: Sequence[np.ndarray]) -> float:
    """:func:`noise_sd` over several recordings (differences never span two recordings)."""
    parts = [measured_differences(r) for r in residuals]
    return _sd_from_differences(np.concatenate(parts) if parts else np.empty(0))


def rmse(values) -> float:
    """Root mean square of the finite values (NaN when there are none)."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    return float(np.sqrt(np.mean(v * v))) if v.size else float("nan")


@dataclass(frozen=True)
class RegimeStat:
    """The residual in one regime.

    Attributes
    ----------
    n_samples : int
        Wheel samples in the regime.
    rmse_rpm : float
        RMS residual there [rpm].
    share_of_samples, share_of_sse : float
        Fraction of all wheel samples, and of the summed squared residual, in the regime [-];
        a share of SSE well above the share of samples says the model fails there.
    """

    n_samples: int
    rmse_rpm: float
    share_of_samples: float
    share_of_sse: float


@dataclass(frozen=True)
class RecordingStat:
    """The residual of one recording.

    Attributes
    ----------
    name : str
    rmse_rpm : float
        Over its wheel samples [rpm].
    wheel_rmse_rpm : tuple of 4 float
        Per wheel [rpm] (NaN for a wheel not measured).
    pose_rmse : tuple of 3 float
        X [m], Y [m], heading [deg] (NaN without pose).
    """

    name: str
    rmse_rpm: float
    wheel_rmse_rpm: tuple[float, ...]
    pose_rmse: tuple[float, ...]


@dataclass(frozen=True)
class Localisation:
    """Where the model fails: per recording, per channel and per regime.

    Attributes
    ----------
    recordings : tuple of RecordingStat
    regimes : dict of str to RegimeStat
    rmse_rpm : float
        Over all wheel samples [rpm].
    noise_rpm : float
        Wheel noise level estimated from the residual's differences [rpm].
    n_samples : int
        Measured wheel samples (a time row holds up to four); each regime grouping of
        :data:`REGIME_GROUPS` shares them out.
    """

    recordings: tuple[RecordingStat, ...]
    regimes: dict[str, RegimeStat]
    rmse_rpm: float
    noise_rpm: float
    n_samples: int = 0

    def worst_regimes(self, ratio: float = 1.5) -> list[str]:
        """Regimes whose share of the squared residual is ``ratio`` times their share of samples.
        """
        out = [(s.share_of_sse / s.share_of_samples, name) for name, s in self.regimes.items()
               if s.share_of_samples > 0 and s.share_of_sse > ratio * s.share_of_samples]
        return [name for _, name in sorted(out, reverse=True)]

    def lines(self) -> list[str]:
        """A plain-text table of the localisation."""
        out = [f"wheel RMSE {self.rmse_rpm:.3f} rpm over all samples; noise level about "
               f"{self.noise_rpm:.3f} rpm",
               "per recording: RMSE [rpm], wheels 1..4 [rpm], pose X [m] Y [m] phi [deg]"]
        for r in self.recordings:
            wheels = " ".join(f"{w:7.3f}" for w in r.wheel_rmse_rpm)
            pose = " ".join(f"{p:7.4f}" for p in r.pose_rmse)
            out.append(f"  {r.name:24s} {r.rmse_rpm:8.3f} | {wheels} | {pose}")
        out.append(f"per regime: wheel samples, RMSE [rpm], share of samples -> share of "
                   f"squared residual; each grouping shares out all {self.n_samples} wheel "
                   "samples")
        for group in REGIME_GROUPS:
            out.append(f" by {group}:")
            for name in REGIME_GROUPS[group]:
                s = self.regimes.get(name)
                if s is not None:
                    out.append(f"  {name:12s} {s.n_samples:7d} {s.rmse_rpm:8.3f}  "
                               f"{100 * s.share_of_samples:5.1f} % -> "
                               f"{100 * s.share_of_sse:5.1f} %")
        worst = self.worst_regimes()
        out.append("the model fails most in: " + (", ".join(worst) if worst else
                                                    "no regime stands out"))
        return out


def localise(measured: Sequence[Recording], predicted: Sequence[Recording],
             robot: RobotProfile, names: Sequence[str] | None = None, *,
             settle_s: float = 0.5, high_rpm: float | None = None) -> Localisation:
    """Residual statistics by recording, channel and regime.

    Parameters
    ----------
    measured, predicted : sequence of Recording
        The recordings and the model's predictions for them (same times).
    robot : RobotProfile
        For the wheel targets of the commands.
    names : sequence of str, optional
        Recording names (default ``rec1``, ``rec2`` ...).
    settle_s : float
        How long after a jump of the target a sample counts as transient [s].
    high_rpm : float, optional
        Wheel target from which a sample counts as high speed [rpm].
    """
    names = list(names) if names is not None else [f"rec{i + 1}" for i in range(len(measured))]
    stats = []
    sq: dict[str, list[np.ndarray]] = {}
    residuals = []
    for name, m, p in zip(names, measured, predicted, strict=True):
        r = wheel_residual(m, p)
        residuals.append(r)
        pr = pose_residual(m, p)
        stats.append(RecordingStat(name, rmse(r), tuple(rmse(r[:, i]) for i in range(4)),
                                   tuple(rmse(pr[:, i]) for i in range(3))))
        for regime, mask in regime_masks(m, robot, settle_s=settle_s, high_rpm=high_rpm).items():
            sq.setdefault(regime, []).append(r[mask & np.isfinite(r)])
    allr = np.concatenate([r[np.isfinite(r)] for r in residuals])
    n_all = max(allr.size, 1)
    sse_all = float(np.sum(allr * allr)) or 1.0
    regimes = {}
    for regime, parts in sq.items():
        v = np.concatenate(parts)
        regimes[regime] = RegimeStat(int(v.size), rmse(v), v.size / n_all,
                                     float(np.sum(v * v)) / sse_all)
    return Localisation(tuple(stats), regimes, rmse(allr), pooled_noise_sd(residuals),
                        int(allr.size))
