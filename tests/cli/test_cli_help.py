"""Every command's ``--help`` shows units as ``[rpm]``: the help is click's plain text, so a
backslash meant to escape rich markup would be printed as it stands."""

from __future__ import annotations

import pytest

from mecanum_hil.cli import _COMMANDS


@pytest.mark.parametrize("name", ["", *sorted(_COMMANDS)])
def test_help_shows_no_backslash(capsys, name):
    from mecanum_hil.cli import main

    assert main([name, "--help"] if name else ["--help"]) == 0
    out = capsys.readouterr().out
    assert f"Usage: mecanum-hil {name}".strip() in out
    assert "\\" not in out, [line for line in out.splitlines() if "\\" in line]


def test_units_show_in_brackets(capsys):
    from mecanum_hil.cli import main

    assert main(["shadow", "--help"]) == 0
    assert "[rpm]" in capsys.readouterr().out
