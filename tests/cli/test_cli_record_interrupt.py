"""What Ctrl-C and SIGTERM print at the end of ``record``: its summary, whose first line names
the reason, then the one line every command cut short by them says (README, docs/link.md)."""

from __future__ import annotations

import os
import re
import tty
from pathlib import Path

import pytest

from mecanum_hil.cli import main
from mecanum_hil.link import session
from mecanum_hil.link.session import RecordResult

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize(("reason", "code", "line"), [
    ("interrupted", 130, "error: interrupted"),
    ("terminated", 143, "error: terminated by a signal")])
def test_record_cut_short_prints_its_summary_then_the_signal_s_line(
        reason, code, line, tmp_path, monkeypatch, capsys):
    master, slave = os.openpty()
    tty.setraw(slave)

    def cut_short(transport, t_s, commands, out, robot, **kw):  # a run the signal ended
        return RecordResult(reason, code, Path(out), 10, 5, 4, 1.28,
                            transport.stats.as_dict(), {})

    monkeypatch.setattr(session, "run_record_session", cut_short)
    try:
        assert main(["record", "--port", os.ttyname(slave), "--profile", "paper-step-60",
                     "--out", str(tmp_path / "x.csv"), "--no-progress"]) == code
    finally:
        os.close(master)
        os.close(slave)
    out, err = capsys.readouterr()
    assert out.startswith(f"{reason} (exit {code}) after 1.28 s\n")
    assert err == line + "\n"


def test_the_readme_and_docs_say_what_ctrl_c_prints():
    readme = " ".join((ROOT / "README.md").read_text().split())
    link = " ".join((ROOT / "docs" / "link.md").read_text().split())
    assert "(Ctrl-C, which says `error: interrupted`, exit 130;" in readme
    assert re.search(r"`interrupted \(exit 130\) after T s`.*`error: interrupted`", link)
