"""The reference controller firmware (drivers/firmware), built once per test process into a
temporary folder: the POSIX host port under AddressSanitizer and UBSan (any memory error or
undefined behaviour ends it with an error, which the tests see), and the shared library the
property tests drive through ctypes."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest
from controller_checks import ControllerProcess
from firmware_make import make

SANITIZE = "-fsanitize=address,undefined -fno-sanitize-recover=all -fno-omit-frame-pointer"


@pytest.fixture(scope="session")
def firmware_build(tmp_path_factory) -> Path:
    """A folder holding ``mh-controller`` (sanitized) and ``libmh_harness.so``."""
    missing = [tool for tool in ("cc", "make") if shutil.which(tool) is None]
    if missing:
        pytest.skip(f"no {' or '.join(missing)} on this machine: the C firmware is not built")
    build = tmp_path_factory.mktemp("firmware")
    make(build, "host", "shared", HOST_CFLAGS=SANITIZE)
    return build


class HostController(ControllerProcess):
    """The POSIX host port in its own process, serving on a pseudo-terminal."""

    def __init__(self, build: Path, *args: str) -> None:
        super().__init__([str(build / "mh-controller"), *args],
                         env={**os.environ, "ASAN_OPTIONS": "detect_leaks=1"})


@pytest.fixture
def host_controller(firmware_build):
    """Factory of host-port controllers (options as arguments), stopped at the end."""
    made: list[HostController] = []

    def start(*args: str) -> HostController:
        ctl = HostController(firmware_build, *args)
        made.append(ctl)
        return ctl

    yield start
    for ctl in made:
        if ctl.proc.poll() is None:
            ctl.proc.kill()
            ctl.proc.wait(5)
