"""``mecanum-hil demo``: the whole loop on the built-in simulated robot."""


from pathlib import Path
from typing import Annotated

import typer


def command(
    out: Annotated[
        Path, typer.Option("--out", "-o", help="Folder for everything the demo writes.")
    ] = Path("demo-out"),
    full: Annotated[bool, typer.Option(
        "--full", help="The complete demo: all seven of the paper's experiments recorded and "
        "seven overhead-camera runs at 640x480, 30 frames/s (several minutes).")] = False,
    quick: Annotated[bool, typer.Option(
        "--quick", hidden=True, help="The default demo (kept as a name for it).")] = False,
) -> None:
    """Run the whole loop on the simulated robot in miniature (about a minute and a half on
    2 cores): model, record, video, fit, diagnose, shadow, and the robot's pose from an
    overhead camera (slip)."""
    from ..demo import run_demo

    run_demo(out, echo=typer.echo, quick=quick, full=full and not quick)
