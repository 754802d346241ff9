"""``mecanum-hil demo``: the whole loop on the built-in simulated robot."""


from pathlib import Path
from typing import Annotated

import typer


def command(
    out: Annotated[
        Path, typer.Option("--out", "-o", help="Folder for everything the demo writes.")
    ] = Path("demo-out"),
    quick: Annotated[bool, typer.Option(
        "--quick", help="Record two of the paper's experiments instead of all seven; no "
        "overhead-camera pose stage.")] = False,
) -> None:
    """Run the whole loop on the simulated robot: model, record, video, fit, diagnose, shadow,
    and the robot's pose from an overhead camera (slip)."""
    from ..demo import run_demo

    run_demo(out, echo=typer.echo, quick=quick)
