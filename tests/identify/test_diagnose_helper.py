"""diagnose with a helper process: the same diagnosis, faster; a helper that fails costs nothing.

A helper is a real second process (``python -c``, pickles over its pipes:
``mecanum_hil/identify/diagnose/helper.py``). Each test waits until the helper has started
(its warm-up done) before diagnosing, so that it takes part whatever the machine's speed.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from mecanum_hil.identify.diagnose import diagnose
from mecanum_hil.identify.diagnose import helper as helper_mod
from mecanum_hil.identify.fit import fit
from mecanum_hil.io.recording import Recording
from mecanum_hil.model import Calibration, Effects, RobotProfile
from mecanum_hil.model.simulate import simulate

ROBOT = RobotProfile()
# two candidates that take part (breakaway and the wheels' gains are hidden) and two that do not
POOL = ("wheel_gain", "breakaway", "dead_time", "saturation")


def _step_recording() -> Recording:
    """A 2-s, 500 Hz step of the model with a hidden breakaway and per-wheel gains, 2 rpm of
    noise (bench/bench_diagnose.py's case)."""
    t = np.arange(1001) / 500.0
    cmd = np.tile([0.0, 0.0, 90.0], (t.size, 1))
    cmd[10:, 0] = 200.0
    truth = Calibration(A=3.0, B=8.0, C=500.0, effects=Effects(
        breakaway_rpm_per_s=4000.0, gains=(0.9, 0.95, 1.0, 1.0)))
    w = simulate(cmd, t, truth, ROBOT).wheel_rpm[0]
    w = w + np.random.default_rng(0).normal(0.0, 2.0, w.shape)
    return Recording(t, cmd, w, np.full((t.size, 3), np.nan))


def _wait(h: helper_mod.Helper, until: str, limit_s: float) -> None:
    """Wait until ``h.<until>()`` (``ready``: started; ``idle``: every job sent answered)."""
    deadline = time.monotonic() + limit_s
    while not getattr(h, until)():
        assert time.monotonic() < deadline, f"the helper was not {until} within {limit_s} s"
        assert not h.broken, "the helper process failed"
        time.sleep(0.05)


def _started(jobs: int = 2) -> list[helper_mod.Helper]:
    helpers = helper_mod.helpers_for(jobs, helper_mod.warm_up)
    for h in helpers:
        _wait(h, "ready", 120.0)
    return helpers


def _diagnosed(rec, cal, jobs, echo=None):
    lines: list[str] = []

    def say(line: str) -> None:
        lines.append(line)
        if echo is not None:
            echo(line)

    d = diagnose([rec], cal, ROBOT, candidates=POOL, jobs=jobs, echo=say)
    return d.to_json(), lines


@pytest.fixture(scope="module")
def step_case():
    rec = _step_recording()
    return rec, fit([rec], ROBOT).calibration


def test_a_helper_gives_the_same_diagnosis(step_case):
    rec, cal = step_case
    alone, lines1 = _diagnosed(rec, cal, jobs=1)
    (h,) = _started()
    before = h.answered
    beside, lines2 = _diagnosed(rec, cal, jobs=2)
    # a job it was late with (numba compiling on a fresh checkout) also ran here
    _wait(h, "idle", 300.0)
    assert h.answered > before, "the helper fitted no candidate"
    assert json.dumps(beside, sort_keys=True) == json.dumps(alone, sort_keys=True)
    assert lines2 == lines1  # the same lines, in the pool's order
    assert [e["effect"] for e in alone["effects"]] == ["wheel_gain", "breakaway"]


def test_a_helper_that_dies_mid_diagnosis_costs_nothing(step_case):
    rec, cal = step_case
    alone, _ = _diagnosed(rec, cal, jobs=1)
    (h,) = _started()

    def kill_in_round_one(line: str) -> None:
        if line.startswith("round 1"):
            h._proc.kill()  # the helper gets its first job now and never answers it

    beside, _ = _diagnosed(rec, cal, jobs=2, echo=kill_in_round_one)
    assert json.dumps(beside, sort_keys=True) == json.dumps(alone, sort_keys=True)
    assert h.broken
    # the next diagnosis starts a new helper, and the broken one is gone
    (h2,) = _started()
    assert h2 is not h and not h2.broken
    assert h._proc.poll() is not None


def test_a_helper_that_stalls_costs_a_bounded_wait_not_a_hang(step_case):
    rec, cal = step_case
    alone, _ = _diagnosed(rec, cal, jobs=1)
    (h,) = _started()

    def stall_in_round_one(line: str) -> None:
        if line.startswith("round 1"):
            os.kill(h._proc.pid, signal.SIGSTOP)  # alive, holding its job, never answering

    try:
        beside, _ = _diagnosed(rec, cal, jobs=2, echo=stall_in_round_one)
    finally:
        os.kill(h._proc.pid, signal.SIGCONT)
        h.stop("test over")
    assert json.dumps(beside, sort_keys=True) == json.dumps(alone, sort_keys=True)


def test_own_load_follows_this_process_like_the_load_average():
    from mecanum_hil import _cores

    _cores.own_load()
    t0 = time.monotonic()
    while time.monotonic() - t0 < 0.5:  # busy
        pass
    busy = _cores.own_load()
    assert 0.0 < busy < 1.0
    time.sleep(0.5)  # idle: the share decays, as the kernel's average does
    assert _cores.own_load() < busy


@pytest.mark.skipif(not os.path.exists("/proc/stat"), reason="reads Linux's /proc/stat")
def test_a_core_another_job_keeps_busy_now_is_seen_at_once(monkeypatch):
    # the load average trails by a minute; what the cores do now is read over a short window
    from mecanum_hil import _cores

    monkeypatch.setattr(_cores, "_now", [None, -math.inf])
    spin = subprocess.Popen([sys.executable, "-c", "import time\nt = time.monotonic()\n"
                             "while time.monotonic() - t < 5: pass"])
    try:
        time.sleep(0.3)  # started and spinning
        assert _cores.busy_cores_now() >= 0.5
    finally:
        spin.kill()
        spin.wait()


def test_a_job_that_ended_seconds_ago_does_not_keep_the_helper_away(monkeypatch):
    from mecanum_hil import _cores

    monkeypatch.setattr(_cores, "usable_cores", lambda: 2)
    monkeypatch.setattr(_cores, "own_load", lambda: 0.0)
    monkeypatch.setattr(_cores.os, "getloadavg", lambda: (1.5, 1.0, 0.5))  # the last minute
    monkeypatch.setattr(_cores, "busy_cores_now", lambda: 0.0)  # idle now
    assert _cores.idle_cores() == 1.0
    monkeypatch.setattr(_cores, "busy_cores_now", lambda: 1.0)  # still running
    assert _cores.idle_cores() < _cores.SPARE_CORE
    monkeypatch.setattr(_cores, "busy_cores_now", lambda: None)  # unreadable: the load's
    assert _cores.idle_cores() < _cores.SPARE_CORE
    # one core: nothing to read
    monkeypatch.setattr(_cores, "usable_cores", lambda: 1)
    monkeypatch.setattr(_cores, "busy_cores_now", lambda: 1 / 0)
    assert _cores.idle_cores() < _cores.SPARE_CORE
    # a reading is kept for a few seconds (each diagnosis asks)
    monkeypatch.undo()
    monkeypatch.setattr(_cores, "_now", [0.25, time.monotonic()])
    assert _cores.busy_cores_now() == 0.25


def test_a_job_that_fails_in_the_helper_reports_the_error_and_the_helper_goes_on():
    (h,) = _started()
    fut = h.submit(int, "not a number")
    with pytest.raises(RuntimeError, match="the helper failed: ValueError"):
        fut.result(timeout=60)
    assert h.submit(max, 3, 4).result(timeout=60) == 4
    assert h.ready()


def test_jobs_1_starts_no_helper(monkeypatch):
    monkeypatch.setattr(helper_mod, "idle_cores", lambda: 8.0)
    assert helper_mod.helpers_for(1) == []
    monkeypatch.setattr(helper_mod, "idle_cores", lambda: 0.2)
    monkeypatch.setattr(helper_mod, "_shared", None)
    assert helper_mod.helpers_for(None) == []  # a busy machine: none by default


def test_more_jobs_than_cores_start_a_process_per_core_and_say_so(monkeypatch):
    # --jobs 64 on two cores started 63 helpers: 30 x slower than --jobs 1
    from mecanum_hil.errors import MecanumHILWarning

    started = []

    class Fake:
        broken = False

        def __init__(self, warm=None):
            started.append(self)

        def close(self):
            pass

    monkeypatch.setattr(helper_mod, "usable_cores", lambda: 3)
    monkeypatch.setattr(helper_mod, "Helper", Fake)
    monkeypatch.setattr(helper_mod, "_shared", None)
    monkeypatch.setattr(helper_mod.atexit, "register", lambda f: None)
    with pytest.warns(MecanumHILWarning, match="--jobs 64: this process may use 3 cores"):
        helpers = helper_mod.helpers_for(64)
    assert len(helpers) == len(started) == 2  # this process and two helpers
    monkeypatch.setattr(helper_mod, "_shared", None)


def test_a_script_without_a_main_guard_runs_once(tmp_path):
    """The helper imports the package only: a user's script that diagnoses at top level is not
    run again in it (as multiprocessing's spawn would)."""
    marker = tmp_path / "runs.txt"
    script = tmp_path / "user_script.py"
    script.write_text(textwrap.dedent(f"""
        import time

        import numpy as np
        from mecanum_hil.identify.diagnose import diagnose
        from mecanum_hil.identify.diagnose import helper
        from mecanum_hil.io.recording import Recording
        from mecanum_hil.model import Calibration, Effects, RobotProfile
        from mecanum_hil.model.simulate import simulate

        with open({str(marker)!r}, "a") as f:
            f.write("ran\\n")
        (h,) = helper.helpers_for(2, helper.warm_up)
        while not h.ready():
            assert not h.broken
        t = np.arange(400) / 100.0
        cmd = np.tile([0.0, 0.0, 90.0], (t.size, 1))
        cmd[20:, 0] = 60.0
        cmd[200:, 0] = -30.0
        truth = Calibration(A=14.7, B=16.1, C=303.0)
        hidden = Calibration(A=14.7, B=16.1, C=303.0, effects=Effects(dead_time_s=0.1))
        w = simulate(cmd, t, hidden, RobotProfile()).wheel_rpm[0]
        w = w + np.random.default_rng(1).normal(0.0, 0.5, w.shape)
        rec = Recording(t, cmd, w, np.full((t.size, 3), np.nan))
        diagnose([rec], truth, candidates=("dead_time", "saturation"), max_rounds=1, jobs=2)
        while not h.idle():  # a job it was late with also ran here; its answer comes later
            assert not h.broken
            time.sleep(0.05)
        print("helper answered", h.answered)
    """))
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                         timeout=300, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert marker.read_text() == "ran\n"
    assert int(out.stdout.split()[-1]) >= 2  # the warm-up and at least one candidate


def test_a_diagnosis_runs_no_kernel_in_the_interpreter(tmp_path):
    """In a fresh process small jobs run the kernels' Python source until numba is worth
    loading (mecanum_hil._jit): equal to rounding, but a search begun there can end in
    another minimum (testPid8 alone: 9.97 rpm; after another diagnosis in one process: 9.15).
    diagnose loads the compiled kernels first, so its result does not depend on what the
    process did before."""
    script = tmp_path / "fresh.py"
    script.write_text(textwrap.dedent("""
        import numpy as np
        from mecanum_hil import _jit
        from mecanum_hil.identify.diagnose import diagnose
        from mecanum_hil.io.recording import Recording
        from mecanum_hil.model import Calibration, Effects, RobotProfile
        from mecanum_hil.model.simulate import simulate

        t = np.arange(200) / 100.0
        cmd = np.tile([0.0, 0.0, 90.0], (t.size, 1))
        cmd[20:, 0] = 60.0
        hidden = Calibration(effects=Effects(gains=(0.9, 1.0, 1.0, 1.0)))
        w = simulate(cmd, t, hidden, RobotProfile()).wheel_rpm[0]  # small: interpreted
        spent = _jit._spent
        rec = Recording(t, cmd, w + np.random.default_rng(1).normal(0.0, 0.5, w.shape),
                        np.full((t.size, 3), np.nan))
        diagnose([rec], Calibration(), candidates=("wheel_gain",), max_rounds=1, jobs=1)
        print(spent > 0, _jit._spent == spent, _jit.is_compiled("mecanum_hil.model._kernels"))
    """))
    env = {**os.environ, "MECANUM_HIL_JIT": "auto"}
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                         timeout=300, cwd=tmp_path, env=env)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["True", "True", "True"]


def test_an_interrupted_diagnosis_ends_its_helper_at_once(step_case):
    # Ctrl-C or SIGTERM: the helper's job is of no use; it was left to finish it (up to a
    # second at exit, after the process had said it was interrupted)
    rec, cal = step_case
    (h,) = _started()

    def interrupt_in_round_one(line: str) -> None:
        if line.startswith("round 1"):
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        _diagnosed(rec, cal, jobs=2, echo=interrupt_in_round_one)
    assert h.broken
    h._proc.wait(5)  # killed, not waiting for stdin to close
    (h2,) = _started()  # the next diagnosis starts a new one
    assert h2 is not h and not h2.broken


def test_a_helpers_kernels_run_on_one_thread():
    """The helper has a core of its own beside the diagnosing process: its kernels run on one
    thread (a second would wait for the diagnosing process's core)."""
    import numba

    (h,) = _started()
    assert h.submit(numba.get_num_threads).result(timeout=60) == 1


def test_the_helpers_are_chosen_while_the_kernels_load_and_ended_when_that_fails(monkeypatch):
    # choosing may wait a fifth of a second for a reading of the cores' use: the diagnosing
    # process loads numba's kernels meanwhile, and a failure there (Ctrl-C) ends what was started
    import threading

    from mecanum_hil.identify.diagnose import selection

    class Fake:
        def __init__(self):
            self.stopped = self.closed = None

        def stop(self, err):
            self.stopped = err

        def close(self):
            self.closed = True

    fake = Fake()
    loading = threading.Event()
    seen: list[bool] = []

    def choose(jobs, warm):
        # still choosing while the kernels load (one after the other, this would wait)
        seen.append(loading.wait(30.0))
        return [fake]

    def load():
        loading.set()
        order.append("loaded")

    monkeypatch.setattr(selection, "helpers_for", choose)
    order: list[str] = []
    assert selection._helpers_beside(None, load) == [fake]
    assert seen == [True] and order == ["loaded"]

    def interrupted():
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        selection._helpers_beside(None, interrupted)
    assert fake.stopped == "interrupted"
    # Ctrl-C while waiting for the choice (the kernels loaded first): the same
    fake.stopped = None

    class Interrupted(threading.Thread):
        waits = 0

        def join(self, timeout=None):
            super().join(timeout)
            Interrupted.waits += 1
            if Interrupted.waits == 1:
                raise KeyboardInterrupt

    monkeypatch.setattr(selection.threading, "Thread", Interrupted)
    with pytest.raises(KeyboardInterrupt):
        selection._helpers_beside(None, lambda: None)
    assert fake.stopped == "interrupted"
    monkeypatch.undo()
    monkeypatch.setattr(selection, "helpers_for", choose)
    # an ordinary failure releases them as a diagnosis that fails does (the shared one kept)
    fake.stopped = None

    def broken():
        raise RuntimeError("no kernels")

    with pytest.raises(RuntimeError, match="no kernels"):
        selection._helpers_beside(None, broken)
    assert fake.stopped is None and fake.closed is True
    monkeypatch.setattr(selection, "helpers_for", lambda jobs, warm: 1 / 0)
    with pytest.raises(ZeroDivisionError):  # the choice's own failure reaches the caller
        selection._helpers_beside(None, lambda: None)
    # one process: nothing chosen, nothing started
    assert selection._helpers_beside(1, lambda: order.append("alone")) == []
    assert order[-1] == "alone"
