"""``mecanum-hil demo``: the whole loop on the built-in simulated robot."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer


def command(
    out: Annotated[
        Path, typer.Option("--out", "-o", help="Folder for recordings and plots.")
    ] = Path("demo-out"),
) -> None:
    """Run the paper's experiments on the model; write recordings and plots into a folder."""
    from ..demo import run_demo

    run_demo(out, echo=typer.echo)
