"""``mecanum-hil record``: drive a controller with a profile and record what comes back.

Exit codes: 0 completed, 1 error, 3 stopped by an observer (shadow mode), 4 link lost
(telemetry stopped), 5 telemetry far from the announced rate, 6 the controller restarted
(clock or sequence went back), 130 Ctrl-C, 143 SIGTERM (docs/link.md). Observers are
collected in ``observers`` below; a command-line option that adds one (e.g. shadow mode)
builds it there.
"""


from pathlib import Path
from types import SimpleNamespace
from typing import Annotated

import typer

from ._options import (
    BitrateOpt,
    ChannelOpt,
    CmdTopicOpt,
    CmdTypeOpt,
    FoxgloveOpt,
    InterfaceOpt,
    JointsOpt,
    JointTopicOpt,
    LinkOptionOpt,
    OdomTopicOpt,
    OutOpt,
    PortOpt,
    ProgressOpt,
    RobotOpt,
    TransportOpt,
    WheelSignsOpt,
    echo_safely,
    link_name,
    raise_signal_end,
    refuse_overwriting,
    require_positive,
    ros2_options,
    shipped_or_file,
)

#: Slowest command rate over ROS 2 [Hz]: a Mecanum drive controller takes a twist stream.
MIN_ROS2_RATE_HZ = 50.0


def refuse_replacing_recording(out: Path, folder: bool) -> None:
    """One-line error when ``--out`` already holds a recording (a folder of episodes with
    ``folder``): a run on the robot is data recorded once, never replaced by accident."""
    from ..errors import ConfigError
    from ..io.recording import sidecar_path
    from ..monitor.eventlog import event_log_path

    if folder:
        taken = out.is_dir() and any(out.iterdir())
    else:
        taken = any(p.exists() for p in (out, sidecar_path(out), event_log_path(out)))
    if taken:
        raise ConfigError(f"{out}: {'a folder with recordings' if folder else 'a recording'} "
                          "is already there (a run made before?): record does not replace it; "
                          "give another --out, or --force to replace it")


def clear_former_run(out: Path, folder: bool) -> None:
    """With ``--force``: remove what a former run left at ``out`` that this run would not
    write over: its event log (a run without ``--shadow`` writes none, and ``export`` or a
    replay would take the old one for the new run's), or, for a folder of episodes, every
    ``episode_NNN`` file and ``summary.json`` (fewer episodes would leave old ones beside the
    new; ``fit runs/*.csv`` would mix two runs). The recording and its sidecar are replaced
    when the run starts."""
    from ..errors import ConfigError
    from ..monitor.eventlog import event_log_path

    if folder:
        stale = [*out.glob("episode_[0-9][0-9][0-9]*"), out / "summary.json"] \
            if out.is_dir() else []
    else:
        stale = [event_log_path(out)]
    for p in stale:
        try:
            p.unlink(missing_ok=True)
        except OSError as err:
            raise ConfigError(f"{p}: --force cannot remove the former run's file: "
                              f"{err.strerror or err}") from err


ProfileOpt = Annotated[str | None, typer.Option(
    "--profile", help="Built-in profile (paper-step-60, ...) or profile TOML file.")]
CommandsOpt = Annotated[Path | None, typer.Option(
    "--commands", help="Recording whose command columns are sent.")]
RateOpt = Annotated[float, typer.Option("--rate", help="Command rate [Hz].")]
DryRunOpt = Annotated[bool, typer.Option(
    "--dry-run", help="Check and show what would be sent; open nothing.")]
ConnectTimeoutOpt = Annotated[float | None, typer.Option(
    "--connect-timeout", help="How long to wait for the controller's HELLO_ACK, or on "
    "ROS 2 for the robot's topics [s] (default 2; ROS 2: 5).")]
LinkTimeoutOpt = Annotated[float, typer.Option(
    "--link-timeout", help="Telemetry silence that counts as a lost link, whatever "
                           "else arrives [s]; at least 3 of the controller's telemetry "
                           "periods.")]
ShadowOpt = Annotated[str | None, typer.Option(
    "--shadow", metavar="CAL", help="Shadow mode: run this calibration's model beside the "
    "robot and flag divergence (events in OUT.shadow.jsonl).")]
OnDivergenceOpt = Annotated[str, typer.Option(
    "--on-divergence", help="With --shadow: none (report) or stop (send STOP at the "
    "first alarm; exit 3).")]
PolicyOpt = Annotated[str | None, typer.Option(
    "--policy", metavar="POLICY", help="Closed loop: this policy file (from train) or "
    "'scripted' drives the robot; --out is then a folder (one recording per episode, "
    "summary.json).")]
TaskOpt = Annotated[str | None, typer.Option(
    "--task", help="With --policy: reach or dodge (must be the policy's).")]
EpisodesOpt = Annotated[int, typer.Option("--episodes", help="With --policy: episodes.")]
SeedOpt = Annotated[int, typer.Option(
    "--seed", help="With --policy: episode i draws its target or strike from seed + i, "
    "as evaluate does.")]
PolicyJsonOpt = Annotated[bool, typer.Option(
    "--json", help="With --policy: print the summary (summary.json) on stdout.")]
ForceOpt = Annotated[bool, typer.Option(
    "--force", help="Replace an existing recording at --out (its sidecar and event log "
    "too: a former event log is removed; with --policy, the folder's episode files and "
    "summary.json).")]


def command(
    out: OutOpt,
    transport: TransportOpt = "serial",
    port: PortOpt = None,
    interface: InterfaceOpt = None,
    channel: ChannelOpt = None,
    bitrate: BitrateOpt = None,
    link_option: LinkOptionOpt = None,
    cmd_topic: CmdTopicOpt = "/cmd_vel",
    cmd_type: CmdTypeOpt = "twist",
    joint_topic: JointTopicOpt = "/joint_states",
    odom_topic: OdomTopicOpt = "/odom",
    joints: JointsOpt = None,
    wheel_signs: WheelSignsOpt = None,
    profile: ProfileOpt = None,
    commands: CommandsOpt = None,
    rate_hz: RateOpt = 50.0,
    robot: RobotOpt = "tdam-stm",
    dry_run: DryRunOpt = False,
    connect_timeout_s: ConnectTimeoutOpt = None,
    link_timeout_s: LinkTimeoutOpt = 0.5,
    progress: ProgressOpt = True,
    shadow: ShadowOpt = None,
    on_divergence: OnDivergenceOpt = "none",
    foxglove: FoxgloveOpt = None,
    policy: PolicyOpt = None,
    task: TaskOpt = None,
    episodes: EpisodesOpt = 1,
    seed: SeedOpt = 0,
    json_out: PolicyJsonOpt = False,
    force: ForceOpt = False,
) -> None:
    """Send a command profile to a robot controller and record commands and telemetry."""
    a = SimpleNamespace(**locals())  # the options, by name, for the steps below
    a.connect_timeout_s = _check_timing(transport, rate_hz, connect_timeout_s, link_timeout_s)
    ros2 = ros2_options(transport, cmd_topic=cmd_topic, cmd_type=cmd_type,
                        joint_topic=joint_topic, odom_topic=odom_topic, joints=joints,
                        wheel_signs=wheel_signs, robot=robot,
                        discovery_timeout_s=a.connect_timeout_s)
    if policy is not None:
        return _record_policy(a, ros2)
    _check_stream_run(a)
    rob, t, cmd, source = _checked_stream(robot, profile, commands, rate_hz)
    options, where = _link_options(a, ros2)
    if dry_run:
        from ..link.record import dry_run_report

        echo_safely(dry_run_report(t, cmd, rob, transport, where))
        return
    meta = {"commands_from": source, "command_rate_hz": rate_hz}
    result = _run(a, options, where, rob, t, cmd, meta)
    _end(result)


def _check_timing(transport: str, rate_hz: float, connect_timeout_s: float | None,
                  link_timeout_s: float) -> float:
    """The connect timeout (its default by transport), after one-line errors for a rate or a
    timeout the link cannot keep."""
    from ..errors import ConfigError

    if connect_timeout_s is None:
        connect_timeout_s = 5.0 if transport == "ros2" else 2.0
    if transport == "ros2" and rate_hz < MIN_ROS2_RATE_HZ:
        raise ConfigError(f"--rate must be at least {MIN_ROS2_RATE_HZ:g} Hz over ROS 2 (robots "
                          f"stop at their reference timeout), got {rate_hz:g}")
    require_positive(connect_timeout_s, "--connect-timeout")
    require_positive(link_timeout_s, "--link-timeout")
    return connect_timeout_s


def _record_policy(a, ros2: dict) -> None:
    """``--policy``: episodes into the folder ``--out`` (:mod:`._record_policy`)."""
    from ._record_policy import record_policy

    if not a.force:
        refuse_replacing_recording(a.out, folder=True)
    out = a.out
    return record_policy(
        out=out, transport=a.transport, port=a.port, interface=a.interface, channel=a.channel,
        bitrate=a.bitrate, link_option=a.link_option, robot=a.robot, policy=a.policy,
        task=a.task, episodes=a.episodes, seed=a.seed, connect_timeout_s=a.connect_timeout_s,
        link_timeout_s=a.link_timeout_s, progress=a.progress, shadow=a.shadow,
        on_divergence=a.on_divergence, json_out=a.json_out, profile=a.profile,
        commands=a.commands, dry_run=a.dry_run, foxglove=a.foxglove, ros2=ros2,
        before_run=(lambda: clear_former_run(out, folder=True)) if a.force else None)


def _check_stream_run(a) -> None:
    """One source of commands, and (unless a dry run) no input or former recording
    overwritten."""
    from ..errors import ConfigError

    if (a.commands is None) == (a.profile is None):
        raise ConfigError("give exactly one of --profile NAME_OR_FILE and --commands REC.csv")
    if not a.dry_run:  # the recording is created before the first command is sent
        refuse_overwriting([(a.commands, "the --commands recording", True),
                            (shipped_or_file(a.profile), "the profile"),
                            (shipped_or_file(a.robot), "the robot profile"),
                            (shipped_or_file(a.shadow), "the --shadow calibration")],
                           [(a.out, "--out", True)])
        if not a.force:
            refuse_replacing_recording(a.out, folder=False)


def _checked_stream(robot: str, profile: str | None, commands: Path | None, rate_hz: float):
    """``(robot profile, t [s], commands, where they come from)``, the commands checked
    against the robot before anything is opened or sent."""
    from ..model import load_robot_profile

    rob = load_robot_profile(robot)
    t, cmd, source = _command_stream(profile, commands, rate_hz)
    rob.check_commands(cmd, source)  # before anything is opened or sent
    return rob, t, cmd, source


def _link_options(a, ros2: dict) -> tuple[dict, str]:
    """The transport's options and how the run names its link."""
    from ..link.transport import transport_options

    options = transport_options(a.transport, port=a.port, interface=a.interface,
                                channel=a.channel, bitrate=a.bitrate,
                                link_options=a.link_option)
    options.update(ros2)
    return options, link_name(a.transport, a.port, a.interface, a.channel, a.cmd_topic)


def _run(a, options: dict, where: str, rob, t, cmd, meta: dict):
    """Open the link, run the session with its observers, close everything; the result."""
    from ..link.session import SessionConfig, run_record_session
    from ..link.transport import open_transport

    observers, shadow_obs, live_view = _observers(a.shadow, a.on_divergence, a.foxglove, rob,
                                                  t, cmd, a.out)
    try:
        link = open_transport(a.transport, options)
    except BaseException:
        if live_view is not None:  # a port that does not open must not leave a server running
            live_view.live.close()
        raise
    try:
        if a.force and a.shadow is None:  # the session replaces the recording from here on
            clear_former_run(a.out, folder=False)
        config = SessionConfig(connect_timeout_s=a.connect_timeout_s,
                               link_timeout_s=a.link_timeout_s)
        if a.progress:
            return _run_with_progress(link, t, cmd, a.out, rob, config, observers, meta, where)
        return run_record_session(link, t, cmd, a.out, rob, config=config,
                                  observers=observers, metadata=meta)
    finally:
        link.close()
        if shadow_obs is not None:
            echo_safely(shadow_obs.close())
        if live_view is not None:
            live_view.live.close()


def _end(result) -> None:
    """Print the run's summary; end with its exit code (an error or a signal as such)."""
    from ..link.record import format_summary

    echo_safely(format_summary(result))
    if result.exit_code == 0:
        return
    if result.error is not None and result.reason in ("error", "link_lost"):
        raise result.error
    raise_signal_end(result.reason)
    raise typer.Exit(result.exit_code)


def _command_stream(profile: str | None, commands: Path | None, rate_hz: float):
    """The commands to send, ``(t [s], commands, where they come from)``."""
    from ..io.recording import read_recording
    from ..link.record import stream_from_recording
    from ..profiles import resolve_profile

    if profile is not None:
        prof = resolve_profile(profile)
        t, cmd = prof.sample(rate_hz)
        return t, cmd, f"profile {prof.name}"
    t, cmd = stream_from_recording(read_recording(commands), rate_hz, str(commands))
    return t, cmd, str(commands)


def _observers(shadow, on_divergence, foxglove, rob, t, cmd, out):
    """The run's observers, ``(all, the shadow monitor or None, the live view or None)``.

    Observers see every telemetry sample (their own thread). Options that watch the run
    (shadow mode, ...) append theirs here.
    """
    from ..errors import ConfigError

    observers: list = []
    shadow_obs = None
    if shadow is None and on_divergence != "none":
        raise ConfigError("--on-divergence acts on shadow mode's alarms: give --shadow CAL too "
                          "(without it nothing watches the run)")
    if shadow is not None:
        from ..monitor.live import record_shadow

        shadow_obs = record_shadow(shadow, rob, t, cmd, out, on_divergence, echo=echo_safely)
        observers.append(shadow_obs)
    live_view = None
    if foxglove is not None:
        from ..monitor.foxglove import start_live_view

        # after the shadow observer: it publishes the prediction of the sample just seen
        live_view = start_live_view(foxglove, shadow_obs, echo=echo_safely)
        observers.append(live_view)
    return observers, shadow_obs, live_view


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
