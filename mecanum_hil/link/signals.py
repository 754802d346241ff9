"""Turning SIGTERM, SIGHUP, SIGINT and the other ending signals into clean stops.

A command stream must never end with the robot still commanded to move: a signal that would
end the process is turned into an exception while the stream runs (``KeyboardInterrupt`` for
Ctrl-C, :class:`~mecanum_hil.errors.SessionTerminated` for the others), so that the stream's
way out sends STOP; while STOP is sent and the recording closed, a signal is kept instead
(:class:`SignalGuard`). Used by the record session (:mod:`mecanum_hil.link.session`), the
policy episodes and the conformance run.
"""

from __future__ import annotations

import signal
import threading
from contextlib import contextmanager
from typing import Any

from ..errors import SessionTerminated

#: Signals that end a command stream, each of which would otherwise end the process with no
#: STOP: SIGTERM (kill, a service manager), SIGHUP (a closed terminal or SSH session) and
#: SIGINT (Ctrl-C) always; SIGQUIT (Ctrl-\) and the others that terminate by default where
#: nothing else handles them. SIGKILL cannot be caught: the controller's watchdog stops then.
ENDING_SIGNALS = ("SIGTERM", "SIGHUP", "SIGINT", "SIGQUIT", "SIGUSR1", "SIGUSR2", "SIGALRM",
                  "SIGXCPU", "SIGVTALRM", "SIGPROF")


def signal_reason(exc: BaseException) -> str:
    """The end reason of a signal's exception: ``interrupted`` for Ctrl-C, else
    ``terminated``."""
    return "interrupted" if isinstance(exc, KeyboardInterrupt) else "terminated"


def signal_end_reason(signum: int) -> str:
    """The end reason of a signal kept by a :class:`SignalGuard` (as :func:`signal_reason`)."""
    return "interrupted" if signum == signal.SIGINT else "terminated"


def _signal_exception(signum: int) -> BaseException:
    """What a signal raises in a stream: ``KeyboardInterrupt`` for Ctrl-C, else
    :class:`SessionTerminated`."""
    return KeyboardInterrupt() if signum == signal.SIGINT else SessionTerminated()


class SignalGuard:
    """The stream's signal handlers, from its start until its recording is closed.

    While raising (the stream runs), the first signal of :data:`ENDING_SIGNALS` ends it:
    SIGINT raises ``KeyboardInterrupt`` (also where the process was started with SIGINT
    ignored: Python then installs no handler, and Ctrl-C did nothing while the robot drove
    on), the others :class:`SessionTerminated`. After that, and once :meth:`defer` is called
    (STOP and the close), a signal is kept in :attr:`pending` and nothing is raised: a second
    Ctrl-C used to land in the close and lose the sidecar's end. Installed only in the main
    thread and when ``active``; guards nest (the inner restores the outer's handlers).

    Parameters
    ----------
    active : bool
        Install the handlers (``SessionConfig.handle_sigterm``).
    """

    def __init__(self, active: bool = True) -> None:
        self.pending: int | None = None
        # installed keeping signals: one that comes while the handlers go in is raised by
        # check() inside the caller's try, not out of this constructor (handlers orphaned)
        self._raise = False
        self._saved: dict[int, Any] = {}
        if active and threading.current_thread() is threading.main_thread():
            for name in ENDING_SIGNALS:
                sig = getattr(signal, name, None)
                if sig is None:
                    continue
                current = signal.getsignal(sig)
                if (name not in ("SIGTERM", "SIGHUP", "SIGINT") and current is not signal.SIG_DFL
                        and getattr(current, "__func__", None) is not SignalGuard._on_signal):
                    continue  # someone else handles (or ignores) it; an outer guard's we take
                self._saved[sig] = signal.signal(sig, self._on_signal)
        self._raise = True

    def check(self) -> None:
        """Raise a signal kept so far (while raising), as its handler would have."""
        if self.pending is not None and self._raise:
            signum, self.pending = self.pending, None
            self._raise = False
            raise _signal_exception(signum)

    def _on_signal(self, signum, frame) -> None:
        if not self._raise:
            self.pending = self.pending or signum
            return
        self._raise = False  # once: the way out that follows must not be cut short
        self.pending = None
        raise _signal_exception(signum)

    def defer(self) -> None:
        """From now on keep a signal in :attr:`pending` instead of raising."""
        self._raise = False

    def rearm(self) -> None:
        """Raise again from now on; a signal kept meanwhile is raised at once."""
        self._raise = True
        self.check()

    @contextmanager
    def raising(self):
        """Raise again while inside (a wait after STOP that a signal may cut short); a signal
        already pending is raised on entry."""
        if self.pending is not None:
            signum, self.pending = self.pending, None
            raise _signal_exception(signum)
        self._raise = True
        try:
            yield
        finally:
            self._raise = False

    def restore(self) -> None:
        """Put back the handlers found at the start."""
        for sig, handler in self._saved.items():
            signal.signal(sig, handler)
        self._saved.clear()

