"""Time as real loggers write it: repeated stamps, jitter, gaps, a wrapping counter."""

import warnings

import numpy as np
import pytest

from mecanum_hil.errors import RecordingError
from mecanum_hil.io.recording import COLUMNS, TimeRepairWarning, read_recording
from mecanum_hil.io.time_repair import decimal_resolution, detect_resolution, repair_time

MS = 1e-3


def stamps(n=970, period=MS):
    return np.round(np.arange(n) * period, 6)


def test_a_clean_log_is_left_alone():
    t = stamps()
    rep = repair_time(t)
    assert not rep.changed and rep.note == ""
    np.testing.assert_array_equal(rep.t_s, t)


def test_resolution_is_the_coarsest_decimal_step():
    assert detect_resolution(stamps()) == pytest.approx(1e-3)
    assert detect_resolution(np.array([0.0, 0.0015, 0.003])) == pytest.approx(1e-4)
    assert detect_resolution(np.array([0.0, np.pi])) == 0.0


def test_three_repeated_stamps_of_970_are_respaced_within_the_resolution():
    truth = np.arange(970) * 0.9995e-3  # a sampling clock slightly fast for the 1 ms stamps
    t = np.floor(truth / MS + 1e-9) * MS
    t[[100, 500, 800]] = t[[99, 499, 799]]
    rep = repair_time(t)
    assert rep.changed and len(rep.t_s) == 970  # no sample dropped
    assert np.all(np.diff(rep.t_s) > 0)
    assert np.max(np.abs(rep.t_s - truth)) <= 1.5 * MS
    assert "median period 1.000 ms" in rep.note and "repeated stamps" in rep.note
    assert "\n" not in rep.note
    assert rep.summary["repeated_stamps"] >= 3


def test_jitter_at_the_resolution_is_undone():
    rng = np.random.default_rng(3)
    truth = stamps(2000)
    jitter = np.where(rng.random(2000) < 0.05, rng.choice([-1.0, 1.0], 2000), 0.0) * MS
    t = np.round(truth + jitter, 6)
    rep = repair_time(t)
    assert np.all(np.diff(rep.t_s) > 0)
    assert np.max(np.abs(rep.t_s - truth)) <= MS + 1e-9
    assert rep.summary["gaps"] == 0  # jitter is not taken for missing samples
    assert "back within the resolution" in rep.note


def test_small_gaps_are_kept_and_counted_not_filled():
    t = np.delete(stamps(), [300, 301, 302, 600])
    rep = repair_time(t)
    np.testing.assert_array_equal(rep.t_s, t)
    assert rep.summary["gaps"] == 2 and rep.summary["missing_samples"] == 4
    assert "2 gaps kept (4 missing samples, longest 4.000 ms)" in rep.note


def test_a_gap_over_the_stated_limit_is_an_error_naming_the_row():
    t = np.delete(stamps(), range(300, 320))
    with pytest.raises(RecordingError, match=r"row 301: a gap of 0.021 s .* limit of 0.01 s"):
        repair_time(t, max_gap_s=0.01)


def test_time_running_back_beyond_the_resolution_is_an_error_naming_the_row():
    t = stamps()
    t[400:] -= 0.005
    with pytest.raises(RecordingError,
                       match=r"row 401: time 0.395 s does not increase: it runs back 4.000 ms"):
        repair_time(t)


def test_a_wrapping_millisecond_counter_is_unwrapped():
    counter = (np.arange(60000) + 65000) % 65536  # uint16 milliseconds: wraps once
    rep = repair_time(counter * MS)
    np.testing.assert_allclose(np.diff(rep.t_s), MS)
    assert rep.summary["wraps"] == 1 and rep.summary["wrap_s"] == pytest.approx(65.536)
    assert "1 wrap of a 65.536 s counter unwrapped" in rep.note


def test_a_stated_modulus_is_used():
    counter = (np.arange(3000) + 900) % 1000  # a 1000-tick counter, too short to be guessed
    rep = repair_time(counter * MS, wrap_s=1.0)
    np.testing.assert_allclose(np.diff(rep.t_s), MS)
    with pytest.raises(RecordingError, match="runs back"):
        repair_time(counter * MS)


HEADER = ",".join(COLUMNS)


def _write(path, times):
    rows = [f"{t:.3f},10,0,90,{i % 7},,,,,," for i, t in enumerate(times)]
    path.write_text(HEADER + "\n" + "\n".join(rows) + "\n")


def test_reading_a_recording_repairs_repeated_stamps_and_warns_once(tmp_path):
    t = stamps()
    t[[100, 500, 800]] = t[[99, 499, 799]]
    p = tmp_path / "rec.csv"
    _write(p, t)
    before = p.read_text()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rec = read_recording(p)
    msgs = [str(w.message) for w in caught if issubclass(w.category, TimeRepairWarning)]
    assert len(msgs) == 1 and "3 repeated stamps" in msgs[0] and str(p) in msgs[0]
    assert len(rec) == 970 and np.all(np.diff(rec.t_s) > 0)
    assert rec.metadata["time_repair"]["repeated_stamps"] == 3
    assert p.read_text() == before  # the file is not changed


def test_reading_a_recording_that_runs_back_names_the_line(tmp_path):
    t = stamps()
    t[400:] -= 0.005
    p = tmp_path / "rec.csv"
    _write(p, t)
    with pytest.raises(RecordingError,
                       match=r"line 402, column 't_s': time 0.395 s does not increase"):
        read_recording(p)


@pytest.mark.parametrize("seed", range(20))
def test_repaired_time_always_increases_and_stays_near_its_stamps(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(50, 3000))
    period = float(rng.choice([1e-3, 2e-3, 0.5e-3]))
    res = 1e-3
    truth = np.cumsum(np.where(rng.random(n) < 0.01, 3, 1)) * period  # a few gaps
    t = np.floor(truth / res + rng.uniform(-0.9, 0.9, n) * (rng.random(n) < 0.1)) * res
    t = np.maximum.accumulate(t) - (rng.random(n) < 0.02) * res  # some stamps a tick back
    rep = repair_time(np.round(t, 9), resolution_s=res)
    assert rep.t_s.size == n and np.all(np.diff(rep.t_s) > 0)
    assert np.max(np.abs(rep.t_s - t)) <= 2 * res + 3 * period + 1e-12


def test_the_resolution_is_what_the_log_writes():
    assert decimal_resolution(["0.340", "0.341", "12"]) == pytest.approx(1e-3)
    assert decimal_resolution(["65000", "65001"]) == 1.0
    assert decimal_resolution(["0.010000"]) == pytest.approx(1e-6)
    assert decimal_resolution(["1e-3"]) is None and decimal_resolution([]) is None
    # a clean 100 Hz grid written with 6 decimals: two swapped rows run back 10 ms, not jitter
    t = np.round(np.arange(100) * 0.01, 6)
    t[[5, 6]] = t[[6, 5]]
    with pytest.raises(RecordingError, match=r"row 7: time 0.05 s does not increase"):
        repair_time(t, resolution_s=decimal_resolution([f"{v:.6f}" for v in t]))
