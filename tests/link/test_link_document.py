"""drivers/protocol.md is self-contained: its wheel-target equations and worked example are the
project's kinematics, its rounding of ``time_us`` is the independent controller's, and its
counting of a run without a delimiter is the host's decoder's."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np

from mecanum_hil.link import protocol as proto
from mecanum_hil.model import load_robot_profile
from mecanum_hil.model.kinematics import command_to_wheels

ROOT = Path(__file__).resolve().parents[2]
DOC = " ".join((ROOT / "drivers" / "protocol.md").read_text().split())


def test_the_wheel_target_example_is_the_project_s_kinematics():
    k = load_robot_profile(ROOT / "drivers" / "tdam-stm.toml").k
    assert f"k = 0.465 / 0.102 = {k:.6f}" in DOC
    w = command_to_wheels(60.0, 30.0, 45.0, k)
    assert "`w = (" + ", ".join(f"{x:.3f}" for x in w) + ")` rpm" in DOC
    assert f"`{np.abs(w).max():.3f} = 60 + {k:.6f} × 30 / 6`" in DOC
    beyond = np.abs(command_to_wheels(60.0, 100.0, 45.0, k)).max()
    assert f"`60 + {k * 100 / 6:.3f} = {beyond:.3f}` rpm: refused" in DOC and beyond > 130


def test_the_largest_wheel_target_is_n_plus_k_omega_over_6_whatever_theta():
    rng = np.random.default_rng(0)
    n, omega = rng.uniform(-300, 300, 2000), rng.uniform(-400, 400, 2000)
    theta, k = rng.uniform(-655.36, 655.36, 2000), rng.uniform(0.5, 10.0, 2000)
    peak = np.abs(command_to_wheels(n, omega, theta, k)).max(axis=-1)
    np.testing.assert_allclose(peak, np.abs(n) + k * np.abs(omega) / 6, rtol=1e-12)


def test_time_us_is_rounded_half_up_as_the_document_says():
    spec = importlib.util.spec_from_file_location(
        "independent_controller", ROOT / "tests" / "link" / "independent_controller.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert "At 16000 Hz sample 1 has `time_us` 63 (62.5 rounded up)" in DOC
    assert module.sample_time_us(1, 16000) == 63
    assert module.sample_time_us(3, 16000) == 188  # 187.5
    assert module.sample_time_us(1, 3) == 333333 and module.sample_time_us(2, 3) == 666667


def test_a_run_without_delimiter_is_one_malformed_frame_counted_at_its_67th_byte():
    assert "a 1,000-byte run is one `malformed` frame and 1,000 garbage bytes" in DOC
    dec = proto.StreamDecoder()
    dec.feed(b"\x00" + b"\x41" * 66)
    assert dec.counts.malformed == 0
    dec.feed(b"\x41")  # the 67th byte: counted now, not at the delimiter
    assert dec.counts.malformed == 1
    dec.feed(b"\x41" * 933 + b"\x00")
    assert dec.counts.malformed == 1 and dec.counts.garbage_bytes == 1000
