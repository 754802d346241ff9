"""Running ``mecanum-hil sim-robot`` in another process, and recording from it.

:func:`spawn_sim_robot` starts the simulated controller on a fresh pseudo-terminal and returns
once it printed its device path; :func:`record_profile_to_simulated_controller` records a
profile through the serial path to it (what ``mecanum-hil demo`` uses).
"""

from __future__ import annotations

import os
import select
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from .._cores import SINGLE_THREAD_ENV
from ..errors import LinkError

# SINGLE_THREAD_ENV is a simulated controller's environment: one thread each for numba and
# BLAS, so a controller stepping a single robot does not fight the host for the machine's cores.


#: How long to wait for sim-robot's first line [s]. It compiles its simulator before it
#: answers: a first run after install compiles numba's kernels, 44 s on the 2-core machine
#: when idle, twice that beside another job; a process that dies is reported at once.
STARTUP_TIMEOUT_S = 180.0


class SimRobotProcess:
    """A running ``sim-robot`` process.

    Attributes
    ----------
    path : str
        What it printed first: the device path (serial/slcan) or the bus it serves.
    proc : subprocess.Popen
    log_path : Path
        File receiving its standard error (one line per event).
    """

    def __init__(self, args: Sequence[str], startup_timeout_s: float = STARTUP_TIMEOUT_S,
                 env: dict[str, str] | None = None) -> None:
        self._log = tempfile.NamedTemporaryFile(prefix="sim-robot-", suffix=".log", delete=False)
        self.log_path = Path(self._log.name)
        full_env = {**os.environ, **SINGLE_THREAD_ENV, **(env or {})}
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "mecanum_hil", "sim-robot", *args],
            stdout=subprocess.PIPE, stderr=self._log, stdin=subprocess.DEVNULL, env=full_env)
        self.path = self._first_line(startup_timeout_s)

    def _first_line(self, timeout_s: float) -> str:
        deadline = time.monotonic() + timeout_s
        buf = b""
        fd = self.proc.stdout.fileno()
        while b"\n" not in buf:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or self.proc.poll() is not None:
                self.stop()
                raise LinkError(f"sim-robot did not start: {self.log().strip()[-500:]}")
            ready, _, _ = select.select([fd], [], [], min(remaining, 0.1))
            if ready:
                chunk = os.read(fd, 4096)
                if not chunk:
                    continue
                buf += chunk
        return buf.split(b"\n", 1)[0].decode().strip()

    def log(self) -> str:
        """What the process wrote to standard error so far."""
        try:
            return self.log_path.read_text(errors="replace")
        except OSError:
            return ""

    def stop(self, timeout_s: float = 5.0) -> int | None:
        """Terminate the process (SIGTERM, then SIGKILL) and return its exit code."""
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout_s)
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        self._log.close()
        return self.proc.returncode

    def __enter__(self) -> SimRobotProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
        try:
            self.log_path.unlink()
        except OSError:
            pass


def spawn_sim_robot(*args: str, startup_timeout_s: float = STARTUP_TIMEOUT_S,
                    env: dict[str, str] | None = None) -> SimRobotProcess:
    """Start ``mecanum-hil sim-robot ARGS`` (e.g. ``"--serial"``) and wait for its first line."""
    return SimRobotProcess(list(args), startup_timeout_s, env)


def record_profile_to_simulated_controller(
    profile,
    out_csv: str | Path,
    *,
    calibration: str = "paper",
    robot: str = "tdam-stm",
    effects: str | Path | None = None,
    command_rate_hz: float = 50.0,
    telemetry_rate_hz: float = 100.0,
    observers: Sequence[Any] = (),
    progress=None,
    env: dict[str, str] | None = None,
):
    """Record a profile through the serial path to a freshly spawned simulated controller.

    Parameters
    ----------
    profile : CommandProfile or str
        The profile, or a built-in name / profile file.
    out_csv : str or Path
        Recording to write.
    calibration, robot : str
        The simulated truth's calibration and the robot profile (names or files).
    effects : str or Path, optional
        Effects file for the simulated controller.
    command_rate_hz, telemetry_rate_hz : float
        Rates [Hz].
    observers : sequence of TelemetryObserver
        Passed to the session (shadow mode).
    env : dict, optional
        Extra environment of the simulated controller's process (``MECANUM_HIL_JIT=never``:
        its simulator in the interpreter, without numba's first compile).

    Returns
    -------
    RecordResult
    """
    from ..model import load_robot_profile
    from ..profiles import resolve_profile
    from .serial_link import SerialTransport
    from .session import run_record_session

    prof = resolve_profile(profile) if isinstance(profile, str | Path) else profile
    rob = load_robot_profile(robot)
    t, cmd = prof.sample(command_rate_hz)
    rob.check_commands(cmd, f"profile {prof.name}")
    args = ["--serial", "--calibration", str(calibration), "--robot", str(robot),
            "--telemetry-rate", f"{telemetry_rate_hz:g}"]
    if effects is not None:
        args += ["--effects", str(effects)]
    with spawn_sim_robot(*args, env=env) as sim, SerialTransport(port=sim.path) as link:
        return run_record_session(
            link, t, cmd, out_csv, rob, observers=observers, progress=progress,
            metadata={"profile": prof.name, "command_rate_hz": command_rate_hz,
                      "simulated_controller": {"calibration": str(calibration),
                                               "effects": str(effects) if effects else None}})
