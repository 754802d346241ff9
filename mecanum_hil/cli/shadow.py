"""``mecanum-hil shadow``: the model beside the robot; flags where the robot stops following it.

Offline (``--replay REC.csv``) the monitor runs over a recording as if live; live
(``--transport can``) it listens passively to a controller someone else commands.
Exit code 0 without alarms, 3 with.
"""


from pathlib import Path
from typing import Annotated

import typer

from ._options import (
    CalibrationOpt,
    CmdTopicOpt,
    CmdTypeOpt,
    FoxgloveOpt,
    JointsOpt,
    JointTopicOpt,
    JsonOpt,
    RobotOpt,
    WheelSignsOpt,
    refuse_overwriting,
    require_positive,
)

#: Exit code when the monitor raised at least one alarm.
EXIT_ALARM = 3


#: The name a replay's event log gets beside a recording whose ``REC.shadow.jsonl`` is a
#: live run's (record --shadow, listen-can): ``run.csv`` -> ``run.replay.jsonl``.
REPLAY_LOG_SUFFIX = ".replay.jsonl"


def build_config(noise_rpm: float | None, drift: float, threshold: float, warmup_s: float):
    """The monitor settings from the command-line options (shared with ``record --shadow``);
    a value that makes no sense is refused naming its option."""
    from ..monitor import ShadowConfig

    require_positive(noise_rpm, "--noise-rpm", "rpm")
    require_positive(drift, "--drift", "noise sigmas", or_zero=True)
    require_positive(threshold, "--threshold", "noise sigmas")
    require_positive(warmup_s, "--warmup", "s", or_zero=True)
    return ShadowConfig(drift_k=drift, threshold_h=threshold, warmup_s=warmup_s,
                        noise_rpm=noise_rpm)


NoiseOpt = Annotated[float | None, typer.Option(
    "--noise-rpm", help="Wheel speed noise (1 sigma) [rpm]; default: estimated in the warm-up.")]
DriftOpt = Annotated[float, typer.Option(
    "--drift", help="CUSUM allowance k [noise sigmas].")]
ThresholdOpt = Annotated[float, typer.Option(
    "--threshold", help="CUSUM decision threshold h [noise sigmas].")]
WarmupOpt = Annotated[float, typer.Option(
    "--warmup", help="Initial window for the noise estimate [s].")]
ReplayOpt = Annotated[Path | None, typer.Option(
    "--replay", help="Recording (CSV) to run the monitor over, as if live.",
    metavar="REC.csv")]
EventsOpt = Annotated[Path | None, typer.Option(
    "--events", help="Event log (JSON lines); default: next to the recording, "
    "REC.shadow.jsonl (none beside a recording shipped with mecanum-hil).")]
NoEventsOpt = Annotated[bool, typer.Option("--no-events", help="Write no event log.")]
PlotOpt = Annotated[Path | None, typer.Option(
    "--plot", help="Replay: also write a PNG of measured against model, alarms marked.")]
ListenTransportOpt = Annotated[str | None, typer.Option(
    "--transport", help="Live: listen on a link passively (can, ros2).")]
CanInterfaceOpt = Annotated[str, typer.Option(
    "--interface", help="Live CAN: python-can interface (socketcan, slcan, virtual...).")]
CanChannelOpt = Annotated[str | None, typer.Option(
    "--channel", help="Live CAN: channel (can0, /dev/ttyACM0...).")]
CanBitrateOpt = Annotated[int | None, typer.Option(
    "--bitrate", help="Live CAN: bitrate [bit/s].")]
HeardOutOpt = Annotated[Path | None, typer.Option(
    "--out", "-o", help="Live: also record what was heard (CSV); the event log goes next "
    "to it.")]
DurationOpt = Annotated[float | None, typer.Option(
    "--duration", help="Live: stop listening after this long [s] (default: until Ctrl-C).")]
OnDivergenceOpt = Annotated[str, typer.Option(
    "--on-divergence", help="Live: 'none' (only report) or 'stop' (send STOP on the bus at "
    "the first alarm).")]
DiagnosticsTopicOpt = Annotated[str, typer.Option(
    "--diagnostics-topic", help="Live ROS 2: where the verdict is published "
    "(diagnostic_msgs/DiagnosticArray).")]


def command(
    replay_path: ReplayOpt = None,
    calibration: CalibrationOpt = "paper",
    robot: RobotOpt = "tdam-stm",
    json_out: JsonOpt = False,
    events: EventsOpt = None,
    no_events: NoEventsOpt = False,
    plot: PlotOpt = None,
    noise_rpm: NoiseOpt = None,
    drift: DriftOpt = 1.0,
    threshold: ThresholdOpt = 10.0,
    warmup: WarmupOpt = 2.0,
    transport: ListenTransportOpt = None,
    interface: CanInterfaceOpt = "socketcan",
    channel: CanChannelOpt = None,
    bitrate: CanBitrateOpt = None,
    out: HeardOutOpt = None,
    duration: DurationOpt = None,
    on_divergence: OnDivergenceOpt = "none",
    foxglove: FoxgloveOpt = None,
    cmd_topic: CmdTopicOpt = "/cmd_vel",
    cmd_type: CmdTypeOpt = "twist",
    joint_topic: JointTopicOpt = "/joint_states",
    joints: JointsOpt = None,
    wheel_signs: WheelSignsOpt = None,
    diagnostics_topic: DiagnosticsTopicOpt = "/diagnostics",
) -> None:
    """Run the model beside the robot and flag persistent divergence (exit 3 on alarms)."""
    from ..errors import ConfigError

    if on_divergence not in ("none", "stop"):
        raise ConfigError(f"--on-divergence must be 'none' or 'stop', got '{on_divergence}'")
    config = build_config(noise_rpm, drift, threshold, warmup)
    if replay_path is not None and foxglove is not None:
        raise ConfigError("--foxglove serves a live run (--transport can); for a recording, "
                          "export it: mecanum-hil export REC.csv --out RUN.mcap")
    if replay_path is not None:
        refuse_overwriting([(replay_path, "the recording", True)],
                           [(None if no_events else events, "--events"), (plot, "--plot")])
        n_alarms = _replay(replay_path, calibration, robot, config, json_out,
                           None if no_events else events, no_events, plot)
    elif transport == "ros2":
        ros2 = dict(cmd_topic=cmd_topic, cmd_type=cmd_type, joint_topic=joint_topic,
                    joints=joints, wheel_signs=wheel_signs, diagnostics_topic=diagnostics_topic)
        n_alarms = _listen_ros2(ros2, calibration, robot, config, out, events, no_events,
                                duration, on_divergence, json_out, foxglove)
    else:
        n_alarms = _listen_can(transport, (interface, channel, bitrate), calibration, robot,
                               config, out, None if no_events else events, duration,
                               on_divergence, foxglove)
    if n_alarms:
        raise typer.Exit(EXIT_ALARM)


def _listen_can(transport: str | None, bus: tuple, calibration: str, robot: str, config,
                out: Path | None, events: Path | None, duration: float | None,
                on_divergence: str, foxglove) -> int:
    """``shadow --transport can``: the monitor beside a controller someone else commands
    (``bus``: interface, channel, bitrate); the number of alarms."""
    from ..errors import ConfigError
    from ..monitor.live import listen_can

    if transport != "can":
        raise ConfigError(f"passive listening needs --transport can or ros2, got "
                          f"'{transport}' (on a serial link, use record --shadow)")
    interface, channel, bitrate = bus
    return listen_can(interface, channel, bitrate, calibration, robot, config,
                      out=out, events=events, duration_s=duration,
                      stop_on_divergence=on_divergence == "stop", echo=typer.echo,
                      foxglove=foxglove)


def _replay(path: Path, calibration: str, robot: str, config, json_out: bool,
            events: Path | None, no_events: bool, plot: Path | None) -> int:
    import json

    from ..errors import MecanumHILError
    from ..io.resources import is_shipped
    from ..io.timing import read_for_analysis
    from ..model import load_calibration, load_robot_profile
    from ..monitor import replay
    from ..monitor.core import nothing_compared
    from ..monitor.eventlog import EventLog, alarm_line, event_log_path, written_by

    rob = load_robot_profile(robot)
    cal = load_calibration(calibration)
    rec = read_for_analysis(path)
    listeners = []
    if not json_out:
        listeners.append(lambda e: typer.echo(alarm_line(e)) if e["event"] in (
            "alarm", "recovered") else None)
    log = None
    # mecanum-hil's own folders (its sample recordings) get an event log only when asked
    no_events = no_events or (events is None and is_shipped(path))
    if not no_events:
        target = events or event_log_path(path)
        mode = written_by(target)
        if mode is not None and mode != "replay":
            # a live run's alarms are data recorded once; a replay can be run again
            if events is not None:
                raise MecanumHILError(
                    f"{target}: the event log of a live run ({mode}): a replay does not "
                    "replace it; give another --events PATH, or --no-events")
            target = path.with_name(path.stem + REPLAY_LOG_SUFFIX)
        try:
            log = EventLog(target, cal, config,
                           {"mode": "replay", "recording": str(path)}, whole=True)
        except MecanumHILError as err:
            if events is not None:
                raise
            # the default place is beside the recording, which may be read-only
            raise MecanumHILError(f"{err}; write it elsewhere with --events PATH, or none "
                                  "with --no-events") from err
        listeners.insert(0, log)
    try:
        result = replay(rec, cal, rob, config, listeners=listeners, source=str(path))
    except BaseException:
        if log is not None:  # interrupted or failed: the previous log stays
            log.discard()
        raise
    if log is not None:
        log.close()
    why = nothing_compared(result, rec, config)
    if why is not None:  # "0 alarms" would read as a robot that matched its model
        raise MecanumHILError(f"{path}: {why}")
    if json_out:
        typer.echo(json.dumps(result.summary()))
    else:
        noise = ", ".join(f"{k} {v:.3g}" for k, v in result.noise.items())
        typer.echo(f"{path}: {result.samples} samples, {len(result.alarms)} alarm(s)"
                   + (f", first at {result.first_alarm_t_s:.3f} s" if result.alarms else "")
                   + (f"; noise {noise}" if noise else ""))
        if log is not None:
            kept = event_log_path(path)
            typer.echo(f"wrote {log.path}" + (f" (the live run's {kept.name} is kept)"
                                              if log.path != kept and events is None else ""))
    if plot is not None:
        from ..monitor.plot import plot_shadow
        from ..prediction import predict

        plot_shadow(rec, predict(rec, cal, rob, source=str(path)), result.alarms, plot,
                    title=f"shadow replay: {path.name}")
        if not json_out:
            typer.echo(f"wrote {plot}")
    return len(result.alarms)


def _listen_ros2(ros2: dict, calibration: str, robot: str, config, out: Path | None,
                 events: Path | None, no_events: bool, duration: float | None,
                 on_divergence: str, json_out: bool, foxglove) -> int:
    """``shadow --transport ros2``: the monitor beside a robot someone else drives; its
    verdict on /diagnostics. The event log goes next to ``--out``, else to ``--events``,
    else to ``shadow-ros2-<UTC time>.jsonl`` here."""
    import datetime as dt
    import json
    import sys

    from ..errors import ConfigError
    from ..model import load_robot_profile
    from ..monitor.live import listen

    if on_divergence != "none":
        raise ConfigError("shadow --transport ros2 never commands the robot: "
                          "--on-divergence stop is not available (its verdict is on "
                          f"{ros2['diagnostics_topic']})")
    if not no_events and events is None and out is None:
        events = Path(f"shadow-ros2-{dt.datetime.now(dt.UTC):%Y%m%dT%H%M%SZ}.jsonl")
    refuse_overwriting([], [(out, "--out", True), (None if no_events else events, "--events")])
    rob = load_robot_profile(robot)

    def open_source():
        from ..monitor.ros2_listen import Ros2Source

        return Ros2Source(rob, **ros2)

    def echo(line: str) -> None:
        typer.echo(line, err=json_out)

    alarms = listen(open_source, calibration, robot, config, out=out,
                    events=None if no_events else events, duration_s=duration, echo=echo,
                    foxglove=foxglove, name=f"ROS 2 {ros2['joint_topic']}",
                    mode="listen-ros2")
    if json_out:
        print(json.dumps({"alarms": [a.summary() for a in alarms],
                          "first_alarm_t_s": alarms[0].t_s if alarms else None}),
              file=sys.stdout, flush=True)
    return len(alarms)
