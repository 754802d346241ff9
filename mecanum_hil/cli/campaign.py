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


FolderOutOpt = Annotated[Path, typer.Option("--out", "-o", help="Folder for the recordings.")]
EffectsOpt = Annotated[Path | None, typer.Option(
    "--effects", help="The simulated controller's effects file: the hidden truth "
    "(tables effects.*, unmodelled.*, noise, faults; docs/link-sim.md).",
    metavar="FX.toml")]
ProfilesOpt = Annotated[list[str] | None, typer.Option(
    "--profile", help="Profiles to record (names or TOML files; repeat the option). "
    "Default: the paper-like campaign.")]
ShortOpt = Annotated[bool, typer.Option(
    "--short", help="The shorter campaign (steps of 4, 8, 30, 100, 120 rpm held 1.5 s, "
    "the ramp, turn, strafe, diagonal).")]
CommandRateOpt = Annotated[float, typer.Option(
    "--command-rate", help="Command rate in Hz (at least 5: the watchdog).")]
TelemetryRateOpt = Annotated[float, typer.Option(
    "--telemetry-rate", help="Telemetry rate in Hz.")]
PoseNoiseOpt = Annotated[str, typer.Option(
    "--pose-noise", help="The camera's noise: X in m, Y in m, heading in deg, or none "
    "(no pose).")]
SeedOpt = Annotated[int, typer.Option("--seed", min=0, help="Seed of the pose noise.")]


def command(
    out: FolderOutOpt,
    effects: EffectsOpt = None,
    calibration: CalibrationOpt = "paper",
    robot: RobotOpt = "tdam-stm",
    profile: ProfilesOpt = None,
    short: ShortOpt = False,
    command_rate_hz: CommandRateOpt = 50.0,
    telemetry_rate_hz: TelemetryRateOpt = 100.0,
    pose_noise: PoseNoiseOpt = "0.003,0.003,0.3",
    seed: SeedOpt = 0,
    json_out: JsonOpt = False,
) -> None:
    """Record a campaign like the paper's from the simulated controller, in simulated time.

    The same firmware and robot as ``sim-robot --effects FX.toml`` behind ``record``, on a
    virtual clock: one recording per profile, as ``record`` writes them, for ``fit`` and
    ``diagnose`` (which are never told what the effects file hides).
    """
    from ..identify.campaign import paper_campaign
    from ..link.effects_file import load_sim_effects
    from ..model import load_calibration, load_robot_profile

    _check(out, profile, short, telemetry_rate_hz)
    noise = _pose_noise(pose_noise)
    rob = load_robot_profile(robot)
    cal = load_calibration(calibration)
    fx = load_sim_effects(effects) if effects is not None else None
    profiles = _profiles(profile, short)
    recs = paper_campaign(fx, rob, calibration=cal, command_rate_hz=command_rate_hz,
                          telemetry_rate_hz=telemetry_rate_hz, pose_noise=noise, seed=seed,
                          profiles=profiles, retime=False)
    files = _write(recs, out)
    _print(recs, files, out, effects, json_out)


def _check(out: Path, profile: list[str] | None, short: bool, telemetry_rate_hz: float) -> None:
    """One-line errors for options that do not go together, a rate, a folder already used."""
    from ..errors import ConfigError, UsageError

    if profile and short:
        raise UsageError("give --profile or --short, not both")
    if not (math.isfinite(telemetry_rate_hz) and telemetry_rate_hz > 0):
        raise ConfigError(f"--telemetry-rate must be a positive number of Hz, got "
                          f"{telemetry_rate_hz:g}")
    if out.exists() and any(out.glob("*.csv")):
        raise ConfigError(f"{out} already holds recordings: fit and diagnose on {out}/*.csv "
                          "would mix two campaigns; choose a new folder")


def _profiles(profile: list[str] | None, short: bool) -> list:
    """The profiles to record, each with a name that makes a file name of its own."""
    from ..errors import ConfigError
    from ..identify.campaign import SHORT_CAMPAIGN, campaign_profiles
    from ..profiles import resolve_profile

    profiles = [resolve_profile(p) for p in profile] if profile else \
        campaign_profiles(**SHORT_CAMPAIGN) if short else campaign_profiles()
    names = [p.name for p in profiles]
    for name in names:
        if names.count(name) > 1:
            raise ConfigError(f"two profiles are named {name!r}: each is written to "
                              "<name>.csv")
        if not name or name != Path(name).name or name.startswith("."):
            raise ConfigError(f"profile name {name!r} cannot be a file name")
    return profiles


def _write(recs: list, out: Path) -> list[Path]:
    """Write each recording to ``out/<profile>.csv`` (all of them, or none); their paths."""
    from ..io.paths import staged_folder
    from ..io.recording import write_recording

    files = []
    with staged_folder(out) as stage:  # a campaign cut short leaves none of its recordings
        for rec in recs:
            name = str(rec.metadata["profile"])
            # as record writes them: the truth stays in the effects file, not in the recordings
            meta = {k: v for k, v in rec.metadata.items() if not k.startswith("true_")}
            write_recording(rec.with_values(metadata=meta), stage / f"{name}.csv")
            files.append(out / f"{name}.csv")
    return files


def _print(recs: list, files: list[Path], out: Path, effects: Path | None,
           json_out: bool) -> None:
    """A line per recording and what to run next, or JSON."""
    import json

    if json_out:
        typer.echo(json.dumps({"recordings": [str(f) for f in files],
                               "effects": str(effects) if effects else None}))
        return
    for rec, path in zip(recs, files, strict=True):
        tlm = sum(1 for e in rec.extra["event"] if e == "tlm")
        typer.echo(f"{rec.metadata['profile']!s:18s} {rec.t_s[-1]:6.1f} s, {tlm:5d} "
                   f"telemetry samples -> {path}")
    typer.echo(f"{len(files)} recordings from the simulated controller "
               f"(effects: {effects or 'none'}); next: mecanum-hil fit {out}/*.csv --out "
               "CAL.toml, then mecanum-hil diagnose ... --calibration CAL.toml")
