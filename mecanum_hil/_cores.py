"""How many cores other jobs leave free: the rule by which a stage decides to work beside itself
(``measure-video`` decoding in a helper thread, ``diagnose`` fitting candidates in a helper
process)."""

from __future__ import annotations

import math
import os
import threading
import time

#: Idle cores (beyond this process's own) from which a stage works beside itself: half a core,
#: i.e. a 1-minute load average of the other jobs up to 0.5 on two cores. Measured for
#: measure-video: with another job busy on the second core (load 1) decoding beside was 0-10 %
#: slower than in turns; asking for a whole idle core (load 0.00) left an idle desktop's 0.1 in
#: turns (review, 2026-11-23). diagnose's helper process follows the same rule.
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
    less the 1-minute load average of the others (all of them where the load is unknown)."""
    cores = usable_cores()
    try:
        load = os.getloadavg()[0]
    except (AttributeError, OSError):  # Windows
        load = 0.0
    return cores - 1 - max(0.0, load - own_load())
