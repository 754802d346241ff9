"""Option aliases shared by the commands (one definition, the same flags everywhere)."""

from __future__ import annotations

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
