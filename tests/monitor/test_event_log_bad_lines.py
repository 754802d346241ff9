"""``export --events`` with bad lines: one error line naming the file and the line, not a
traceback (AttributeError, KeyError, OverflowError ...) nor 0 events exported silently."""

from __future__ import annotations

import pytest

pytest.importorskip("mcap")

BAD_LINES = {
    "array": ("[1,2,3]", "not an event"),
    "nan": ('{"t_s": NaN, "event": "x"}', "t_s"),
    "huge": ('{"t_s": 1e300, "event": "x"}', "t_s"),
    "text_time": ('{"t_s": "abc", "event": "recovered"}', "t_s"),
    "alarm_no_channel": ('{"t_s": 1, "event": "alarm"}', "channel"),
    "noise_no_channel": ('{"t_s": 1, "event": "noise"}', "channel"),
    "only_line_not_json": ("not json", "not JSON"),
}


@pytest.mark.parametrize("case", sorted(BAD_LINES))
def test_a_bad_event_line_is_one_error_naming_file_and_line(repo, tmp_path, one_line_error,
                                                            case):
    line, expect = BAD_LINES[case]
    events = tmp_path / "ev.jsonl"
    events.write_text('{"event": "start", "t_s": null}\n' + line + "\n"
                      if case != "only_line_not_json" else line + "\n")
    number = 1 if case == "only_line_not_json" else 2
    err = one_line_error(["export", str(repo / "recordings/samples/paper-turn.csv"), "-o",
                          str(tmp_path / "run.mcap"), "--events", str(events)])
    assert f"{events}, line {number}: " in err and expect in err
    assert "internal error" not in err
    assert not (tmp_path / "run.mcap").exists()


def test_a_cut_last_line_after_good_ones_is_still_dropped(repo, tmp_path, capsys):
    from mecanum_hil.cli import main

    events = tmp_path / "ev.jsonl"
    events.write_text('{"event": "recovered", "t_s": 1.0, "channel": "FL"}\n{"event": "al')
    assert main(["export", str(repo / "recordings/samples/paper-turn.csv"), "-o",
                 str(tmp_path / "run.mcap"), "--events", str(events)]) == 0
    assert "/mecanum/alarms 1" in capsys.readouterr().out
