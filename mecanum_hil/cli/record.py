"""``mecanum-hil record``: drive a controller with a profile and record what comes back.

Exit codes: 0 completed, 1 error, 3 stopped by an observer (shadow mode), 4 link lost,
130 Ctrl-C, 143 SIGTERM (docs/link.md). Observers are collected in ``observers`` below; a
command-line option that adds one (e.g. shadow mode) builds it there.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ._options import OutOpt, RobotOpt


def command(
    out: OutOpt,
    transport: Annotated[str, typer.Option(
        "--transport", "-t", help="serial, can, or a plug-in's name.")] = "serial",
    port: Annotated[str | None, typer.Option(
        "--port", help="Serial port: a device, loop://, socket://HOST:PORT ...")] = None,
    interface: Annotated[str | None, typer.Option(
        "--interface", help="python-can interface (socketcan, slcan, pcan, virtual, ...).")
    ] = None,
    channel: Annotated[str | None, typer.Option(
        "--channel", help="python-can channel (can0, /dev/ttyACM0, ...).")] = None,
    bitrate: Annotated[int | None, typer.Option(
        "--bitrate", help="Bit rate [bit/s]: CAN bus rate, or serial baud rate.")] = None,
    link_option: Annotated[list[str] | None, typer.Option(
        "--link-option", metavar="KEY=VALUE",
        help="Extra transport option, repeatable (e.g. sleep_after_open=0 for slcan).")
    ] = None,
    profile: Annotated[str | None, typer.Option(
        "--profile", help="Built-in profile (paper-step-60, ...) or profile TOML file.")] = None,
    commands: Annotated[Path | None, typer.Option(
        "--commands", help="Recording whose command columns are sent.")] = None,
    rate_hz: Annotated[float, typer.Option("--rate", help="Command rate [Hz].")] = 50.0,
    robot: RobotOpt = "tdam-stm",
    dry_run: Annotated[bool, typer.Option(
        "--dry-run", help="Check and show what would be sent; open nothing.")] = False,
    connect_timeout_s: Annotated[float, typer.Option(
        "--connect-timeout", help="How long to wait for the controller's HELLO_ACK [s].")
    ] = 2.0,
    link_timeout_s: Annotated[float, typer.Option(
        "--link-timeout", help="Telemetry silence that counts as a lost link [s].")] = 0.5,
    progress: Annotated[bool, typer.Option(
        "--progress/--no-progress", help="Show a progress bar.")] = True,
    shadow: Annotated[str | None, typer.Option(
        "--shadow", metavar="CAL", help="Shadow mode: run this calibration's model beside the "
        "robot and flag divergence (events in OUT.shadow.jsonl).")] = None,
    on_divergence: Annotated[str, typer.Option(
        "--on-divergence", help="With --shadow: none (report) or stop (send STOP at the "
        "first alarm; exit 3).")] = "none",
) -> None:
    """Send a command profile to a robot controller and record commands and telemetry."""
    from ..errors import ConfigError
    from ..io.recording import read_recording
    from ..link.record import dry_run_report, format_summary, stream_from_recording
    from ..link.session import SessionConfig, run_record_session
    from ..link.transport import open_transport, parse_option_value
    from ..model import load_robot_profile
    from ..profiles import resolve_profile

    if (commands is None) == (profile is None):
        raise ConfigError("give exactly one of --profile NAME_OR_FILE and --commands REC.csv")
    rob = load_robot_profile(robot)
    if profile is not None:
        prof = resolve_profile(profile)
        t, cmd = prof.sample(rate_hz)
        source = f"profile {prof.name}"
    else:
        t, cmd = stream_from_recording(read_recording(commands), rate_hz, str(commands))
        source = str(commands)
    rob.check_commands(cmd, source)  # before anything is opened or sent

    options: dict[str, object] = {}
    if transport == "serial":
        options.update(port=port, baudrate=bitrate)
    elif transport == "can":
        options.update(interface=interface, channel=channel, bitrate=bitrate)
    else:
        options.update(port=port, interface=interface, channel=channel, bitrate=bitrate)
    for item in link_option or []:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"--link-option needs KEY=VALUE, got {item!r}")
        options[key.strip()] = parse_option_value(value)
    where = port or f"{interface}:{channel}"
    if dry_run:
        typer.echo(dry_run_report(t, cmd, rob, transport, where))
        return

    # Observers see every telemetry sample (their own thread). Options that watch the run
    # (shadow mode, ...) append theirs here.
    observers: list = []
    shadow_obs = None
    if shadow is None and on_divergence != "none":
        raise ConfigError("--on-divergence acts on shadow mode's alarms: give --shadow CAL too "
                          "(without it nothing watches the run)")
    if shadow is not None:
        from ..monitor.live import record_shadow

        shadow_obs = record_shadow(shadow, rob, t, cmd, out, on_divergence, echo=typer.echo)
        observers.append(shadow_obs)

    link = open_transport(transport, options)
    try:
        config = SessionConfig(connect_timeout_s=connect_timeout_s, link_timeout_s=link_timeout_s)
        meta = {"commands_from": source, "command_rate_hz": rate_hz}
        if progress:
            result = _run_with_progress(link, t, cmd, out, rob, config, observers, meta, where)
        else:
            result = run_record_session(link, t, cmd, out, rob, config=config,
                                        observers=observers, metadata=meta)
    finally:
        link.close()
        if shadow_obs is not None:
            typer.echo(shadow_obs.close())
    typer.echo(format_summary(result))
    if result.exit_code == 0:
        return
    if result.error is not None and result.reason in ("error", "link_lost"):
        raise result.error
    raise typer.Exit(result.exit_code)


def _run_with_progress(link, t, cmd, out, rob, config, observers, meta, where):
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    from ..link.session import run_record_session

    columns = (TextColumn("[bold]record[/] {task.description}"), BarColumn(),
               TextColumn("{task.completed:.1f}/{task.total:.1f} s"), TimeRemainingColumn(),
               TextColumn("{task.fields[counts]}"))
    with Progress(*columns, transient=True) as bar:
        task = bar.add_task(where, total=float(t[-1]) or 1.0, counts="")

        def update(elapsed_s, total_s, counts):
            bar.update(task, completed=min(elapsed_s, total_s),
                       counts=f"sent {counts['sent']} rx {counts['received']} "
                              f"lost {counts['lost']} crc {counts['crc_errors']}"
                              + "".join(f" | {o.status_line()}" for o in observers
                                        if hasattr(o, "status_line")))

        return run_record_session(link, t, cmd, out, rob, config=config, observers=observers,
                                  metadata=meta, progress=update)
