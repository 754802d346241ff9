"""What ``mecanum-hil record`` needs besides the session: the command stream, the dry run's
description and the end-of-run summary (pure functions of their inputs)."""

from __future__ import annotations

import numpy as np

from ..errors import RecordingError
from ..io.recording import Recording
from ..model.kinematics import command_to_wheels
from ..model.robot import RobotProfile
from .protocol import Command, Stop, encode
from .session import NOT_AS_ASKED, STOP_AT_ONCE, RecordResult


def stream_from_recording(rec: Recording, rate_hz: float, source: str = "recording"
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Send times and commands at ``rate_hz`` reproducing a recording's command columns.

    The command in force at each send time is the recording's row at or before it (the
    recording's commands are piecewise constant), from its first to its last ``t_s``.
    """
    from ..prediction import require_commands

    require_commands(rec, source)
    if not rate_hz > 0:
        raise RecordingError(f"command rate must be > 0 Hz, got {rate_hz}")
    span = float(rec.t_s[-1] - rec.t_s[0])
    n = int(np.floor(span * rate_hz + 1e-9))
    t = np.arange(n + 1) / float(rate_hz)
    idx = np.searchsorted(rec.t_s - rec.t_s[0], t + 1e-9, side="right") - 1
    return t, rec.commands[np.clip(idx, 0, len(rec) - 1)].copy()


def dry_run_report(t_s: np.ndarray, commands: np.ndarray, robot: RobotProfile,
                   transport_name: str, where: str, frames: int = 3) -> str:
    """What a run would send, without opening anything (commands already checked)."""
    wheels = command_to_wheels(commands[:, 0], commands[:, 1], commands[:, 2], robot.k)
    rate = (len(t_s) - 1) / t_s[-1] if len(t_s) > 1 and t_s[-1] > 0 else float("nan")
    lines = [
        f"dry run: nothing is opened or sent ({transport_name} {where})",
        f"  {len(t_s)} commands at {rate:.6g} Hz over {t_s[-1]:.3f} s, then STOP",
        f"  n [rpm] {commands[:, 0].min():g}..{commands[:, 0].max():g}, omega [deg/s] "
        f"{commands[:, 1].min():g}..{commands[:, 1].max():g}, theta [deg] "
        f"{commands[:, 2].min():g}..{commands[:, 2].max():g}",
        f"  peak wheel target {np.abs(wheels).max():.1f} rpm (limit "
        f"{robot.wheel_speed_max_rpm:g} rpm, {robot.name}): within limits",
    ]
    if transport_name == "serial":
        lines.append("  first frames on the wire (HELLO, COMMAND ..., serial framing):")
        from .protocol import Hello

        lines.append(f"    HELLO   {encode(Hello()).hex(' ')}")
        for i in range(min(frames, len(t_s))):
            n, w, th = commands[i]
            msg = Command(float(np.float32(n)), float(np.float32(w)), float(np.float32(th)),
                          seq=i + 1)
            lines.append(f"    t={t_s[i]:.3f} s COMMAND {encode(msg).hex(' ')}")
        lines.append(f"    end     STOP {encode(Stop(seq=len(t_s) + 1)).hex(' ')}")
    elif transport_name == "ros2":
        from .ros2.convert import command_to_twist_si

        lines.append("  first twists (linear.x, linear.y [m/s], angular.z [rad/s]):")
        for i in range(min(frames, len(t_s))):
            vx, vy, wz = (v + 0.0 for v in command_to_twist_si(*commands[i],
                                                              robot.wheel_radius_m))
            lines.append(f"    t={t_s[i]:.3f} s  {vx:+.4f} {vy:+.4f} {wz:+.4f}")
        lines.append("    end     a zero twist, five times within 0.1 s")
    return "\n".join(lines)


def format_summary(result: RecordResult) -> str:
    """The end-of-run summary: counters and latency percentiles."""
    s = result.stats
    lat = result.latency_ms

    def pct(prefix: str) -> str:
        if not lat.get(f"{prefix}_n"):
            return "n/a"
        return (f"p50 {lat[f'{prefix}_p50']:.2f} / p90 {lat[f'{prefix}_p90']:.2f} / "
                f"p99 {lat[f'{prefix}_p99']:.2f} / max {lat[f'{prefix}_max']:.2f} ms "
                f"(n={int(lat[f'{prefix}_n'])})")

    lines = [
        f"{result.reason} (exit {result.exit_code}) after {result.duration_s:.2f} s"
        + (f": {result.message}" if result.message else ""),
        f"  recording   {result.path} ({result.rows} rows, {result.telemetry_received} "
        f"telemetry samples)",
        f"  frames      sent {s['sent']} (commands {result.commands_sent}), "
        f"received {s['received']}, lost {s['lost']}"
        + (f", own echoes ignored {s['echoes']}" if s.get("echoes") else ""),
        f"  errors      crc {s['crc_errors']}, malformed {s['malformed']}, unknown types "
        f"{s['unknown_types']}, wrong version {s['version_errors']}, bus {s['bus_errors']}, "
        f"send {s['send_errors']}, garbage bytes {s['garbage_bytes']}",
        f"  round trip  {pct('rtt')}",
        f"  cmd -> ack  {pct('ack')}",
    ]
    if result.reason in ("telemetry_rate", "controller_reset", *STOP_AT_ONCE):
        lines.append("  telemetry   the run was stopped: see end_message and link_events in the "
                     "sidecar")
    elif result.reason in NOT_AS_ASKED:
        lines.append("  not asked   the profile ran to its end, but not as asked: see end_message "
                     "and link_events in the sidecar")
    if result.observer_dropped:
        lines.append(f"  observers   missed {result.observer_dropped} samples (too slow)")
    return "\n".join(lines)
