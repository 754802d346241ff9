"""Benchmark of the robot link: 500 Hz commands and 1 kHz telemetry over a pseudo-terminal.

``python bench/bench_link.py`` runs 10 s; ``--duration 60`` is the full run (the
figure recorded in docs/benchmarks/link.md). ``sim-robot --serial --telemetry-rate 1000`` runs
in another process; ``record``'s session drives it at 500 Hz. Printed: frames sent, received
and lost (must be 0), the PING round trip and command-to-acknowledgement latency percentiles,
as ratios against the baseline measured in the same run: a bare 33-byte echo between two
processes over a pseudo-terminal (no framing, no CRC, no model).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
import tty
from pathlib import Path

import numpy as np

ECHO = """
import os, sys
fd = int(sys.argv[1])
while True:
    data = os.read(fd, 4096)
    if not data:
        break
    os.write(fd, data)
"""


def raw_echo_baseline(n: int = 3000, size: int = 33) -> np.ndarray:
    """Round trips [s] of ``size`` bytes echoed by another process over a pty."""
    master, slave = os.openpty()
    tty.setraw(slave)
    child = subprocess.Popen([sys.executable, "-c", ECHO, str(master)], pass_fds=(master,))
    os.close(master)
    payload = bytes(range(1, size + 1))
    out = np.empty(n)
    try:
        for i in range(n):
            t0 = time.perf_counter()
            os.write(slave, payload)
            got = 0
            while got < size:
                got += len(os.read(slave, 4096))
            out[i] = time.perf_counter() - t0
            time.sleep(0.0005)
    finally:
        os.close(slave)
        child.kill()
        child.wait()
    return out[100:]  # skip the warm-up


def bench_profile(duration_s: float):
    """Steps between 30 and 90 rpm every 2 s, straight ahead."""
    from mecanum_hil.profiles import CommandProfile, Segment

    segs = []
    n = 0
    while sum(s.duration_s for s in segs) < duration_s - 1e-9:
        segs.append(Segment("step", min(2.0, duration_s - n * 2.0), 30.0 if n % 2 else 90.0))
        n += 1
    return CommandProfile("bench-steps", tuple(segs))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=10.0, help="run length [s] (full: 60)")
    ap.add_argument("--command-rate", type=float, default=500.0)
    ap.add_argument("--telemetry-rate", type=float, default=1000.0)
    args = ap.parse_args()

    from mecanum_hil.io.recording import read_recording
    from mecanum_hil.link.serial_link import SerialTransport
    from mecanum_hil.link.session import SessionConfig, run_record_session
    from mecanum_hil.link.sim_process import spawn_sim_robot
    from mecanum_hil.model import load_robot_profile

    base = raw_echo_baseline() * 1e3
    b50, b99 = np.percentile(base, [50, 99])
    print(f"baseline: raw 33-byte echo over a pty between two processes: p50 {b50:.3f} ms, "
          f"p99 {b99:.3f} ms")

    prof = bench_profile(args.duration)
    t, cmd = prof.sample(args.command_rate)
    robot = load_robot_profile()
    with tempfile.TemporaryDirectory() as tmp, \
            spawn_sim_robot("--serial", "--telemetry-rate", f"{args.telemetry_rate:g}",
                            "--quiet") as sim, \
            SerialTransport(port=sim.path) as link:
        out = Path(tmp) / "bench.csv"
        res = run_record_session(link, t, cmd, out, robot,
                                 config=SessionConfig(ping_rate_hz=50.0, tail_s=0.1))
        rec = read_recording(out)
        cmd_rows = rec.t_s[[e == "cmd" for e in rec.extra["event"]]]
    s = res.stats
    lat = res.latency_ms
    lateness = (cmd_rows[: t.size] - t[: cmd_rows.size]) * 1e3
    expected_tlm = args.telemetry_rate * res.duration_s
    print(f"link: {args.duration:g} s, commands {args.command_rate:g} Hz, telemetry "
          f"{args.telemetry_rate:g} Hz -> {res.reason}")
    print(f"  frames sent {s['sent']} (commands {res.commands_sent} of {t.size}), received "
          f"{s['received']} (telemetry {res.telemetry_received}, "
          f"{res.telemetry_received / expected_tlm:.3f} of the nominal rate)")
    print(f"  lost {s['lost']}, crc {s['crc_errors']}, malformed {s['malformed']}, "
          f"send errors {s['send_errors']}")
    print(f"  command send lateness vs schedule: p50 {np.percentile(lateness, 50):.3f} ms, "
          f"p99 {np.percentile(lateness, 99):.3f} ms, max {lateness.max():.3f} ms")
    print(f"  PING round trip: p50 {lat['rtt_p50']:.3f} ms ({lat['rtt_p50'] / b50:.1f}x "
          f"baseline), p99 {lat['rtt_p99']:.3f} ms ({lat['rtt_p99'] / b99:.1f}x baseline), "
          f"n={int(lat['rtt_n'])}")
    print(f"  command -> acknowledging telemetry: p50 {lat['ack_p50']:.3f} ms "
          f"({lat['ack_p50'] / b50:.1f}x baseline), p99 {lat['ack_p99']:.3f} ms "
          f"({lat['ack_p99'] / b99:.1f}x baseline)")
    ok = res.reason == "completed" and s["lost"] == 0 and s["crc_errors"] == 0
    print("PASS: no frame lost" if ok else "FAIL: frames lost or run did not complete")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
