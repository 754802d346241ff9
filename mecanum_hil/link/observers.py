"""Observers of a running session (shadow mode) and the pump that feeds them.

Observers see every telemetry sample (and, when they take them, every command) on their own
thread, through a bounded queue: a slow observer never delays a command, and the samples it
could not keep up with are dropped and counted (:attr:`ObserverPump.dropped`). An observer
asks the session to stop with ``stop_requested``; the session then raises
:class:`ObserverStopError` and ends with STOP and reason ``observer_stop``.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Sequence
from typing import Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class TelemetryObserver(Protocol):
    """Something that watches the telemetry of a running session (e.g. shadow mode).

    ``on_telemetry`` is called on the session's observer thread, in order, once per telemetry
    sample: ``t_s`` host receive time since the first command [s], ``commands`` the
    ``(n [rpm], omega [deg/s], theta [deg])`` in force as sent, shape (3,), ``wheel_rpm`` the
    reported wheel speeds 1..4 [rpm], shape (4,). It must not keep the arrays (they are not
    reused, but copying is cheap). The session reads ``stop_requested`` before every command;
    once it is true the session sends STOP and ends with reason ``observer_stop`` (exit 3).
    An exception raised by an observer ends the session with reason ``error``.

    Optionally an observer also defines ``on_command(t_s, commands)``: it is then told every
    command (and the final stop) at its actual send time, in order with the telemetry, and its
    ``on_telemetry`` receives ``controller_time_s=`` (the controller's clock for the sample [s]),
    which lets it time samples by the controller instead of by a possibly stalled host.
    """

    stop_requested: bool

    def on_telemetry(self, t_s: float, commands: np.ndarray, wheel_rpm: np.ndarray) -> None:
        """See the class docstring."""



class ObserverPump:
    """Feeds observers on their own thread so they never slow the command stream.

    Parameters
    ----------
    observers : sequence of TelemetryObserver
        Fed in order; none starts no thread.
    maxlen : int
        Items buffered before the oldest are dropped (``SessionConfig.observer_queue``).

    Attributes
    ----------
    dropped : int
        Items the observers did not see because they lagged.
    error : BaseException or None
        What an observer raised (the thread then stops; the session ends with ``error``).
    """

    def __init__(self, observers: Sequence[TelemetryObserver], maxlen: int) -> None:
        self.observers = list(observers)
        self._queue: deque = deque(maxlen=maxlen)
        self._event = threading.Event()
        self._done = False
        self.dropped = 0
        self.error: BaseException | None = None
        self._thread = None
        if self.observers:
            self._thread = threading.Thread(target=self._run, name="telemetry-observers",
                                            daemon=True)
            self._thread.start()

    def _put(self, item: tuple) -> None:
        if self._thread is None:
            return
        if len(self._queue) == self._queue.maxlen:
            self.dropped += 1
        self._queue.append(item)
        self._event.set()

    def push(self, t_s: float, commands: np.ndarray, wheels: np.ndarray,
             controller_time_s: float | None = None) -> None:
        """A telemetry sample for the observers."""
        self._put((t_s, commands, wheels, controller_time_s))

    def push_command(self, t_s: float, commands: np.ndarray) -> None:
        """A command as sent, for the observers that take commands."""
        self._put((t_s, commands, None, None))

    @property
    def stop_requested(self) -> bool:
        """Whether an observer asks the session to stop."""
        return any(getattr(o, "stop_requested", False) for o in self.observers)

    def _run(self) -> None:
        """The observers' thread: hand each queued item to every observer, in order."""
        while True:
            self._event.wait(0.05)
            self._event.clear()
            while self._queue:
                t_s, cmd, wheels, ctrl_t = self._queue.popleft()
                for obs in self.observers:
                    try:
                        takes_commands = hasattr(obs, "on_command")
                        if wheels is None:
                            if takes_commands:
                                obs.on_command(t_s, cmd)
                        elif takes_commands:
                            obs.on_telemetry(t_s, cmd, wheels, controller_time_s=ctrl_t)
                        else:
                            obs.on_telemetry(t_s, cmd, wheels)
                    except Exception as err:  # reported by the session, which then stops
                        self.error = err
                        return
            if self._done:
                return

    def close(self, timeout_s: float = 2.0) -> None:
        """Let the observers take what is queued, then stop the thread (wait ``timeout_s``
        [s] at most)."""
        if self._thread is not None:
            self._done = True
            self._event.set()
            self._thread.join(timeout_s)



class ObserverStopError(Exception):
    """An observer asked the session to stop (reason ``observer_stop``)."""
