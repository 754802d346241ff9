"""The adapter between a batch task and the library's stages: the one place that imports them.

Each function runs one stage on files already on the worker's disk, exactly as the serial
command does (same readers, same calls, same defaults), and returns the row fields as a plain
dict. Where the library's entry points move, only this module changes.

Per-file isolation: recordings are read one by one; one that cannot be read is left out and
named (``bad``), the stage runs on the others. A stage error (the fit refuses the data, the
video has no marker) fails the whole group; the task turns it into the row's ``error``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ..errors import ConfigError, MecanumHILError

COEFFICIENTS = ("A", "B", "C")


def read_recordings(paths: Sequence[Path], names: Sequence[str]
                    ) -> tuple[list[Any], list[str], list[str]]:
    """Read recordings as ``fit``/``diagnose``/``shadow --replay`` do (telemetry re-timed).

    Returns
    -------
    (recordings, names, bad)
        The readable recordings with their names, and one ``"name: why"`` per bad file.
    """
    from ..io.timing import read_for_analysis

    recs, ok, bad = [], [], []
    for path, name in zip(paths, names, strict=True):
        try:
            recs.append(read_for_analysis(path))
            ok.append(name)
        except MecanumHILError as err:
            bad.append(_named(err, path, name))
    return recs, ok, bad


def _named(err: Exception, path: Path, name: str) -> str:
    """The error's text with the worker's staging path replaced by the archive's name."""
    text = str(err).replace(str(path), name)
    return text if name in text else f"{name}: {text}"


def _coefficients(cal, ci95: dict[str, tuple[float, float] | None]) -> dict[str, Any]:
    """The coefficients and their intervals as row fields; NaN where there is no interval
    (none computed, or the data cannot bound it)."""
    row: dict[str, Any] = {}
    for k in COEFFICIENTS:
        lo, hi = ci95.get(k) or (math.nan, math.nan)
        row[k] = float(getattr(cal, k))
        row[f"{k}_lo"] = float(lo)
        row[f"{k}_hi"] = float(hi)
    return row


#: Each stage's revision, part of a group's settings hash: raised when what a stage writes for
#: the same inputs changes, so that a resumed batch runs those groups again instead of keeping
#: rows the stage no longer writes (shadow 2: a replay that compared nothing is left out, not
#: counted as 0 alarms).
REVISIONS = {"fit": 1, "diagnose": 1, "shadow": 2, "measure-video": 1}


def run_fit(recordings: Sequence[Any], names: Sequence[str], robot, calibration,
            method: str = "lsq") -> tuple[dict[str, Any], Any]:
    """``mecanum-hil fit`` on one group: the row fields and the fitted calibration."""
    from ..identify.fit import fit

    res = fit(list(recordings), robot, method, calibration, sources=list(names))
    row = _coefficients(res.calibration, dict(res.ci95))
    row.update(rmse_rpm=float(res.rmse_rpm), fit_percent=float(res.fit_percent),
               effects=sorted(res.calibration.effects.active()), warnings=list(res.warnings),
               details={"method": res.method, "n_samples": int(res.n_samples)})
    return row, res.calibration


def run_diagnose(recordings: Sequence[Any], names: Sequence[str], robot, calibration,
                 method: str = "lsq", candidates: Sequence[str] | None = None
                 ) -> tuple[dict[str, Any], Any]:
    """``fit`` then ``diagnose --calibration <the fit>`` on one group (the README's pipeline).

    The coefficients, intervals and RMSE are the final (extended) model's; ``effects`` the
    effects ``diagnose`` named. One process per group (``jobs=1``): the fleet already runs
    groups side by side on every core, and the workers all start at once, while the load
    average still says the machine is idle; a helper each would run two processes per core.
    """
    from ..identify.diagnose import CANDIDATES, diagnose

    _, fitted = run_fit(recordings, names, robot, calibration, method)
    diag = diagnose(list(recordings), fitted, robot, names=list(names),
                    candidates=tuple(candidates) if candidates else CANDIDATES, jobs=1)
    final = diag.calibration
    row = _coefficients(final, dict(final.ci95))
    row.update(rmse_rpm=float(diag.rmse_final), rmse_initial_rpm=float(diag.rmse_initial),
               effects=list(diag.effects), unexplained=bool(diag.unexplained),
               details={"diagnosis": diag.to_json(), "fitted": {k: float(getattr(fitted, k))
                                                                for k in COEFFICIENTS}})
    return row, final


def run_shadow(recordings: Sequence[Any], names: Sequence[str], robot, calibration,
               config: dict[str, Any] | None = None) -> tuple[dict[str, Any], list[str]]:
    """``shadow --replay REC --calibration CAL`` on each recording of the group.

    Returns the row fields and the recordings that could not be replayed or whose replay
    compared nothing (``"name: why"``, :func:`~mecanum_hil.monitor.core.nothing_compared`): as
    ``shadow --replay`` refuses them, they are left out, never counted as no alarm.
    """
    from ..monitor import ShadowConfig, replay
    from ..monitor.core import nothing_compared

    cfg = ShadowConfig(**(config or {}))
    alarms = 0
    first: float | None = None
    with_alarms, bad, per = [], [], {}
    for rec, name in zip(recordings, names, strict=True):
        try:
            res = replay(rec, calibration, robot, cfg, source=name)
        except MecanumHILError as err:
            bad.append(f"{name}: {err}" if name not in str(err) else str(err))
            continue
        why = nothing_compared(res, rec, cfg)
        if why is not None:  # counted as 0 alarms it would read as a robot that matched
            bad.append(f"{name}: {why}")
            continue
        per[name] = res.summary()
        if res.alarms:
            alarms += len(res.alarms)
            with_alarms.append(name)
            t = res.first_alarm_t_s
            first = t if first is None else min(first, t)
    row = _coefficients(calibration, dict(calibration.ci95))
    row.update(alarms=alarms, alarm_inputs=with_alarms,
               first_alarm_t_s=math.nan if first is None else float(first),
               effects=sorted(calibration.effects.active()), details={"replays": per})
    return row, bad


def run_measure_video(path: Path, name: str, options: dict[str, Any], robot=None,
                      calibration=None) -> tuple[dict[str, Any], Any]:
    """``measure-video VIDEO`` on one video: the row fields and the measured recording.

    Decoding and analysis take turns in the task's one thread (``decode_beside=False`` unless
    the options say otherwise), as ``run_diagnose`` keeps to one process: the fleet already
    runs videos side by side on every core, and its workers all start while the load average
    still says the machine is idle; decoder threads beside each would oversubscribe the cores.
    """
    from ..vision.measure import measure_video

    measure = measure_options(options)
    try:
        result = measure_video(path, measure)
    except MecanumHILError as err:
        raise type(err)(_named(err, path, name)) from err
    summary = {k: v for k, v in result.summary.items() if k not in ("video",)}
    row = {"warnings": list(result.warnings), "details": summary}
    return row, result.recording


def measure_options(options: dict[str, Any]):
    """The ``MeasureOptions`` of a batch's measure-video options (``wheel``, ``roi``,
    ``marker``, ``marker_hsv`` and ``MeasureOptions``' own fields), as ``measure-video`` builds
    them; a bad value raises its one-line error."""
    from ..vision.detect import MarkerSpec, parse_hsv, parse_roi
    from ..vision.measure import MeasureOptions

    opts = dict(options)
    opts.setdefault("decode_beside", False)
    wheel = int(opts.pop("wheel", 1))
    roi = opts.pop("roi", None)
    marker = opts.pop("marker", "auto")
    hsv = opts.pop("marker_hsv", None)
    spec = parse_hsv(hsv) if hsv else MarkerSpec(marker)
    rois = tuple(parse_roi(r, wheel) for r in roi) if roi else ((wheel, None),)
    return MeasureOptions(rois=rois, marker=spec, **opts)


def check_options(command: str, options: dict[str, Any]) -> None:
    """Refuse a bad stage option once, before any task runs (each task would fail alike).

    Raises
    ------
    MecanumHILError
        The stage's own one-line error (``ConfigError`` for an unknown option).
    """
    try:
        if command in ("fit", "diagnose"):
            method = options.get("method", "lsq")
            if method not in ("lsq", "paper-grid"):
                raise ConfigError(f"--method must be lsq or paper-grid, got {method!r}")
        if command == "diagnose" and options.get("candidates") is not None:
            from ..identify.diagnose import candidate_pool

            candidate_pool(list(options["candidates"]))
        if command == "shadow":
            from ..monitor import ShadowConfig

            ShadowConfig(**(options.get("config") or {}))
        if command == "measure-video":
            measure_options(options.get("video", {}))
    except TypeError as err:  # an option the stage does not have (library callers)
        raise ConfigError(f"batch {command}: bad option: {err}") from None


def calibration_text(calibration, header: str) -> str:
    """A calibration as the TOML every ``--calibration`` reads."""
    from ..model.calibration import calibration_to_toml

    return calibration_to_toml(calibration, header)


def recording_text(recording, path: Path) -> Path:
    """Write a recording (CSV + sidecar) where ``write_recording`` would."""
    from ..io.recording import write_recording

    return write_recording(recording, path)
