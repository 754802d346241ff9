"""Building the reference controller firmware (drivers/firmware) with its Makefile."""

from __future__ import annotations

import subprocess
from pathlib import Path

FIRMWARE = Path(__file__).resolve().parents[2] / "drivers" / "firmware"


def make(build: Path, *targets: str, **variables: str) -> subprocess.CompletedProcess:
    """``make -C drivers/firmware BUILD=build TARGETS``; fails the test on a build error."""
    args = ["make", "-s", "-C", str(FIRMWARE), f"BUILD={build}", *targets,
            *(f"{k}={v}" for k, v in variables.items())]
    done = subprocess.run(args, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    return done
