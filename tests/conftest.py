"""Shared test fixtures."""

from __future__ import annotations

from pathlib import Path

import pytest

# before numpy loads: importing the package sets OPENBLAS_NUM_THREADS (mecanum_hil/__init__.py)
import mecanum_hil  # noqa: F401

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture(autouse=True)
def _host_timing_is_not_judged(monkeypatch):
    """A loaded machine pauses the test process's command stream for longer than half a
    controller watchdog, and delays a scripted controller whose clock counts its samples:
    ``record`` would end such runs with ``host_stall`` or ``clock_drift``. Tests of other
    behaviour do not judge either (the environment reaches the commands tests start as
    subprocesses too); the tests of those rules set ``SessionConfig``'s fields themselves."""
    monkeypatch.setenv("MECANUM_HIL_HOST_STALL_SHARE", "inf")
    monkeypatch.setenv("MECANUM_HIL_CLOCK_DRIFT_SLACK_S", "inf")


@pytest.fixture(scope="session")
def repo() -> Path:
    """The repository root."""
    return REPO


@pytest.fixture(scope="session")
def shared_real_data() -> Path:
    """../shared/data/real, or skip when this checkout has no shared folder beside it."""
    path = SHARED_DATA / "real"
    if not path.is_dir():
        pytest.skip("../shared/data/real is not present beside this checkout")
    return path


@pytest.fixture
def one_line_error(capsys):
    """Run the CLI on ``argv``: it must fail with one ``error: ...`` line; returns the line."""
    from mecanum_hil.cli import main

    def run(argv) -> str:
        code = main(argv)
        err = capsys.readouterr().err.strip()
        assert code != 0 and err.startswith("error: ") and "\n" not in err, err
        return err
    return run
