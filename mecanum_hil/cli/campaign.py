"""``mecanum-hil campaign``: record an identification campaign from the simulated controller,
in simulated time, with a hidden truth from an effects file."""


import math
from pathlib import Path
from typing import Annotated

import typer

from ._options import CalibrationOpt, JsonOpt, RobotOpt


def _pose_noise(text: str):
    from ..errors import ConfigError

    if text.strip().lower() == "none":
        return None
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) and v >= 0 for v in values):
        raise ConfigError(f"--pose-noise must be X_M,Y_M,PHI_DEG (three numbers >= 0) or none, "
                          f"got {text!r}")
    return values


def command(
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder for the recordings.")],
    effects: Annotated[Path | None, typer.Option(
        "--effects", help="The simulated controller's effects file: the hidden truth "
        "(tables effects.*, unmodelled.*, noise, faults; docs/link-sim.md).",
        metavar="FX.toml")] = None,
    calibration: CalibrationOpt = "paper",
    robot: RobotOpt = "tdam-stm",
    profile: Annotated[list[str] | None, typer.Option(
        "--profile", help="Profiles to record (names or TOML files; repeat the option). "
        "Default: the paper-like campaign.")] = None,
    short: Annotated[bool, typer.Option(
        "--short", help="The shorter campaign (steps of 4, 8, 30, 100, 120 rpm held 1.5 s, "
        "the ramp, turn, strafe, diagonal).")] = False,
    command_rate_hz: Annotated[float, typer.Option(
        "--command-rate", help="Command rate in Hz (at least 5: the watchdog).")] = 50.0,
    telemetry_rate_hz: Annotated[float, typer.Option(
        "--telemetry-rate", help="Telemetry rate in Hz.")] = 100.0,
    pose_noise: Annotated[str, typer.Option(
        "--pose-noise", help="The camera's noise: X in m, Y in m, heading in deg, or none "
        "(no pose).")] = "0.003,0.003,0.3",
    seed: Annotated[int, typer.Option("--seed", min=0, help="Seed of the pose noise.")] = 0,
    json_out: JsonOpt = False,
) -> None:
    """Record a campaign like the paper's from the simulated controller, in simulated time.

    The same firmware and robot as ``sim-robot --effects FX.toml`` behind ``record``, on a
    virtual clock: one recording per profile, as ``record`` writes them, for ``fit`` and
    ``diagnose`` (which are never told what the effects file hides).
    """
    import json

    from ..errors import ConfigError, UsageError
    from ..identify.campaign import SHORT_CAMPAIGN, campaign_profiles, paper_campaign
    from ..io.paths import staged_folder
    from ..io.recording import write_recording
    from ..link.effects_file import load_sim_effects
    from ..model import load_calibration, load_robot_profile
    from ..profiles import resolve_profile

    if profile and short:
        raise UsageError("give --profile or --short, not both")
    if not (math.isfinite(telemetry_rate_hz) and telemetry_rate_hz > 0):
        raise ConfigError(f"--telemetry-rate must be a positive number of Hz, got "
                          f"{telemetry_rate_hz:g}")
    if out.exists() and any(out.glob("*.csv")):
        raise ConfigError(f"{out} already holds recordings: fit and diagnose on {out}/*.csv "
                          "would mix two campaigns; choose a new folder")
    noise = _pose_noise(pose_noise)
    rob = load_robot_profile(robot)
    cal = load_calibration(calibration)
    fx = load_sim_effects(effects) if effects is not None else None
    profiles = [resolve_profile(p) for p in profile] if profile else \
        campaign_profiles(**SHORT_CAMPAIGN) if short else campaign_profiles()
    names = [p.name for p in profiles]
    for name in names:
        if names.count(name) > 1:
            raise ConfigError(f"two profiles are named {name!r}: each is written to "
                              "<name>.csv")
        if not name or name != Path(name).name or name.startswith("."):
            raise ConfigError(f"profile name {name!r} cannot be a file name")
    recs = paper_campaign(fx, rob, calibration=cal, command_rate_hz=command_rate_hz,
                          telemetry_rate_hz=telemetry_rate_hz, pose_noise=noise, seed=seed,
                          profiles=profiles, retime=False)
    files = []
    with staged_folder(out) as stage:  # a campaign cut short leaves none of its recordings
        for rec in recs:
            name = str(rec.metadata["profile"])
            # as record writes them: the truth stays in the effects file, not in the recordings
            meta = {k: v for k, v in rec.metadata.items() if not k.startswith("true_")}
            write_recording(rec.with_values(metadata=meta), stage / f"{name}.csv")
            files.append(out / f"{name}.csv")
    if not json_out:
        for rec, path in zip(recs, files, strict=True):
            tlm = sum(1 for e in rec.extra["event"] if e == "tlm")
            typer.echo(f"{rec.metadata['profile']!s:18s} {rec.t_s[-1]:6.1f} s, {tlm:5d} "
                       f"telemetry samples -> {path}")
    if json_out:
        typer.echo(json.dumps({"recordings": [str(f) for f in files],
                               "effects": str(effects) if effects else None}))
    else:
        typer.echo(f"{len(files)} recordings from the simulated controller "
                   f"(effects: {effects or 'none'}); next: mecanum-hil fit {out}/*.csv --out "
                   "CAL.toml, then mecanum-hil diagnose ... --calibration CAL.toml")
