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
    "--transport", "-t", help="serial, can, or a plug-in's name.")]
PortOpt = Annotated[str | None, typer.Option(
    "--port", help="Serial port: a device, loop://, socket://HOST:PORT ...")]
InterfaceOpt = Annotated[str | None, typer.Option(
    "--interface", help="python-can interface (socketcan, slcan, pcan, virtual, ...).")]
ChannelOpt = Annotated[str | None, typer.Option(
    "--channel", help="python-can channel (can0, /dev/ttyACM0, ...).")]
BitrateOpt = Annotated[int | None, typer.Option(
    "--bitrate", help="Bit rate [bit/s]: CAN bus rate, or serial baud rate.")]
LinkOptionOpt = Annotated[list[str] | None, typer.Option(
    "--link-option", metavar="KEY=VALUE",
    help="Extra transport option, repeatable (e.g. sleep_after_open=0 for slcan).")]
