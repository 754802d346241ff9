"""Fixtures shared by the import/export tests."""

from __future__ import annotations

import pytest

from mecanum_hil.cli import main


@pytest.fixture
def one_line_error(capsys):
    """Run the CLI on ``argv``: it must fail with one ``error: ...`` line; returns the line."""
    def run(argv) -> str:
        code = main(argv)
        err = capsys.readouterr().err.strip()
        assert code != 0 and err.startswith("error: ") and "\n" not in err, err
        return err
    return run
