"""The data a record session is set up with and ends with.

:class:`SessionConfig` (its settings), the reasons a session ends with their exit codes
(:data:`EXIT_CODES`, the table in :mod:`mecanum_hil.link.session`), :class:`RecordResult` (how
it ended and what it counted) and the errors of the telemetry checks. Kept apart from the
session so that the stop path (:mod:`mecanum_hil.link.stop_path`) and the session share them
without importing each other; all are importable from :mod:`mecanum_hil.link.session`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import LinkError, LinkLostError

#: Exit code of each way a session can end.
EXIT_CODES = {"completed": 0, "error": 1, "observer_stop": 3, "link_lost": 4,
              "telemetry_rate": 5, "controller_reset": 6, "estop": 7, "drive_fault": 8,
              "not_acknowledged": 9, "invalid_readings": 10, "clock_drift": 11,
              "host_stall": 12, "interrupted": 130, "terminated": 143}

#: Reasons that end the run at once (STOP, then the tail of telemetry is kept).
STOP_AT_ONCE = ("estop", "drive_fault", "not_acknowledged")
#: Reasons judged while the profile runs to its end: they only set the reason and exit code.
NOT_AS_ASKED = ("invalid_readings", "clock_drift", "host_stall")


@dataclass(frozen=True)
class SessionConfig:
    """Settings of a record session.

    Attributes
    ----------
    connect_timeout_s : float
        How long HELLO is repeated (every 0.1 s) before giving up [s].
    link_timeout_s : float
        Telemetry silence after which the link counts as lost, whatever other frames arrive
        (when the controller announced telemetry) [s].
    ping_rate_hz : float
        Rate of PING frames for the round-trip latency [Hz]; 0 for none.
    tail_s : float
        Telemetry kept after the STOP at the end of a completed profile [s].
    max_send_failures : int
        Consecutive failed sends after which the link counts as lost.
    handle_sigterm : bool
        Turn SIGTERM into a clean stop (main thread only).
    observer_queue : int
        Samples buffered for observers before the oldest are dropped (and counted).
    host_stall_share : float or None
        Share of the announced watchdog time the host's command stream may pause before the
        run ends with ``host_stall``; None: the environment variable
        ``MECANUM_HIL_HOST_STALL_SHARE``, else
        :data:`~mecanum_hil.link.session.HOST_STALL_SHARE` (0.5).
    clock_drift_slack_s : float or None
        Drift of the controller clock beyond ``CLOCK_DRIFT_MAX`` of the elapsed time that ends
        the run with ``clock_drift`` [s]; None: the environment variable
        ``MECANUM_HIL_CLOCK_DRIFT_SLACK_S``, else
        :data:`~mecanum_hil.link.session.CLOCK_DRIFT_SLACK_S` (0.1 s).
    """

    connect_timeout_s: float = 2.0
    link_timeout_s: float = 0.5
    ping_rate_hz: float = 5.0
    tail_s: float = 0.2
    max_send_failures: int = 5
    handle_sigterm: bool = True
    observer_queue: int = 10000
    host_stall_share: float | None = None
    clock_drift_slack_s: float | None = None


@dataclass(frozen=True)
class RecordResult:
    """How a session ended and what it counted.

    Attributes
    ----------
    reason : str
        One of :data:`EXIT_CODES`.
    exit_code : int
        Process exit code for ``reason``.
    path : Path
        The recording written.
    rows : int
        Rows in the recording.
    commands_sent, telemetry_received : int
        Command frames sent and telemetry samples recorded.
    duration_s : float
        Time from the first command to the end [s].
    stats : dict
        The transport's counters (:class:`~mecanum_hil.link.transport.LinkStats`).
    latency_ms : dict
        ``rtt_*`` PING round trip and ``ack_*`` command-to-acknowledgement latency
        percentiles (``p50``, ``p90``, ``p99``, ``max``, ``n``) [ms].
    message : str
        The error's text for ``error``/``link_lost``, else empty.
    observer_dropped : int
        Telemetry samples observers did not see because they lagged.
    controller : str
        Name the controller gave in HELLO_ACK.
    signal_at_end : int or None
        A signal that came while STOP was being sent and the recording closed: kept, not
        raised, so that neither was cut short (``record --policy`` then runs no further
        episode).
    """

    reason: str
    exit_code: int
    path: Path
    rows: int
    commands_sent: int
    telemetry_received: int
    duration_s: float
    stats: dict[str, int]
    latency_ms: dict[str, float]
    message: str = ""
    observer_dropped: int = 0
    controller: str = ""
    error: BaseException | None = field(default=None, compare=False, repr=False)
    signal_at_end: int | None = None


class TelemetrySilenceError(LinkLostError):
    """No telemetry for the link timeout (the port itself still works)."""


class TelemetryCheckError(LinkError):
    """The telemetry is not sane: the run ends with STOP and ``reason``'s exit code.

    Attributes
    ----------
    reason : str
        ``"telemetry_rate"``, ``"controller_reset"`` or one of :data:`STOP_AT_ONCE` (see
        :data:`EXIT_CODES`).
    """

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason
        self.exit_code = EXIT_CODES[reason]


def percentiles_ms(samples_s: Sequence[float], prefix: str) -> dict[str, float]:
    """``p50``, ``p90``, ``p99``, ``max`` [ms] and ``n`` of latency samples [s]."""
    out: dict[str, float] = {f"{prefix}_n": float(len(samples_s))}
    if len(samples_s):
        arr = np.asarray(samples_s) * 1e3
        for q in (50, 90, 99):
            out[f"{prefix}_p{q}"] = float(np.percentile(arr, q))
        out[f"{prefix}_max"] = float(arr.max())
    return out

