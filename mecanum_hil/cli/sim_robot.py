"""``mecanum-hil sim-robot``: the simulated controller, serving the wire protocol."""


from pathlib import Path
from typing import Annotated

import typer

from ._options import CalibrationOpt, RobotOpt, require_positive


def command(
    serial: Annotated[bool, typer.Option(
        "--serial", help="Serve the framed serial protocol on a new pseudo-terminal; its path "
                         "is the first line of output.")] = False,
    can: Annotated[str | None, typer.Option(
        "--can", metavar="INTERFACE:CHANNEL",
        help="Serve the CAN protocol on a python-can bus (socketcan:can0, virtual:x, ...).")
    ] = None,
    slcan: Annotated[bool, typer.Option(
        "--slcan", help="Play an SLCAN (Lawicel) USB-CAN adapter on a new pseudo-terminal; "
                        "its path is the first line of output.")] = False,
    calibration: CalibrationOpt = "paper",
    robot: RobotOpt = "tdam-stm",
    effects: Annotated[Path | None, typer.Option(
        "--effects", help="TOML file of extra effects, noise and timed faults "
                          "(docs/link.md).")] = None,
    telemetry_rate_hz: Annotated[float, typer.Option(
        "--telemetry-rate", help="Telemetry rate [Hz]: 0 sends none, else 1 Hz up to the "
                                 "internal rate, a whole divisor of it within 1%.")] = 100.0,
    internal_rate_hz: Annotated[float, typer.Option(
        "--internal-rate", help="Rate of the model's internal tick [Hz].")] = 1000.0,
    duration_s: Annotated[float | None, typer.Option(
        "--duration", help="Stop after this long [s] (default: until killed).")] = None,
    protocol_version: Annotated[int | None, typer.Option(
        "--protocol-version", hidden=True,
        help="Protocol version to claim (tests of a version mismatch).")] = None,
    quiet: Annotated[bool, typer.Option("--quiet", help="No event log on stderr.")] = False,
) -> None:
    """Run the simulated robot controller until stopped (SIGTERM or Ctrl-C)."""
    import os
    import signal
    import sys

    from ..link.protocol import PROTOCOL_VERSION

    _check_telemetry_rate(telemetry_rate_hz, internal_rate_hz)
    require_positive(duration_s, "--duration")
    # one robot per process: spare the machine's cores (set before numba is imported)
    from ..link.sim_process import SINGLE_THREAD_ENV

    for key, value in SINGLE_THREAD_ENV.items():
        os.environ.setdefault(key, value)

    from ..link.effects_file import load_sim_effects
    from ..link.simulated import ControllerModel, SimulatedController, open_controller_end
    from ..model import load_calibration, load_robot_profile

    cal = load_calibration(calibration)
    rob = load_robot_profile(robot)
    sim_fx = load_sim_effects(effects) if effects is not None else None
    model = ControllerModel(cal, rob, sim_fx, rate_hz=internal_rate_hz)
    model.wheel_rpm(0)  # compile/load the simulator before announcing readiness

    def log(line: str) -> None:
        if not quiet:
            print(f"sim-robot: {line}", file=sys.stderr, flush=True)

    kind = "serial" if serial else "slcan" if slcan else "can"
    transport, where, keep = open_controller_end(kind, can)
    ctrl = SimulatedController(transport, model, telemetry_rate_hz,
                               version=protocol_version or PROTOCOL_VERSION, log=log)
    signal.signal(signal.SIGTERM, lambda signum, frame: ctrl.stop_event.set())
    print(where, flush=True)
    log(f"serving on {where} ({kind}); calibration {cal.source}"
        + (f", effects {sim_fx.source}" if sim_fx else ""))
    try:
        ctrl.serve(duration_s)
    except KeyboardInterrupt:
        pass  # Ctrl-C is how it is stopped (as SIGTERM): a normal end, exit 0
    finally:
        transport.close()
        for fd in keep:
            os.close(fd)
        log(f"stopped; {ctrl.commands_received} commands, {ctrl.stops_received} stops, "
            f"{ctrl.bad_commands} commands refused, {transport.stats.sent} frames sent, "
            f"{model.calls} model calls")


def _check_telemetry_rate(telemetry_rate_hz: float, internal_rate_hz: float) -> None:
    """Refuse a telemetry rate the internal tick cannot give (within 1 %)."""
    from ..errors import ConfigError
    from ..link.simulated import telemetry_ticks_for

    ticks = telemetry_ticks_for(telemetry_rate_hz, internal_rate_hz)  # ConfigError if not
    if ticks and abs(internal_rate_hz / ticks - telemetry_rate_hz) > 0.01 * telemetry_rate_hz:
        # samples are taken on ticks: say so rather than send another rate than asked for
        raise ConfigError(f"--telemetry-rate {telemetry_rate_hz:g} Hz is not a whole divisor "
                          f"of the {internal_rate_hz:g} Hz internal tick; the nearest it gives "
                          f"is {internal_rate_hz / ticks:.6g} Hz")
