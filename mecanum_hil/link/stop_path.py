"""The stop path: every way out of a command stream leaves the robot commanded to stop.

:func:`stream_stop_close` runs a session's stream and, whatever happens, sends STOP and closes
the recording. It is the one place the ways out are handled, for ``record`` and ``record
--policy``, in steps that each do one thing:

1. :func:`end_stream` streams until the profile ends or something ends it first (a signal
   raised by the :class:`~mecanum_hil.link.signals.SignalGuard` too) and classifies how
   (:func:`stream_until_end`); from then on a signal is kept, not raised;
2. :func:`send_stop` sends STOP (and keeps the tail of telemetry after a completed stream);
   after telemetry silence it probes whether the controller restarted;
3. :func:`settle_after_stop` waits for the wheels to come to rest (``record --policy``), the
   one wait after STOP a signal may cut short;
4. :func:`ending_of_failure` classifies an exception no step took (``SystemExit``, a
   callback's) before it goes on its way;
5. :func:`close_recording` sends STOP if no step did (:func:`stop_if_not_yet`), closes the
   observers and writes the sidecar's end (:func:`end_metadata`), whatever failed before;
6. :func:`result_of` gives the :class:`~mecanum_hil.link.session_types.RecordResult`.

The session is duck-typed (``sess``): the record session of :mod:`mecanum_hil.link.session` or
the policy session; this module imports neither, so that both can import it.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from ..errors import LinkError, LinkLostError, MecanumHILError, SessionTerminated
from ..io.recording import RecordingWriter
from .observers import ObserverStopError
from .session_types import (
    EXIT_CODES,
    NOT_AS_ASKED,
    STOP_AT_ONCE,
    RecordResult,
    SessionConfig,
    TelemetryCheckError,
    TelemetrySilenceError,
    percentiles_ms,
)
from .signals import SignalGuard, signal_reason
from .transport import Transport

#: What a signal raises in a stream (Ctrl-C, and the others of
#: :data:`~mecanum_hil.link.signals.ENDING_SIGNALS`).
SIGNAL_EXCEPTIONS = (KeyboardInterrupt, SessionTerminated)


@dataclass(frozen=True)
class Ending:
    """How a command stream ended, as far as known.

    Attributes
    ----------
    reason : str
        A key of :data:`~mecanum_hil.link.session_types.EXIT_CODES`.
    message : str
        The error's text (or a check's), else empty.
    error : BaseException or None
        The exception that ended it, when one did.
    """

    reason: str = "completed"
    message: str = ""
    error: BaseException | None = field(default=None, compare=False)

    @property
    def ran_to_end(self) -> bool:
        """Whether the whole profile was sent (completed, or one of ``NOT_AS_ASKED``)."""
        return self.reason == "completed" or self.reason in NOT_AS_ASKED


@dataclass(frozen=True)
class Closed:
    """What closing the recording measured.

    Attributes
    ----------
    duration_s : float
        Time from the first command to the close [s] (0 when none was sent).
    latency_ms : dict
        PING round-trip and acknowledgement latency percentiles [ms].
    late : BaseException or None
        A signal's exception that landed while closing (no guard): raised once closed.
    """

    duration_s: float
    latency_ms: dict[str, float]
    late: BaseException | None = None


def stream_until_end(sess: Any, config: SessionConfig) -> tuple[Ending, float]:
    """Handshake and stream until the profile ends or something ends it first.

    Returns how it ended and the telemetry to keep after STOP [s] (only after a completed
    profile, or a controller that stopped the wheels itself). The caller sends STOP whatever
    this returns or raises.
    """
    try:
        sess.run()
        sess.finish_checks()
        if sess.not_as_asked is not None:  # the profile ran to its end, not as asked
            reason, message = sess.not_as_asked
            return Ending(reason, message), config.tail_s
        return Ending(), config.tail_s
    except ObserverStopError:
        return Ending("observer_stop"), 0.0
    except TelemetryCheckError as err:
        # the controller stopped (or ignores) the commands: the tail shows the wheels at rest
        tail = config.tail_s if err.reason in STOP_AT_ONCE else 0.0
        return Ending(err.reason, str(err), err), tail
    except LinkLostError as err:
        return Ending("link_lost", str(err), err), 0.0
    except KeyboardInterrupt:
        return Ending("interrupted"), 0.0
    except SessionTerminated:
        return Ending("terminated"), 0.0
    except Exception as err:
        return Ending("error", str(err), err), 0.0


def end_stream(sess: Any, config: SessionConfig, guard: SignalGuard) -> tuple[Ending, float]:
    """:func:`stream_until_end`, ended by a signal kept before it too; then keep signals.

    From its return on the guard keeps a signal instead of raising it: nothing may cut STOP or
    the close short.
    """
    try:
        guard.check()
        ending, tail_s = stream_until_end(sess, config)
        guard.defer()
    except SIGNAL_EXCEPTIONS as exc:  # as the stream was ending
        ending, tail_s = Ending(signal_reason(exc)), 0.0
        guard.defer()
    return ending, tail_s


def send_stop(sess: Any, ending: Ending, keep_receiving_s: float,
              settling: bool) -> tuple[Ending, bool]:
    """Send STOP, keep ``keep_receiving_s`` [s] of telemetry; after silence, probe for a restart.

    Returns the ending (``controller_reset`` when the controller restarted) and whether the
    wheels are still to be waited for: not after a signal that the STOP raised (where no guard
    defers signals: not the main thread, ``handle_sigterm`` off). With ``settling`` (episodes
    to come) that signal ends the run; without, it cut the tail, a courtesy, short and the run
    keeps its reason.
    """
    try:
        sess.stop(keep_receiving_s)
        if isinstance(ending.error, TelemetrySilenceError):  # a restart or a lost link
            why = sess.restarted()
            if why is not None:
                ending = replace(ending, reason="controller_reset", message=why)
    except SIGNAL_EXCEPTIONS as exc:
        if settling:
            ending = replace(ending, reason=signal_reason(exc))
        settling = False
    return ending, settling


def settle_after_stop(guard: SignalGuard, settle: Callable[[], None],
                      ending: Ending) -> tuple[Ending, bool]:
    """Wait for rest after STOP (``settle``), the one wait a signal may cut short.

    Returns the ending and whether STOP is to be sent again: after a signal (which ends the
    run as ``interrupted`` or ``terminated``). A link error ends it as ``link_lost`` (only
    settling receives on its own: STOP never raises), anything else as ``error``.
    """
    try:
        with guard.raising():
            settle()
    except SIGNAL_EXCEPTIONS as exc:
        return replace(ending, reason=signal_reason(exc)), True
    except LinkError as err:
        return Ending("link_lost", str(err), err), False
    except Exception as err:  # a row that cannot be written while settling, ...
        return Ending("error", str(err), err), False
    return ending, False


def ending_of_failure(ending: Ending, exc: BaseException) -> Ending:
    """The ending when ``exc`` (which no step took) leaves the stop path.

    The sidecar must not say the stream ran to its end: a signal (raised here where no guard
    defers it) gives its reason, anything else ``error``. An ending already cut short stays.
    """
    if not ending.ran_to_end:
        return ending
    if isinstance(exc, SIGNAL_EXCEPTIONS):
        return replace(ending, reason=signal_reason(exc))
    return replace(ending, reason="error", message=f"ended by {type(exc).__name__}: {exc}")


def stop_if_not_yet(sess: Any) -> BaseException | None:
    """Send STOP unless it was sent or tried already (an exception or a signal came first).

    Returns a signal's exception the STOP raised (kept, to be raised once the recording is
    closed), else None.
    """
    if sess.stop_attempted:
        return None
    try:
        sess.stop(0.0)
    except SIGNAL_EXCEPTIONS as exc:
        return exc
    return None


def close_observers(sess: Any) -> BaseException | None:
    """Close the observers' thread; returns a signal's exception that landed meanwhile.

    Any other failure is ignored: the recording is closed all the same.
    """
    try:
        sess.pump.close()
    except SIGNAL_EXCEPTIONS as exc:
        return exc
    except Exception:
        pass
    return None


def end_metadata(sess: Any, transport: Transport, reason: str, message: str,
                 latency: dict[str, float]) -> dict[str, Any]:
    """The sidecar's keys known once the stream has ended: how, and what the link did."""
    result_meta = {"end_reason": reason, "exit_code": EXIT_CODES[reason],
                   "link_stats": transport.stats.as_dict(), "latency_ms": latency,
                   "link_events": sess.events,
                   **transport.link_metadata(),
                   "invalid_readings": sess.invalid_readings,
                   "run_checks": {
                       "invalid_samples": sess.invalid_samples,
                       "longest_invalid_s": round(sess.longest_invalid_s, 6),
                       "clock_drift_s": round(sess.clock_drift_s, 6),
                       "widest_command_gap_s": round(sess.widest_command_gap_s, 6),
                       "unacknowledged_commands": len(sess._acks)},
                   "controller": sess.controller,
                   "controller_wheel_limit_rpm": (sess.wheel_limit_rpm
                                                  if math.isfinite(sess.wheel_limit_rpm)
                                                  else None),
                   "telemetry_rate_hz": sess.telemetry_rate_hz,
                   # the recording's sample rate is the telemetry's (commands interleave)
                   "sample_rate_hz": sess.telemetry_rate_hz or None}
    if message:
        result_meta["end_message"] = message
    return result_meta


def end_metadata_or_fallback(sess: Any, transport: Transport, ending: Ending,
                             latency: dict[str, float],
                             end_extra: Callable[[], dict[str, Any]] | None
                             ) -> tuple[dict[str, Any], BaseException | None]:
    """The sidecar's end, written whatever failed (or was cut short) in making it.

    Returns the keys (the reason, exit code and what failed when making them failed) and a
    signal's exception that landed meanwhile, else None.
    """
    try:
        meta = end_metadata(sess, transport, ending.reason, ending.message, latency)
        if end_extra is not None:
            meta.update(end_extra())
    except (*SIGNAL_EXCEPTIONS, Exception) as err:
        late = err if isinstance(err, SIGNAL_EXCEPTIONS) else None
        return {"end_reason": ending.reason, "exit_code": EXIT_CODES[ending.reason],
                "end_message": f"{ending.message} (end metadata failed: {err!r})"}, late
    return meta, None


def close_recording(sess: Any, transport: Transport, writer: RecordingWriter,
                    guard: SignalGuard, ending: Ending,
                    end_extra: Callable[[], dict[str, Any]] | None) -> Closed:
    """STOP if not sent yet, close the observers, write the sidecar's end; handlers back.

    Without a guard (``handle_sigterm`` off, not the main thread) a signal raises where it
    lands: one that lands in the fallback STOP, the observers' close or the end's metadata is
    kept in :attr:`Closed.late`, not raised in place of the close.
    """
    try:
        guard.defer()
        late = stop_if_not_yet(sess)
        late_close = close_observers(sess)
        late = late or late_close
        duration = 0.0 if sess.t0 is None else time.perf_counter() - sess.t0
        latency = {**percentiles_ms(sess.rtt, "rtt"), **percentiles_ms(sess.ack, "ack")}
        end_meta, late_meta = end_metadata_or_fallback(sess, transport, ending, latency,
                                                       end_extra)
        writer.close(end_meta)
    finally:
        guard.restore()
    return Closed(duration, latency, late or late_meta)


def result_of(sess: Any, transport: Transport, writer: RecordingWriter, out: str | Path,
              ending: Ending, closed: Closed, guard: SignalGuard) -> RecordResult:
    """The session's result; an ``error`` without its own exception takes an observer's."""
    error = ending.error
    if sess.pump.error is not None and ending.reason == "error" and error is None:
        error = sess.pump.error
    exit_code = EXIT_CODES[ending.reason]
    if ending.reason == "error" and isinstance(error, MecanumHILError):
        exit_code = error.exit_code
    return RecordResult(ending.reason, exit_code, Path(out), writer.rows, sess.commands_sent,
                        sess.telemetry, closed.duration_s, transport.stats.as_dict(),
                        closed.latency_ms, ending.message, sess.pump.dropped, sess.controller,
                        error, guard.pending)


def stream_stop_close(sess: Any, transport: Transport, writer: RecordingWriter,
                      out: str | Path, config: SessionConfig, *,
                      settle: Callable[[], None] | None = None,
                      cut_short: Callable[[str], None] | None = None,
                      end_extra: Callable[[], dict[str, Any]] | None = None) -> RecordResult:
    """Run ``sess`` to its end, STOP at every way out, close the recording; the result.

    Parameters
    ----------
    settle : callable, optional
        After the STOP of a completed stream, in place of keeping ``config.tail_s`` of
        telemetry (``record --policy`` waits for the wheels to come to rest). A Ctrl-C or
        SIGTERM in it ends the run as ``interrupted`` (STOP again), a link error as
        ``link_lost``.
    cut_short : callable, optional
        ``cut_short(reason)`` before the STOP of a stream that did not complete.
    end_extra : callable, optional
        Keys added to the sidecar's end (called as the recording is closed).
    """
    ending, failing = Ending(), None  # failing: an exception on its way out of the stream
    guard = SignalGuard(config.handle_sigterm)
    try:
        ending, tail_s = end_stream(sess, config, guard)
        ran_to_end = ending.ran_to_end
        if not ran_to_end and cut_short is not None:
            cut_short(ending.reason)
        # every way out: STOP first, then the recording is closed cleanly
        ending, settling = send_stop(sess, ending, tail_s if settle is None else 0.0,
                                     settle is not None)
        if settling and ran_to_end and sess.t0 is not None:
            ending, stop_again = settle_after_stop(guard, settle, ending)
            if stop_again:
                sess.stop(0.0)
    except BaseException as exc:  # what no step takes (SystemExit, a callback's)
        guard.defer()  # nothing may cut STOP or the close short from here
        failing, ending = exc, ending_of_failure(ending, exc)
        raise
    finally:
        closed = close_recording(sess, transport, writer, guard, ending, end_extra)
        # not in place of an exception already on its way out: STOP has gone out
        if closed.late is not None and failing is None:
            raise closed.late
    return result_of(sess, transport, writer, out, ending, closed, guard)
