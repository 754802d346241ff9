"""Small jobs run the kernels' own source in the interpreter (mecanum_hil/_jit.py): numba is not
loaded for them, and the interpreter gives numba's numbers."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from mecanum_hil.model import Calibration
from mecanum_hil.model.simulate import simulate

ROOT = Path(__file__).resolve().parents[2]

# the cases, as source: run here and in the interpreted subprocess alike
CASES = """
import numpy as np
from mecanum_hil.model import Effects

EFFECTS = {
    "linear": Effects(),
    "dead_time": Effects(dead_time_s=0.033),
    "nonlinear": Effects(dead_time_s=0.013, top_speed_rpm=90.0, rate_limit_rpm_per_s=300.0,
                         deadband_rpm=3.0, gains=(1.0, 0.9, 1.0, 1.1),
                         efficiency=(0.9, 0.8, 0.95)),
    "drive": Effects(controller_period_s=0.007, drive_lag_s=0.02, breakaway_rpm_per_s=2000.0),
    "friction": Effects(friction_rpm_per_s=700.0, dead_time_s=0.013),
    "drive_deadband": Effects(drive_deadband_rpm=30.0, friction_rpm_per_s=200.0),
}
rng = np.random.default_rng(3)
t = np.cumsum(rng.uniform(0.004, 0.02, 150))  # irregular, like a real logger
cmd = np.column_stack([np.repeat(rng.uniform(-80, 80, 10), 15),
                       np.repeat(rng.uniform(-40, 40, 10), 15),
                       np.repeat(rng.uniform(-180, 180, 10), 15)])
"""
_cases: dict = {}
exec(CASES, _cases)
EFFECTS, CMD, T = _cases["EFFECTS"], _cases["cmd"], _cases["t"]


def _run(code: str, mode: str, env_extra: dict | None = None) -> dict:
    env = {**os.environ, "MECANUM_HIL_JIT": mode, **(env_extra or {})}
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True,
                         text=True, env=env, check=True, timeout=600, cwd=ROOT)
    return json.loads(out.stdout)


SIMULATE_ALL = CASES + """
import json, sys
from mecanum_hil.model import Calibration
from mecanum_hil.model.simulate import simulate
out = {}
for name, fx in EFFECTS.items():
    tr = simulate(cmd, t, Calibration(effects=fx), initial_pose=(0.3, -0.2, 10.0))
    out[name] = [tr.wheel_rpm.tolist(), tr.pose.tolist(), tr.final_state.tolist()]
out["numba_loaded"] = "numba" in sys.modules
print(json.dumps(out))
"""


def test_the_interpreter_gives_numbas_numbers_for_every_effect():
    interpreted = _run(SIMULATE_ALL, "never")
    assert interpreted.pop("numba_loaded") is False
    for name, fx in EFFECTS.items():
        ref = simulate(CMD, T, Calibration(effects=fx), initial_pose=(0.3, -0.2, 10.0))
        wheels, pose, state = (np.array(a) for a in interpreted[name])
        np.testing.assert_allclose(wheels, ref.wheel_rpm, rtol=0, atol=1e-9, err_msg=name)
        np.testing.assert_allclose(pose, ref.pose, rtol=0, atol=1e-12, err_msg=name)
        np.testing.assert_allclose(state, ref.final_state, rtol=0, atol=1e-9, err_msg=name)


REPLAY = """
import json, sys
import numpy as np
from mecanum_hil.io.recording import read_recording
from mecanum_hil.model import Calibration, Effects, load_robot_profile
from mecanum_hil.monitor.core import replay
rec = read_recording("recordings/samples/paper-step-60.csv")
# a model whose first wheel is 30 % weak: the replay raises alarms
weak = Calibration(effects=Effects(gains=(0.7, 1.0, 1.0, 1.0)))
res = replay(rec, weak, load_robot_profile())
print(json.dumps({"alarms": [repr(a) for a in res.alarms], "samples": res.samples,
                  "numba_loaded": "numba" in sys.modules}))
"""


def test_a_short_replay_runs_without_numba_and_agrees_with_it():
    interpreted = _run(REPLAY, "auto")
    compiled = _run(REPLAY, "always")
    assert interpreted.pop("numba_loaded") is False
    assert compiled.pop("numba_loaded") is True
    assert interpreted == compiled
    assert interpreted["alarms"]


def test_a_large_job_is_compiled():
    code = """
    import json, sys
    import numpy as np
    from mecanum_hil.model.simulate import simulate, uniform_time
    t = uniform_time(60.0, 1000)  # 60,001 robot-steps: over the interpreter's budget
    cmd = np.tile([60.0, 0.0, 90.0], (t.size, 1))
    simulate(cmd, t)
    print(json.dumps({"numba_loaded": "numba" in sys.modules}))
    """
    assert _run(code, "auto") == {"numba_loaded": True}


@pytest.mark.parametrize("mode", ["never", "always"])
def test_the_mode_is_honoured(mode):
    code = """
    import json, sys
    import numpy as np
    from mecanum_hil.model.simulate import simulate, uniform_time
    t = uniform_time(0.5, 100)
    simulate(np.tile([60.0, 0.0, 90.0], (t.size, 1)), t)
    print(json.dumps({"numba_loaded": "numba" in sys.modules}))
    """
    assert _run(code, mode) == {"numba_loaded": mode == "always"}


def test_kernel_threads_caps_the_calling_threads_kernels_and_restores_them():
    """``kernel_threads(1)``: beside a helper process (a core each) a kernel runs on one thread,
    then the count is as before; with numba not loaded it does nothing (and loads nothing)."""
    code = """
    import json, sys
    from mecanum_hil._jit import kernel_threads, load_compiled
    with kernel_threads(1):
        pass
    before = "numba" in sys.modules
    load_compiled("mecanum_hil.model._kernels")
    import numba
    numba.set_num_threads(2)
    with kernel_threads(1):
        inside = numba.get_num_threads()
    print(json.dumps({"numba_loaded_by_it": before, "inside": inside,
                      "after": numba.get_num_threads()}))
    """
    env_threads = {"NUMBA_NUM_THREADS": "2"}
    assert _run(code, "auto", env_threads) == {"numba_loaded_by_it": False, "inside": 1,
                                               "after": 2}


def test_forced_never_keeps_numba_out_of_the_process_even_for_large_jobs_and_the_monitor():
    """``forced("never")``: a job over the interpreter's budget and the shadow monitor's
    per-sample core (a kernel called directly) run in the interpreter; numba is not loaded,
    and after the block the environment's mode is back."""
    code = """
    import json, sys
    import numpy as np
    from mecanum_hil._jit import forced, mode
    from mecanum_hil.model import Calibration, RobotProfile
    from mecanum_hil.model.simulate import simulate, uniform_time
    from mecanum_hil.monitor.core import ShadowMonitor
    with forced("never"):
        inside = mode()
        t = uniform_time(20.0, 1000)  # 20,001 robot-steps: over the interpreter's budget
        simulate(np.tile([60.0, 0.0, 90.0], (t.size, 1)), t)
        mon = ShadowMonitor(Calibration(), RobotProfile())
        mon.on_telemetry(0.0, (60.0, 0.0, 90.0), np.zeros(4))
    print(json.dumps({"numba_loaded": "numba" in sys.modules, "inside": inside,
                      "after": mode()}))
    """
    assert _run(code, "auto") == {"numba_loaded": False, "inside": "never", "after": "auto"}
