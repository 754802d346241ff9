"""``mecanum-hil sim-robot``: the simulated controller, serving the wire protocol."""


from pathlib import Path
from typing import Annotated

import typer

from ._options import (
    CalibrationOpt,
    CmdTopicOpt,
    CmdTypeOpt,
    JointTopicOpt,
    OdomTopicOpt,
    RobotOpt,
    require_positive,
)

SerialOpt = Annotated[bool, typer.Option(
    "--serial", help="Serve the framed serial protocol on a new pseudo-terminal; its path "
                     "is the first line of output.")]
CanOpt = Annotated[str | None, typer.Option(
    "--can", metavar="INTERFACE:CHANNEL",
    help="Serve the CAN protocol on a python-can bus (socketcan:can0, virtual:x, ...).")]
SlcanOpt = Annotated[bool, typer.Option(
    "--slcan", help="Play an SLCAN (Lawicel) USB-CAN adapter on a new pseudo-terminal; "
                    "its path is the first line of output.")]
SimTransportOpt = Annotated[str | None, typer.Option(
    "--transport", help="ros2: a simulated ROS 2 robot (cmd_vel in, joint_states and odom "
                        "out, in ROS_DOMAIN_ID); the first line of output is "
                        "'ros2:domain N'.")]
SimJointsOpt = Annotated[str | None, typer.Option(
    "--joints", help="ROS 2: joint names of wheels FL,FR,RL,RR.")]
SimWheelSignsOpt = Annotated[str | None, typer.Option(
    "--wheel-signs", help="ROS 2: +1 or -1 per wheel joint (S1,S2,S3,S4).")]
JointRateOpt = Annotated[float, typer.Option(
    "--joint-rate", help="ROS 2: joint state and odometry rate [Hz].")]
BestEffortOpt = Annotated[bool, typer.Option(
    "--best-effort", help="ROS 2: publish joint states and odometry best effort "
                          "(sensor-data QoS).")]
ClockOffsetOpt = Annotated[float, typer.Option(
    "--clock-offset", help="ROS 2: the robot's clock minus the host's [s] (a robot "
                           "without NTP).")]
EffectsOpt = Annotated[Path | None, typer.Option(
    "--effects", help="TOML file of extra effects, noise and timed faults "
                      "(docs/link-sim.md).")]
TelemetryRateOpt = Annotated[float, typer.Option(
    "--telemetry-rate", help="Telemetry rate [Hz]: 0 sends none, else 1 Hz up to the "
                             "internal rate, a whole divisor of it within 1%.")]
InternalRateOpt = Annotated[float, typer.Option(
    "--internal-rate", help="Rate of the model's internal tick [Hz].")]
DurationOpt = Annotated[float | None, typer.Option(
    "--duration", help="Stop after this long [s] (default: until killed).")]
ProtocolVersionOpt = Annotated[int | None, typer.Option(
    "--protocol-version", hidden=True,
    help="Protocol version to claim (tests of a version mismatch).")]
QuietOpt = Annotated[bool, typer.Option("--quiet", help="No event log on stderr.")]


def command(
    serial: SerialOpt = False,
    can: CanOpt = None,
    slcan: SlcanOpt = False,
    transport: SimTransportOpt = None,
    cmd_topic: CmdTopicOpt = "/cmd_vel",
    cmd_type: CmdTypeOpt = "twist",
    joint_topic: JointTopicOpt = "/joint_states",
    odom_topic: OdomTopicOpt = "/odom",
    joints: SimJointsOpt = None,
    wheel_signs: SimWheelSignsOpt = None,
    joint_rate_hz: JointRateOpt = 50.0,
    best_effort: BestEffortOpt = False,
    clock_offset_s: ClockOffsetOpt = 0.0,
    calibration: CalibrationOpt = "paper",
    robot: RobotOpt = "tdam-stm",
    effects: EffectsOpt = None,
    telemetry_rate_hz: TelemetryRateOpt = 100.0,
    internal_rate_hz: InternalRateOpt = 1000.0,
    duration_s: DurationOpt = None,
    protocol_version: ProtocolVersionOpt = None,
    quiet: QuietOpt = False,
) -> None:
    """Run the simulated robot controller until stopped (SIGTERM or Ctrl-C)."""
    _check(transport, telemetry_rate_hz, internal_rate_hz, duration_s)
    model, cal, sim_fx = _model(calibration, robot, effects, internal_rate_hz)
    log = _logger(quiet)
    if transport == "ros2":
        ros2 = dict(cmd_topic=cmd_topic, cmd_type=cmd_type, joint_topic=joint_topic,
                    odom_topic=odom_topic, joints=joints, wheel_signs=wheel_signs,
                    joint_rate_hz=joint_rate_hz, best_effort=best_effort,
                    clock_offset_s=clock_offset_s)
        return _serve_ros2(model, ros2, duration_s, log)
    kind = "serial" if serial else "slcan" if slcan else "can"
    _serve_wire(kind, can, model, (cal, sim_fx), telemetry_rate_hz, protocol_version,
                duration_s, log)


def _check(transport: str | None, telemetry_rate_hz: float, internal_rate_hz: float,
           duration_s: float | None) -> None:
    """One-line errors for a transport, rate or duration the simulator cannot serve."""
    from ..errors import ConfigError

    if transport not in (None, "ros2"):
        raise ConfigError(f"--transport takes ros2 (--serial, --slcan and --can serve the "
                          f"wire protocol), got {transport!r}")
    _check_telemetry_rate(telemetry_rate_hz, internal_rate_hz)
    require_positive(duration_s, "--duration")


def _model(calibration: str, robot: str, effects: Path | None, internal_rate_hz: float):
    """``(the controller's model, compiled; its calibration; the extra effects or None)``."""
    import os

    # one robot per process: spare the machine's cores (set before numba is imported)
    from ..link.sim_process import SINGLE_THREAD_ENV

    for key, value in SINGLE_THREAD_ENV.items():
        os.environ.setdefault(key, value)

    from ..link.effects_file import load_sim_effects
    from ..link.simulated import ControllerModel
    from ..model import load_calibration, load_robot_profile

    cal = load_calibration(calibration)
    rob = load_robot_profile(robot)
    sim_fx = load_sim_effects(effects) if effects is not None else None
    model = ControllerModel(cal, rob, sim_fx, rate_hz=internal_rate_hz)
    model.wheel_rpm(0)  # compile/load the simulator before announcing readiness
    return model, cal, sim_fx


def _logger(quiet: bool):
    """The event log: one ``sim-robot:`` line on stderr each (nothing with ``--quiet``)."""
    import sys

    def log(line: str) -> None:
        if not quiet:
            print(f"sim-robot: {line}", file=sys.stderr, flush=True)
    return log


def _serve_wire(kind: str, can: str | None, model, sources, telemetry_rate_hz: float,
                protocol_version: int | None, duration_s: float | None, log) -> None:
    """Serve the wire protocol (serial, SLCAN or CAN) until SIGTERM, Ctrl-C or
    ``duration_s``; ``sources``: the calibration and extra effects (or None) named in the
    log."""
    import os
    import signal

    from ..link.protocol import PROTOCOL_VERSION
    from ..link.simulated import SimulatedController, open_controller_end

    cal, sim_fx = sources
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


def _serve_ros2(model, options: dict, duration_s: float | None, log) -> None:
    """Serve the simulated ROS 2 robot until SIGTERM, Ctrl-C or ``duration_s``."""
    import signal

    from ..errors import ConfigError
    from ..importers.rosbag import parse_joints, parse_wheel_signs
    from ..link.ros2.node import CMD_TYPES, Ros2Node
    from ..link.ros2.sim_robot import DEFAULT_JOINTS, SimulatedRos2Robot

    if options["cmd_type"] not in CMD_TYPES:  # before the participant is created
        raise ConfigError(f"--cmd-type must be one of {', '.join(CMD_TYPES)}, "
                          f"got {options['cmd_type']!r}")
    require_positive(options["joint_rate_hz"], "--joint-rate", "Hz")
    joints = parse_joints(options.pop("joints")) if options["joints"] else DEFAULT_JOINTS
    signs = parse_wheel_signs(options.pop("wheel_signs") or "1,1,1,1")
    options.pop("joints", None)
    options.pop("wheel_signs", None)
    node = Ros2Node()
    try:
        robot = SimulatedRos2Robot(model, node, joints=joints, wheel_signs=signs, log=log,
                                   **options)
        signal.signal(signal.SIGTERM, lambda signum, frame: robot.stop_event.set())
        print(f"ros2:domain {node.domain}", flush=True)
        log(f"serving ROS 2 in domain {node.domain}: {options['cmd_topic']} in, "
            f"{options['joint_topic']} and {options['odom_topic'] or 'no odometry'} out")
        try:
            robot.serve(duration_s)
        except KeyboardInterrupt:
            pass  # Ctrl-C is how it is stopped (as SIGTERM): a normal end, exit 0
        log(f"stopped; {robot.commands_received} commands, {robot.stale_commands} refused as "
            f"stale, {robot.timeouts} reference timeouts, last command {robot.last_twist}")
    finally:
        node.close()
