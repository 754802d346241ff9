"""A second process that fits candidates beside this one.

Each round of :mod:`.selection` fits every candidate of the library on its own (the model so far
plus one effect): independent jobs, each a few hundred milliseconds to seconds. On a machine
with a core to spare, a helper process takes the costliest job left while this process works
through the others, so a round takes about half the time on two cores.

Why a process started with ``python -c`` and pickles over its pipes, and not
:mod:`multiprocessing`: forking a process whose numba kernels have started OpenMP threads is
unsafe, and the ``spawn`` and ``forkserver`` methods import the user's main script again in
the child (running it, where it lacks an ``if __name__ == "__main__"`` guard). The helper
imports this package and nothing else.

The helper is only ever an accelerator: the same functions on the same pickled inputs, numba
compiled in both processes (``MECANUM_HIL_JIT=always`` there, as this process is once a fit has
run), OpenBLAS on one thread in both, so the results are the same as in this process. Whatever
goes wrong with it (it fails to start, dies, returns an error, does not answer in time) the
job is run here instead; a helper that failed is stopped and not used again (a new one may be
started by the next diagnosis), one that is late is given no more jobs until it answers.

The helper's side is :func:`_serve`: it reads ``(function, args)`` pickles from stdin until it
closes and answers each with ``("ok", result)`` or ``("error", text)`` on stdout.
"""

from __future__ import annotations

import atexit
import os
import pickle
import queue
import signal
import subprocess
import sys
import threading
import warnings
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any

from ..._cores import SPARE_CORE, idle_cores, usable_cores
from ...errors import MecanumHILWarning

#: Idle cores (beyond this process's own: :func:`~mecanum_hil._cores.idle_cores`) from which
#: ``diagnose`` starts a helper by default: the package's rule for working beside itself
#: (:data:`mecanum_hil._cores.SPARE_CORE`, half a core, as measure-video decodes beside its
#: analysis). A helper costs about 1.3 s of CPU to start (imports, numba's kernels loaded), on
#: the other core.
HELPER_IDLE_CORES = SPARE_CORE

#: Seconds a helper is given to finish its current job when this process exits.
_EXIT_WAIT_S = 1.0


class Helper:
    """One helper process; :meth:`submit` sends it a job, :meth:`ready` says it has started.

    Parameters
    ----------
    warm : callable, optional
        A first job to run (a small simulation: loads numba's compiled kernels), whose end
        marks the helper ready.
    """

    def __init__(self, warm: Callable[[], Any] | None = None):
        # this package from where this process has it, whatever the helper's working folder
        root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(
            os.path.abspath(__file__)))))
        path = os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH", "")) if p)
        # compiled as this process is once a fit has run (unless the user asked for never)
        jit = "never" if os.environ.get("MECANUM_HIL_JIT", "").strip().lower() == "never" \
            else "always"
        # a core of its own beside the diagnosing process: numba's kernels on one thread
        env = dict(os.environ, MECANUM_HIL_JIT=jit, PYTHONPATH=path, NUMBA_NUM_THREADS="1")
        self._proc = subprocess.Popen(
            [sys.executable, "-c", f"from {__name__} import _serve; _serve()"],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env)
        self._lock = threading.Lock()
        self._waiting: list[Future] = []
        #: Pickled jobs for the writing thread; None ends it (and closes the helper's stdin).
        self._outbox: queue.SimpleQueue[bytes | None] = queue.SimpleQueue()
        self.broken = False
        #: Jobs answered (the warm-up included).
        self.answered = 0
        threading.Thread(target=self._read, name="diagnose-helper-read", daemon=True).start()
        threading.Thread(target=self._write, name="diagnose-helper-write", daemon=True).start()
        self._warm = self.submit(warm) if warm is not None else None

    def ready(self) -> bool:
        """True once the helper has started (its warm-up job done) and works."""
        return not self.broken and (self._warm is None or (
            self._warm.done() and self._warm.exception() is None))

    def idle(self) -> bool:
        """True when the helper is ready and holds no job."""
        with self._lock:
            return self.ready() and not self._waiting

    def pending(self) -> list[Future]:
        """The jobs sent and not yet answered, in the order sent."""
        with self._lock:
            return list(self._waiting)

    def submit(self, fn: Callable[..., Any], *args: Any) -> Future:
        """Run ``fn(*args)`` in the helper (``fn`` a module-level function); the future holds
        its result, or an exception when the helper failed."""
        fut: Future = Future()
        try:
            # pickled before the job is queued: a job that does not pickle is this caller's
            data = pickle.dumps((fn, args), protocol=pickle.HIGHEST_PROTOCOL)
        except (pickle.PicklingError, AttributeError, TypeError) as err:
            fut.set_exception(RuntimeError(f"cannot hand the job over: {err}"))
            return fut
        with self._lock:
            if self.broken:
                fut.set_exception(RuntimeError("the helper process is not running"))
                return fut
            self._waiting.append(fut)
        # sent by a thread of its own: a helper that has stopped reading (stalled, its pipe
        # full) never blocks the diagnosis
        self._outbox.put(data)
        return fut

    def _write(self) -> None:
        """Jobs to the helper's stdin, in the order submitted; closes it at the end."""
        pipe = self._proc.stdin
        while (data := self._outbox.get()) is not None:
            try:
                pipe.write(data)
                pipe.flush()
            except (OSError, ValueError) as err:
                self.stop(err)
                return
        try:
            pipe.close()
        except (OSError, ValueError):
            pass

    def stop(self, err: BaseException | str) -> None:
        """Stop using the helper: every job it holds fails with ``err`` and its process is
        killed (it may be stuck, or answering nonsense)."""
        with self._lock:
            self._break_locked(err)
        try:
            self._proc.kill()
        except OSError:
            pass

    def _read(self) -> None:
        """Answers, in the order the jobs went out, until the helper's stdout closes."""
        while True:
            try:
                status, value = pickle.load(self._proc.stdout)
            except Exception as err:  # EOF, a broken pipe, an answer that does not unpickle
                self.stop(err)
                return
            with self._lock:
                fut = self._waiting.pop(0) if self._waiting else None
                self.answered += 1
            if fut is None:
                continue
            if status == "ok":
                fut.set_result(value)
            else:
                fut.set_exception(RuntimeError(f"the helper failed: {value}"))

    def _break_locked(self, err: BaseException | str) -> None:
        """Mark the helper unusable and fail every job it still holds (lock held)."""
        self.broken = True
        waiting, self._waiting = self._waiting, []
        for fut in waiting:
            if not fut.done():
                fut.set_exception(RuntimeError(f"the helper process stopped: {err}"))

    def close(self) -> None:
        """End the helper: its stdin closed once the jobs already sent are written, then
        killed if it has not exited within :data:`_EXIT_WAIT_S` (it may be in the middle of
        a job, or stalled)."""
        with self._lock:
            self._break_locked("the helper was closed")
        self._outbox.put(None)
        try:
            self._proc.wait(_EXIT_WAIT_S)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()


_shared: Helper | None = None
_shared_lock = threading.Lock()


def helpers_for(jobs: int | None, warm: Callable[[], Any] | None = None) -> list[Helper]:
    """The helpers a diagnosis may use: ``jobs - 1`` of them (``jobs`` processes in all, this
    one included); ``None``: the one this process has started, or one where
    :data:`HELPER_IDLE_CORES` are free, else none.

    One helper is kept for the life of this process (and ended when it exits): the second
    diagnosis of a batch in the same process finds it started. More than one are started for
    the call and ended by :func:`release`.
    """
    global _shared
    if jobs is None:
        # a helper this process started is kept (its own load is this process's work);
        # otherwise one where a core is idle
        started = _shared is not None and not _shared.broken
        want = 1 if started or idle_cores() >= HELPER_IDLE_CORES else 0
    else:
        cores = usable_cores()
        if jobs > cores:
            # a process per core at most: more only wait for one another (64 took 30 x longer
            # than 1), each costing a second of CPU to start
            warnings.warn(f"--jobs {jobs}: this process may use {cores} cores: {cores} "
                          "processes", MecanumHILWarning, stacklevel=2)
        want = max(0, min(jobs, cores) - 1)
    if want == 0:
        return []
    out: list[Helper] = []
    with _shared_lock:
        if _shared is not None and _shared.broken:
            _shared.close()
            _shared = None
        if _shared is None:
            try:
                _shared = Helper(warm)
            except OSError:  # cannot start a process here: this one does the work
                return []
            atexit.register(_shared.close)
        out.append(_shared)
    for _ in range(want - 1):
        try:
            out.append(Helper(warm))
        except OSError:
            break
    return out


def release(helpers: list[Helper], interrupted: bool = False) -> None:
    """End the helpers :func:`helpers_for` started for one call (the shared one stays); after
    an interrupted diagnosis (Ctrl-C, SIGTERM) kill them all at once, the shared one included
    (their jobs are of no use; a later diagnosis starts a new one)."""
    for h in helpers:
        if interrupted:
            h.stop("interrupted")
        elif h is not _shared:
            h.close()


def _serve() -> None:
    """The helper's side: jobs from stdin, answers on stdout, until stdin closes."""
    # Ctrl-C in the terminal reaches the whole process group: the diagnosing process decides
    # (it closes the pipe, and the helper ends at the end of its job)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    answers = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)  # anything a job prints goes where stderr goes, never into the answers
    sys.stdout = sys.stderr
    from ..fit import one_blas_thread

    jobs = sys.stdin.buffer
    while True:
        try:
            fn, args = pickle.load(jobs)
        except EOFError:
            return
        try:
            with one_blas_thread():
                data = pickle.dumps(("ok", fn(*args)), protocol=pickle.HIGHEST_PROTOCOL)
        except Exception as err:
            data = pickle.dumps(("error", f"{type(err).__name__}: {err}"))
        try:
            answers.write(data)
            answers.flush()
        except OSError:
            return


def warm_up() -> None:
    """A helper's first job: numba's compiled kernels loaded, and a short simulation."""
    import numpy as np

    from ..._jit import load_compiled
    from ...model import Calibration, RobotProfile
    from ...model.simulate import simulate

    load_compiled("mecanum_hil.model._kernels")
    t = np.arange(50) * 0.01
    simulate(np.tile([60.0, 0.0, 90.0], (t.size, 1)), t, Calibration(), RobotProfile())
