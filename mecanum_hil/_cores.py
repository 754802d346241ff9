"""How many cores other jobs leave free, and how many threads the native libraries take of them.

:func:`idle_cores` is the rule by which a stage decides to work beside itself
(``measure-video`` decoding in a helper thread, ``diagnose`` fitting candidates in a helper
process). The BLAS and OpenMP thread pools are this module's too: :data:`SINGLE_THREAD_ENV`
is the environment of a process started to step one robot or run one task (one thread per
pool), and :func:`one_blas_thread` runs OpenBLAS on one thread inside a block of this process.
The process's own default, ``OPENBLAS_NUM_THREADS=1`` unless the user set
it, is set by the package's ``__init__``: the earliest point, before numpy loads OpenBLAS.
"""

from __future__ import annotations

import math
import os
import threading
import time
from contextlib import contextmanager
from typing import Any

#: Idle cores (beyond this process's own) from which a stage works beside itself: half a core,
#: i.e. a 1-minute load average of the other jobs up to 0.5 on two cores. Measured for
#: measure-video: with another job busy on the second core (load 1) decoding beside was 0-10 %
#: slower than in turns; asking for a whole idle core (load 0.00) left an idle desktop's 0.1 in
#: turns. diagnose's helper process follows the same rule.
SPARE_CORE = 0.5

#: This process's share of the load average as last computed, with the wall and CPU clocks
#: then [s] (from the package's import, when it was 0).
_own = [0.0, time.monotonic(), time.process_time()]
_own_lock = threading.Lock()


def own_load() -> float:
    """This process's own share of the 1-minute load average, kept the way the kernel keeps
    the load: an average damped with a 60-s time constant of how busy this process was
    (its CPU time over the wall time) since the last call; a busy script that diagnoses one
    recording after another must not count itself as another job, and one that has been idle
    for minutes counts for little."""
    with _own_lock:
        now, cpu = time.monotonic(), time.process_time()
        wall = now - _own[1]
        if wall > 0.0:
            busy = min(1.0, max(0.0, (cpu - _own[2]) / wall))
            decay = math.exp(-wall / 60.0)
            _own[:] = [_own[0] * decay + busy * (1.0 - decay), now, cpu]
        return _own[0]


def usable_cores() -> int:
    """Cores this process may run on (its CPU affinity on Linux, else the machine's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def idle_cores() -> float:
    """Cores this process may run on beyond its own one that other jobs leave free: the count
    less the 1-minute load average of the others (all of them where the load is unknown).

    The load average trails by a minute: a job that ended seconds ago (the ``fit`` before a
    ``diagnose``, the recording before it) still counts. Where it says fewer than
    :data:`SPARE_CORE` are free, how busy the machine's cores are now is read too (over
    :data:`NOW_WINDOW_S`, at most every :data:`NOW_EVERY_S`; Linux's ``/proc/stat``), and
    the larger count of free cores is taken: a job that is still running shows in both.
    """
    cores = usable_cores()
    try:
        load = os.getloadavg()[0]
    except (AttributeError, OSError):  # Windows
        load = 0.0
    by_load = cores - 1 - max(0.0, load - own_load())
    if by_load >= SPARE_CORE or cores - 1 < SPARE_CORE:  # free, or no second core at all
        return by_load
    busy = busy_cores_now()
    return by_load if busy is None else max(by_load, cores - 1 - busy)


#: The window over which :func:`busy_cores_now` reads the cores' use [s], and how long a
#: reading is kept [s].
NOW_WINDOW_S = 0.2
NOW_EVERY_S = 5.0

_now: list = [None, -math.inf]  # the last reading of busy_cores_now, and when it was taken


def busy_cores_now() -> float | None:
    """Cores of this process's own (its CPU affinity) that other jobs keep busy now: their CPU
    time outside idle over :data:`NOW_WINDOW_S` (``/proc/stat``'s lines per core), less this
    process's own, in cores; None where it cannot be read. A reading is kept for
    :data:`NOW_EVERY_S`."""
    with _own_lock:
        if time.monotonic() - _now[1] < NOW_EVERY_S:
            return _now[0]
    busy = None
    try:
        mine = _affinity()
        before, cpu0, t0 = _cpu_times(mine), time.process_time(), time.monotonic()
        time.sleep(NOW_WINDOW_S)
        after, cpu1, t1 = _cpu_times(mine), time.process_time(), time.monotonic()
    except (OSError, ValueError, IndexError):
        pass
    else:
        shares = [(a[1] - b[1]) / (a[0] - b[0]) for b, a in zip(before, after, strict=True)
                  if a[0] > b[0]]
        if shares and t1 > t0:
            busy = max(0.0, sum(shares) - (cpu1 - cpu0) / (t1 - t0))
    with _own_lock:
        _now[:] = [busy, time.monotonic()]
    return busy


def _affinity() -> set[int] | None:
    """The cores this process may run on (None: all, where the affinity is unknown)."""
    try:
        return set(os.sched_getaffinity(0))
    except AttributeError:
        return None


def _cpu_times(cores: set[int] | None) -> list[tuple[int, int]]:
    """Per core of ``cores`` (all where None): CPU time since boot and the part of it not idle
    (nor waiting for I/O), in jiffies (``/proc/stat``'s ``cpuN`` lines)."""
    out = []
    with open("/proc/stat", encoding="ascii") as f:
        for line in f:
            name, *values = line.split()
            if not (name.startswith("cpu") and name[3:].isdigit()):
                continue
            if cores is not None and int(name[3:]) not in cores:
                continue
            fields = [int(v) for v in values]
            # user nice system idle iowait irq softirq steal (guest time is inside user)
            total = sum(fields[:8])
            out.append((total, total - fields[3] - fields[4]))
    if not out:
        raise ValueError("no per-core lines in /proc/stat")
    return out


#: Environment of a child process that steps one robot or runs one task beside others (a
#: simulated controller, a worker of the local cluster): one thread each for numba, OpenMP,
#: OpenBLAS and MKL, so that nested thread pools do not oversubscribe a small machine.
SINGLE_THREAD_ENV = {"NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1",
                     "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


#: ``openblas_set_num_threads`` / ``..._get_...`` under the names OpenBLAS builds export.
_BLAS_SYMBOLS = (("openblas_set_num_threads", "openblas_get_num_threads"),
                 ("openblas_set_num_threads64_", "openblas_get_num_threads64_"),
                 ("scipy_openblas_set_num_threads64_", "scipy_openblas_get_num_threads64_"),
                 ("scipy_openblas_set_num_threads", "scipy_openblas_get_num_threads"))
_blas_lock = threading.Lock()
_blas_depth = 0
_blas_saved: list[tuple[Any, int]] = []


def _openblas_controls() -> list[tuple[Any, Any]]:
    """(set, get) thread-count functions of every OpenBLAS loaded in this process (numpy's and
    scipy's are separate libraries); none where ``/proc/self/maps`` is not there."""
    import ctypes

    try:
        with open("/proc/self/maps") as f:
            paths = sorted({line.split()[-1] for line in f if ".so" in line
                            and "openblas" in line.rsplit("/", 1)[-1].lower()})
    except OSError:
        return []
    out = []
    for path in paths:
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for set_name, get_name in _BLAS_SYMBOLS:
            if hasattr(lib, set_name) and hasattr(lib, get_name):
                out.append((getattr(lib, set_name), getattr(lib, get_name)))
                break
    return out


@contextmanager
def one_blas_thread():
    """Run OpenBLAS on one thread inside (re-entrant; the counts are restored after).

    A fit's linear algebra is many small products of a tall Jacobian; OpenBLAS spreads each
    over its threads, whose waiting spins take the cores the simulator needs: on the 2-core
    machine of ``docs/benchmarks/diagnose.md`` a campaign's diagnosis took 2.7 x the CPU time
    with OpenBLAS's default threads. One thread also makes the sums' order, and so the fitted
    values, the same on every machine.
    """
    global _blas_depth
    with _blas_lock:
        if _blas_depth == 0:
            _blas_saved.clear()
            for set_threads, get_threads in _openblas_controls():
                try:
                    _blas_saved.append((set_threads, int(get_threads())))
                    set_threads(1)
                except (OSError, ValueError, TypeError):  # pragma: no cover - odd builds
                    continue
        _blas_depth += 1
    try:
        yield
    finally:
        with _blas_lock:
            _blas_depth -= 1
            if _blas_depth == 0:
                for set_threads, count in _blas_saved:
                    set_threads(count)
                _blas_saved.clear()
