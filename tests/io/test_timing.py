"""Telemetry re-timed by the controller's clock: a stalled host does not corrupt the data."""

import numpy as np
import pytest

from mecanum_hil.io.recording import Recording
from mecanum_hil.io.timing import controller_offset, retime_telemetry


def recording_with_a_stall(stall_at=1.0, stall_s=0.04, drift=50e-6):
    """Commands at 50 Hz, telemetry at 100 Hz; the host stalls once and receives a burst."""
    cmd_t = np.arange(0, 2, 0.02)
    ctrl = np.arange(0.005, 2, 0.01)               # controller sample times (its own clock)
    recv = ctrl * (1 + drift) + 0.0123 + 0.0003    # offset + link latency
    stalled = (recv > stall_at) & (recv < stall_at + stall_s)
    recv[stalled] = stall_at + stall_s + np.arange(stalled.sum()) * 1e-5
    t = np.concatenate([cmd_t, recv])
    n = np.concatenate([np.where(cmd_t >= 0.5, 60.0, 0.0), np.full(recv.size, np.nan)])
    order = np.argsort(t, kind="stable")
    t, n = t[order], n[order]
    ct = np.concatenate([np.full(cmd_t.size, np.nan), ctrl])[order]
    # rows as record writes them: telemetry rows carry the command in force at receipt
    filled = n.copy()
    for i in range(1, n.size):
        if np.isnan(filled[i]):
            filled[i] = filled[i - 1] if i else 0.0
    cmds = np.column_stack([filled, np.zeros(t.size), np.full(t.size, 90.0)])
    wheels = np.where(np.isnan(ct), np.nan, 1.0)[:, None].repeat(4, axis=1)
    extra = {"controller_time_s": ["" if np.isnan(c) else f"{c:.6f}" for c in ct]}
    return Recording(t, cmds, wheels, np.full((t.size, 3), np.nan), extra), ctrl


def test_offset_is_the_lower_envelope_and_follows_drift():
    rng = np.random.default_rng(0)
    c = np.arange(0, 20, 0.01)
    recv = c * (1 + 80e-6) + 3.0 + rng.exponential(0.0005, c.size)
    a, b = controller_offset(recv, c)
    assert b == pytest.approx(80e-6, abs=5e-6)
    assert np.all(c + a + b * c <= recv + 1e-12)
    assert np.median(recv - (c + a + b * c)) < 0.001


def test_a_stall_no_longer_shifts_the_samples():
    rec, ctrl = recording_with_a_stall()
    out = retime_telemetry(rec)
    tlm = np.isfinite(out.wheel_rpm[:, 0])
    new = out.t_s[tlm]
    expected = ctrl * (1 + 50e-6) + 0.0123 + 0.0003
    assert np.abs(new - expected).max() < 1e-4  # the 40 ms stall is gone
    assert np.all(np.diff(out.t_s) > 0)
    # each telemetry row carries the command in force at its new time
    step = out.t_s[tlm] >= 0.5 + 1e-9
    assert np.all(out.commands[tlm][step, 0] == 60.0)
    assert np.all(out.commands[tlm][~step, 0] == 0.0)
    assert out.metadata["retimed"]["by"] == "controller_time_s"


def test_without_controller_time_nothing_changes():
    rec = Recording(np.arange(3.0), np.zeros((3, 3)), np.ones((3, 4)), np.full((3, 3), np.nan))
    assert retime_telemetry(rec) is rec


@pytest.mark.parametrize(("change", "fragment"), [
    (lambda c: np.where(c > 1.0, c - 3.0, c), "runs back"),            # a controller reset
    (lambda c: np.full_like(c, 5.0), "stands still"),                 # a frozen clock
    (lambda c: c * 1000.0, "a wrong unit or column"),                 # ms in a seconds column
    (lambda c: np.full_like(c, 1e300) + np.arange(c.size), "stands still"),  # nonsense
])
def test_a_controller_clock_that_cannot_be_trusted_is_not_used(change, fragment):
    from mecanum_hil.io.timing import ClockWarning

    rec, _ = recording_with_a_stall()
    ct = rec.extra_numeric("controller_time_s")
    tlm = np.isfinite(ct)
    ct[tlm] = change(ct[tlm])
    bad = rec.with_values(extra={"controller_time_s": [
        "" if np.isnan(c) else repr(float(c)) for c in ct]})
    with pytest.warns(ClockWarning, match=fragment):
        out = retime_telemetry(bad, "run.csv")
    assert out is bad  # timed by the host's receive times, as without the column
