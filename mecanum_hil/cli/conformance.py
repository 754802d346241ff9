"""``mecanum-hil conformance``: check a controller against every rule of drivers/protocol.md.

Exit codes: 0 every rule that ran passed, 1 a rule failed (or the link could not be opened).
The wheels turn: run it with the robot on stands.
"""


from pathlib import Path
from typing import Annotated

import typer

from ._options import (
    BitrateOpt,
    ChannelOpt,
    InterfaceOpt,
    LinkOptionOpt,
    PortOpt,
    RobotOpt,
    TransportOpt,
    require_positive,
    require_writable,
)

RuleOpt = Annotated[list[str] | None, typer.Option(
    "--rule", metavar="NAME", help="Run only this rule or group (hello, command.valid, "
    "...); repeatable.")]
EstopPressedOpt = Annotated[bool, typer.Option(
    "--estop-pressed", help="The e-stop was pressed before the run: also run the "
    "estop.* rules (release it before estop.reset).")]
JsonPathOpt = Annotated[str | None, typer.Option(
    "--json", metavar="PATH", help="Also write the report as JSON ('-' for stdout).")]
ListOpt = Annotated[bool, typer.Option("--list", help="List the rules and exit.")]
AnswerTimeoutOpt = Annotated[float, typer.Option(
    "--answer-timeout", metavar="S", help="How long an answer (HELLO_ACK, ERROR, PONG, an "
    "acknowledging sample) may take [s]; the rules that check that nothing answers wait "
    "as long. More for a controller behind a slow adapter or on a loaded host.")]


def command(
    transport: TransportOpt = "serial",
    port: PortOpt = None,
    interface: InterfaceOpt = None,
    channel: ChannelOpt = None,
    bitrate: BitrateOpt = None,
    link_option: LinkOptionOpt = None,
    robot: RobotOpt = "tdam-stm",
    rule: RuleOpt = None,
    estop_pressed: EstopPressedOpt = False,
    json_out: JsonPathOpt = None,
    list_rules: ListOpt = False,
    answer_timeout: AnswerTimeoutOpt = 0.3,
) -> None:
    """Drive a controller through every rule of the protocol and report pass/fail per rule."""
    import sys

    from ..errors import ConfigError
    from ..link.conformance import RULES, run_conformance, select_rules
    from ..link.transport import open_transport, transport_options
    from ..model import load_robot_profile

    if list_rules:
        for name, (_, text, _section) in RULES.items():
            typer.echo(f"{name:<22} {text}")
        return
    require_positive(answer_timeout, "--answer-timeout")
    names = select_rules(rule or [])
    if not names:
        raise ConfigError(f"no rule matches {rule} (see --list)")
    require_writable((json_out, "--json"))  # before the suite runs, not after
    rob = load_robot_profile(robot)
    options = transport_options(transport, port=port, interface=interface, channel=channel,
                                bitrate=bitrate, link_options=link_option)
    link = open_transport(transport, options)
    quiet = json_out == "-"
    try:
        report = run_conformance(
            link, rob, rules=names, estop_pressed=estop_pressed, answer_s=answer_timeout,
            progress=None if quiet else (lambda r: print(
                f"  {r.outcome:<4}  {r.rule}", file=sys.stderr, flush=True)))
    finally:
        link.close()
    _report(report, json_out)


def _report(report, json_out: str | None) -> None:
    """The report: as text (and JSON to a file), or as JSON on stdout; exit 1 if a rule
    failed."""
    import json

    if json_out == "-":
        typer.echo(json.dumps(report.as_dict(), indent=2))
    else:
        typer.echo(report.format())
        if json_out is not None:
            Path(json_out).write_text(json.dumps(report.as_dict(), indent=2) + "\n")
    if not report.ok:
        raise typer.Exit(1)
