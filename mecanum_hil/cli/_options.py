"""Option aliases shared by the commands (one definition, the same flags everywhere)."""


from pathlib import Path
from typing import Annotated

import typer

CalibrationOpt = Annotated[
    str,
    typer.Option("--calibration", "-c", help="Calibration: a shipped name (paper) or a TOML file.",
                 metavar="CAL"),
]
RobotOpt = Annotated[
    str,
    typer.Option("--robot", help="Robot profile: a shipped name (tdam-stm) or a TOML file.",
                 metavar="ROBOT"),
]
OutOpt = Annotated[Path, typer.Option("--out", "-o", help="Recording (CSV) to write.")]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print the result as JSON on stdout.")]
ProgressOpt = Annotated[bool, typer.Option(
    "--progress/--no-progress", help="Show a progress bar.")]

#: Options whose value may be left out (``--foxglove`` alone serves on localhost:8765); typer
#: has no such options, so :func:`fill_optional_values` gives them an empty value first.
OPTIONAL_VALUE = ("--foxglove",)

FoxgloveOpt = Annotated[str | None, typer.Option(
    "--foxglove", metavar="[HOST:PORT]", help="Serve a live view for Foxglove (WebSocket) at "
    "HOST:PORT; alone: 127.0.0.1:8765, this machine only (docs/ros2.md).")]


def fill_optional_values(args: list[str]) -> list[str]:
    """``--foxglove`` followed by nothing or by another option gets the empty value."""
    out: list[str] = []
    for i, arg in enumerate(args):
        out.append(arg)
        if arg in OPTIONAL_VALUE and (i + 1 == len(args) or args[i + 1].startswith("-")):
            out.append("")
    return out


# The robot link's options, shared by the commands that open a link (record, conformance).
TransportOpt = Annotated[str, typer.Option(
    "--transport", "-t", help="serial, can, ros2, or a plug-in's name.")]
PortOpt = Annotated[str | None, typer.Option(
    "--port", help="Serial port: a device, loop://, socket://HOST:PORT ...")]
InterfaceOpt = Annotated[str | None, typer.Option(
    "--interface", help="python-can interface (socketcan, slcan, pcan, virtual, ...).")]
ChannelOpt = Annotated[str | None, typer.Option(
    "--channel", help="python-can channel (can0, /dev/ttyACM0, ...).")]
BitrateOpt = Annotated[int | None, typer.Option(
    "--bitrate", help="Bit rate [bit/s]: CAN bus rate, or serial baud rate.")]
# The ROS 2 link's options (record, shadow --transport ros2; docs/ros2-live.md).
CmdTopicOpt = Annotated[str, typer.Option(
    "--cmd-topic", help="ROS 2: command topic (geometry_msgs Twist or TwistStamped).")]
CmdTypeOpt = Annotated[str, typer.Option(
    "--cmd-type", help="ROS 2: twist or twist-stamped (stamped now, frame base_link).")]
JointTopicOpt = Annotated[str, typer.Option(
    "--joint-topic", help="ROS 2: sensor_msgs/JointState topic (velocities in rad/s).")]
OdomTopicOpt = Annotated[str, typer.Option(
    "--odom-topic", help="ROS 2: nav_msgs/Odometry topic for the pose ('' for none).")]
JointsOpt = Annotated[str | None, typer.Option(
    "--joints", metavar="FL,FR,RL,RR", help="ROS 2: joint names of wheels 1..4 (default: "
    "detected by name, as import does).")]
WheelSignsOpt = Annotated[str | None, typer.Option(
    "--wheel-signs", metavar="S1,S2,S3,S4", help="ROS 2: -1 for a joint whose positive axis "
    "turns the wheel backwards (default +1,+1,+1,+1).")]


def ros2_options(transport: str, *, cmd_topic: str, cmd_type: str, joint_topic: str,
                 odom_topic: str, joints: str | None, wheel_signs: str | None,
                 robot: str | None = None, discovery_timeout_s: float | None = None) -> dict:
    """The ``ros2`` transport's options from the command line ({} for another transport)."""
    if transport != "ros2":
        return {}
    options = dict(cmd_topic=cmd_topic, cmd_type=cmd_type, joint_topic=joint_topic,
                   odom_topic=odom_topic or None, joints=joints, wheel_signs=wheel_signs,
                   robot=robot, discovery_timeout_s=discovery_timeout_s)
    return {k: v for k, v in options.items() if v is not None}


def link_name(transport: str, port: str | None, interface: str | None, channel: str | None,
              cmd_topic: str = "/cmd_vel") -> str:
    """How a run names its link in progress lines and dry runs."""
    if transport == "ros2":
        return f"ROS 2 {cmd_topic}"
    return port or f"{interface}:{channel}"


LinkOptionOpt = Annotated[list[str] | None, typer.Option(
    "--link-option", metavar="KEY=VALUE",
    help="Extra transport option, repeatable (e.g. sleep_after_open=0 for slcan).")]


#: Options of which a command takes exactly one, by parameter name, as the message names them:
#: none or several is a usage error (exit 2), found before the command runs.
ONE_OF = {
    "record": {"profile": "--profile NAME_OR_FILE", "commands": "--commands REC.csv",
               "policy": "--policy POLICY"},
    "shadow": {"replay_path": "--replay REC.csv", "transport": "--transport can|ros2"},
    "simulate": {"commands": "--commands REC.csv", "profile": "--profile NAME_OR_FILE"},
    "sim-robot": {"serial": "--serial", "slcan": "--slcan", "can": "--can INTERFACE:CHANNEL",
                  "transport": "--transport ros2"},
}


def check_one_of(command: str, values: dict) -> None:
    """:class:`~mecanum_hil.errors.UsageError` unless exactly one of ``command``'s
    :data:`ONE_OF` options is among ``values`` (given: neither ``None`` nor ``False``)."""
    from ..errors import UsageError

    options = ONE_OF.get(command, {})
    given = [name for name in options if values.get(name) not in (None, False)]
    if options and len(given) != 1:
        *first, last = options.values()
        raise UsageError(f"give exactly one of {', '.join(first)} and {last}")


def refuse_overwriting(inputs, outputs) -> None:
    """One-line error when an output names an input: writing it would destroy data already
    recorded (``fit -o run.csv run.csv``, ``import log.csv -o log.csv``); or when an output
    cannot be written at all (:func:`require_writable`), before any work.

    Parameters
    ----------
    inputs : iterable of (Path or None, str) or (Path or None, str, bool)
        Files read, with how the user gave them (``"the recording"``); a third item ``True``
        marks a recording whatever its name (its JSON sidecar is read too).
    outputs : iterable of (Path or None, str) or (Path or None, str, bool)
        Files to be written, with their option (``"--out"``); a third item ``True`` marks a
        recording whatever its name (``-o run.txt`` also writes ``run.json``). A CSV is
        taken for a recording, with its sidecar, either way.
    """
    from ..errors import ConfigError

    def same(a: Path, b: Path) -> bool:
        try:
            return a.resolve() == b.resolve() or (a.exists() and b.exists()
                                                   and a.samefile(b))
        except OSError:
            return False

    def with_sidecar(path: Path, recording: bool) -> list[Path]:
        side = path.with_suffix(".json")
        return [path] + ([side] if side != path and (recording or path.suffix.lower() == ".csv")
                         else [])

    given = [(Path(item[0]), item[1], len(item) > 2 and bool(item[2]))
             for item in inputs if item[0] is not None]
    for item in outputs:
        out, option = item[0], item[1]
        if out is None:
            continue
        out = Path(out)
        for target in with_sidecar(out, len(item) > 2 and bool(item[2])):
            for path, what, recording in given:
                if any(same(target, h) for h in with_sidecar(path, recording)):
                    raise ConfigError(f"{out}: {option} would overwrite {what} ({path}); "
                                      "write to another file")
    require_writable(*((item[0], item[1]) for item in outputs))


def shipped_or_file(name: str | None) -> Path | None:
    """A calibration or robot given as a file (for :func:`refuse_overwriting`); ``None`` for a
    shipped name (``paper``) or nothing."""
    if name is None or not name.lower().endswith(".toml"):
        return None
    return Path(name)


def require_writable(*outputs: tuple[Path | str | None, str]) -> None:
    """One-line error, before any work, for an output that cannot be written: a folder in its
    place, or no permission (a read-only place, ``/proc``) in the folder it goes to or the
    nearest existing one above it (the writers create missing folders). Otherwise a fit or a
    training ran to the end first, and a first output was written before the second failed.

    Parameters
    ----------
    outputs : (path or None, option)
        Files to be written, with their option (``"--report"``); ``None`` and ``-`` (stdout)
        are skipped.
    """
    from ..io.paths import check_file_writable

    for path, option in outputs:
        if path is not None and str(path) != "-":
            check_file_writable(path, f"{option} {path}")


def require_positive(value: float | None, option: str, unit: str = "s",
                     or_zero: bool = False) -> None:
    """One-line error unless ``value`` (an option's, ``None`` when not given) is a finite
    number > 0 (>= 0 with ``or_zero``): NaN passes every comparison (``--link-timeout nan``
    switched lost-link detection off) and 0 or a negative time makes no sense."""
    import math

    from ..errors import ConfigError

    if value is not None and not (math.isfinite(value) and (value >= 0 if or_zero
                                                             else value > 0)):
        raise ConfigError(f"{option} must be a finite number {'>=' if or_zero else '>'} 0 "
                          f"[{unit}], got {value:g}")


def echo_safely(text: str) -> None:
    """Print ``text`` on stdout where it may be closed (``record ... | head``): a closed
    stdout must not end a run that drives the robot, nor change its exit code (click would
    exit 1, silently). What cannot be printed is dropped, and stdout points at the null
    device from then on (no second error at exit)."""
    import errno
    import sys

    try:
        typer.echo(text)
        sys.stdout.flush()
    except UnicodeError:  # a real error (a character the terminal cannot show): said
        raise
    except (OSError, ValueError) as err:
        # a closed pipe (EPIPE), a terminal hung up (EIO, with SIGHUP), a closed stream
        if isinstance(err, OSError) and err.errno not in (errno.EPIPE, errno.EIO):
            raise
        if isinstance(err, ValueError) and not getattr(sys.stdout, "closed", False):
            raise
        point_at_devnull(sys.stdout)


def raise_signal_end(reason: str) -> None:
    """End a command whose run Ctrl-C or a signal cut short (it sent STOP and printed its
    summary) as any command ends then: ``error: interrupted`` (exit 130) or ``error:
    terminated by a signal`` (exit 143) on standard error."""
    from ..errors import SessionTerminated

    if reason == "interrupted":
        raise KeyboardInterrupt
    if reason == "terminated":
        raise SessionTerminated()


def point_at_devnull(stream) -> None:
    """Make ``stream``'s file descriptor the null device (a closed pipe or a hung-up terminal
    behind it), so that what is still buffered or printed later goes nowhere instead of
    raising again at exit."""
    import os

    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, stream.fileno())
        os.close(devnull)
    except (OSError, ValueError):
        pass
