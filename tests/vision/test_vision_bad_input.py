"""Bad input: one clear line and a non-zero exit where no trustworthy result exists."""

from __future__ import annotations

import json
import math
import os
import queue
import threading
import time

import numpy as np
import pytest
from vision_cases import steady

from mecanum_hil.cli import main
from mecanum_hil.errors import VideoError
from mecanum_hil.io.recording import read_recording, write_recording
from mecanum_hil.vision import MeasureOptions, RenderSettings, measure_video, render_video
from mecanum_hil.vision.video import VideoWriter, decode_ahead, frame_times, open_video


@pytest.fixture(scope="session")
def good_video(tmp_path_factory):
    path = tmp_path_factory.mktemp("vid") / "good.avi"
    return render_video(steady(60.0, 2.0), path, RenderSettings(noise_std=2.0))


def run_cli(args, capsys):
    code = main(args)
    out = capsys.readouterr()
    return code, out.out, out.err


def one_error_line(err: str) -> str:
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("error: ")
    assert "Traceback" not in err
    return lines[0]


def test_missing_file(tmp_path, capsys):
    code, _, err = run_cli(["measure-video", str(tmp_path / "nope.mp4"), "--out",
                            str(tmp_path / "o.csv")], capsys)
    assert code == 1 and "file not found" in one_error_line(err)


def test_undecodable_file(tmp_path, capsys):
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(bytes(np.random.default_rng(0).integers(0, 256, 4000, dtype=np.uint8)))
    code, _, err = run_cli(["measure-video", str(junk), "--out", str(tmp_path / "o.csv")],
                           capsys)
    assert code == 1 and "OpenCV can decode" in one_error_line(err)


def test_truncated_mp4_is_refused(tmp_path, capsys):
    res = render_video(steady(60.0, 1.0), tmp_path / "t.mp4")
    data = res.path.read_bytes()
    res.path.write_bytes(data[: len(data) // 2])  # the index (moov) at the end is lost
    code, _, err = run_cli(["measure-video", str(res.path), "--out", str(tmp_path / "o.csv")],
                           capsys)
    assert code == 1
    one_error_line(err)


def test_what_the_whole_process_prints_on_a_broken_video_is_one_line(tmp_path, good_video):
    """Native code (OpenCV trying its backends, its AVI parser) printed to the process's
    stderr beside the error; and a warning must not be wrapped at 80 columns in a pipe."""
    import subprocess
    import sys

    def stderr_of(video):
        r = subprocess.run([sys.executable, "-m", "mecanum_hil", "measure-video", str(video),
                            "--out", str(tmp_path / "o.csv")], capture_output=True, text=True,
                           timeout=120)
        return r.returncode, r.stderr

    data = good_video.path.read_bytes()
    for name, content in (("zero.mp4", b""), ("head.avi", data[:500])):
        (tmp_path / name).write_bytes(content)
        code, err = stderr_of(tmp_path / name)
        assert code == 1 and err.count("\n") == 1 and err.startswith("error: "), err
    (tmp_path / "cut.avi").write_bytes(data[: int(len(data) * 0.6)])
    code, err = stderr_of(tmp_path / "cut.avi")
    assert code == 0 and err.count("\n") == 1 and err.startswith("warning: "), err
    assert "truncated?" in err


def test_truncated_avi_measures_what_is_there_and_warns(tmp_path, good_video):
    data = good_video.path.read_bytes()
    cut = tmp_path / "cut.avi"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    meas = measure_video(cut)
    assert 0.4 * good_video.frame_t_s.size < len(meas.recording) < good_video.frame_t_s.size
    assert any("truncated" in w for w in meas.warnings)
    got = meas.recording.wheel_rpm[:, 0]
    assert np.nanmean(got) == pytest.approx(60.0, abs=0.3)


def test_an_mp4_cut_at_its_start_warns_that_its_frame_rate_is_a_guess(tmp_path):
    # FFmpeg reads what is left as a bare MPEG-4 stream at a guessed 25 fps: the 30 fps
    # wheel measured 17 % slow, without a word
    res = render_video(steady(60.0, 2.0), tmp_path / "v.mp4", RenderSettings(fps=30.0))
    data = res.path.read_bytes()
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(data[2000:])
    meas = measure_video(cut)
    said = [w for w in meas.warnings if "does not start like an MP4" in w]
    assert said and "give --fps" in said[0]
    assert not any("does not start" in w for w in measure_video(res.path).warnings)
    # with the rate given, nothing is guessed
    fixed = measure_video(cut, MeasureOptions(fps=30.0))
    assert not any("does not start" in w for w in fixed.warnings)
    assert np.nanmedian(fixed.recording.wheel_rpm[:, 0]) == pytest.approx(60.0, rel=0.02)


def test_the_container_check_takes_every_first_box_ffmpeg_takes(tmp_path):
    from mecanum_hil.vision.video import container_mismatch

    for box in (b"ftyp", b"pnot", b"wide", b"moov", b"styp", b"moof", b"uuid"):
        (tmp_path / "a.mov").write_bytes(b"\x00\x00\x00\x14" + box + b"\x00" * 24)
        assert container_mismatch(tmp_path / "a.mov") is None, box
    (tmp_path / "a.mp4").write_bytes(b"\x00\x00\x01\xb0\x01\x00\x00\x01\xb5" + b"\x00" * 8)
    assert container_mismatch(tmp_path / "a.mp4") == "an MP4/QuickTime file"
    (tmp_path / "a.avi").write_bytes(b"RIFF\x00\x00\x00\x00AVI LIST")
    (tmp_path / "a.webm").write_bytes(b"\x1a\x45\xdf\xa3\x00\x00\x00\x00")
    assert container_mismatch(tmp_path / "a.avi") is None
    assert container_mismatch(tmp_path / "a.webm") is None


def test_an_interrupted_render_leaves_the_previous_video_and_no_part_file(tmp_path):
    # Ctrl-C part-way replaced a whole video with a shorter one that played as if whole
    path = tmp_path / "v.mp4"
    whole = render_video(steady(60.0, 2.0), path)
    before = path.read_bytes()

    def interrupt(done, total):
        if done >= 10:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        render_video(steady(30.0, 4.0), path, progress=interrupt)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.mp4"]
    assert whole.frame_t_s.size > 10


def test_no_marker(tmp_path, capsys):
    path = tmp_path / "grey.avi"
    with VideoWriter(path, 30.0, (160, 120)) as w:
        for i in range(30):
            w.write(np.full((120, 160, 3), 100 + i, np.uint8))
    code, _, err = run_cli(["measure-video", str(path), "--out", str(tmp_path / "o.csv")], capsys)
    assert code == 1 and "no marker" in one_error_line(err)


def test_marker_that_does_not_move(tmp_path):
    res = render_video(steady(0.0, 1.0), tmp_path / "still.avi")
    with pytest.raises(VideoError, match=r"no saturated blob moves|does not move"):
        measure_video(res.path)


def test_marker_in_too_few_frames(tmp_path, capsys):
    res = render_video(steady(60.0, 2.0), tmp_path / "hidden.avi",
                       RenderSettings(occlusions_s=((0.6, 2.5),)))
    code, _, err = run_cli(["measure-video", str(res.path), "--out", str(tmp_path / "o.csv")],
                           capsys)
    line = one_error_line(err)
    assert code == 1 and "marker found in only 3" in line and "--min-found" in line
    # A lower bar accepts it; the hidden frames stay empty.
    meas = measure_video(res.path, MeasureOptions(min_found=0.25))
    assert np.isnan(meas.recording.wheel_rpm[res.frame_t_s >= 0.6, 0]).all()


def test_aruco_marker_absent(tmp_path, good_video, capsys):
    code, _, err = run_cli(["measure-video", str(good_video.path), "--out",
                            str(tmp_path / "o.csv"), "--marker", "aruco"], capsys)
    assert code == 1 and "no ArUco marker" in one_error_line(err)


def test_aliasing_is_reported_not_folded(tmp_path):
    t = np.arange(0.0, 2.0 + 1e-9, 0.01)
    rec = steady(0.0, 2.0).with_values(wheel_rpm=np.repeat((600.0 * t)[:, None], 4, 1))
    res = render_video(rec, tmp_path / "fast.avi")  # 1200 rpm at 30 fps: > 0.5 turn/frame
    with pytest.raises(VideoError, match="aliasing at t="):
        measure_video(res.path)


def test_missing_frame_rate():
    with pytest.raises(VideoError, match="no frame rate"):
        frame_times(np.full(10, np.nan), math.nan, source="v.mp4")
    timing = frame_times(np.full(10, np.nan), math.nan, fps_override=25.0)
    assert timing.t_s[-1] == pytest.approx(9 / 25.0)


def test_variable_frame_rate_is_flagged_and_its_timestamps_used():
    stamps = np.cumsum(np.r_[0.0, np.tile([1 / 30, 1 / 20], 10)])
    timing = frame_times(stamps, 30.0)
    assert timing.variable and timing.source == "timestamps"
    np.testing.assert_allclose(timing.t_s, stamps - stamps[0])
    assert not frame_times(np.arange(10) / 30.0, 30.0).variable


def test_bad_options(tmp_path, good_video, capsys):
    for extra in (["--roi", "1:10,10"], ["--marker-hsv", "1,2,3"], ["--marker", "qr"],
                  ["--roi", "1:400,400,50,50"]):
        code, _, err = run_cli(["measure-video", str(good_video.path), "--out",
                                str(tmp_path / "o.csv"), *extra], capsys)
        assert code != 0
        one_error_line(err)


def test_cli_measure_json_and_merge(tmp_path, good_video, capsys):
    rec_path = tmp_path / "rec.csv"
    rec = steady(60.0, 2.0)
    write_recording(rec, rec_path)
    out = tmp_path / "m.csv"
    code, stdout, _ = run_cli(["measure-video", str(good_video.path), "--out", str(out),
                               "--recording", str(rec_path), "--json"], capsys)
    assert code == 0
    summary = json.loads(stdout)
    for key in ("video", "frames", "fps", "duration_s", "timing", "variable_frame_rate",
                "marker", "method", "wheels", "offset_s", "alignment", "warnings", "out",
                "merged"):
        assert key in summary
    assert summary["frames"] == good_video.frame_t_s.size
    assert summary["wheels"][0]["found_fraction"] == 1.0
    measured = read_recording(out)
    assert measured.metadata["source_video"] == str(good_video.path)
    assert np.isnan(measured.wheel_rpm[:, 1:]).all() and np.isnan(measured.commands).all()
    merged = read_recording(summary["merged"])
    assert np.nanmean(merged.extra_numeric("wheel1_video_rpm")) == pytest.approx(60.0, abs=0.3)


def test_cli_render_then_measure_several_wheels(tmp_path, paper, capsys):
    rec_path = tmp_path / "turn.csv"
    write_recording(paper("paper-turn"), rec_path)
    video = tmp_path / "turn.mp4"
    code, stdout, _ = run_cli(["render-video", "--recording", str(rec_path), "--out", str(video),
                               "--wheels", "1,2", "--size", "400x200", "--duration", "3",
                               "--truth", str(tmp_path / "truth.csv"), "--json"], capsys)
    assert code == 0
    rois = json.loads(stdout)["rois"]
    args = ["measure-video", str(video), "--out", str(tmp_path / "m.csv")]
    for wheel, (x, y, w, h) in rois.items():
        args += ["--roi", f"{wheel}:{x},{y},{w},{h}"]
    code, stdout, _ = run_cli(args, capsys)
    assert code == 0 and "wheel 2: marker found in 100.0%" in stdout
    got = read_recording(tmp_path / "m.csv").wheel_rpm
    truth = read_recording(tmp_path / "truth.csv").wheel_rpm
    for k in (0, 1):
        assert np.sqrt(np.nanmean((got[:, k] - truth[:, k]) ** 2)) < 1.5
    assert np.isnan(got[:, 2:]).all()


def test_zero_frame_video_is_one_line(tmp_path, capsys):
    path = tmp_path / "empty.avi"
    with VideoWriter(path, 30.0, (160, 120)):
        pass
    code, _, err = run_cli(["measure-video", str(path), "--out", str(tmp_path / "o.csv")],
                           capsys)
    assert code == 1 and "0 frame(s)" in one_error_line(err)
    assert not (tmp_path / "o.csv").exists()


def test_outputs_never_overwrite_the_video_or_the_recording(tmp_path, good_video, capsys):
    video = tmp_path / "v.avi"
    video.write_bytes(good_video.path.read_bytes())
    rec_path = tmp_path / "rec.csv"
    write_recording(steady(60.0, 2.0), rec_path)
    before = {p: p.read_bytes() for p in (video, rec_path)}
    out = str(tmp_path / "m.csv")
    for extra in (["--out", str(video)],
                  ["--out", str(rec_path), "--recording", str(rec_path)],
                  ["--out", out, "--recording", str(rec_path), "--merged", str(video)],
                  ["--out", out, "--recording", str(rec_path), "--merged", str(rec_path)],
                  ["--out", out, "--recording", str(rec_path), "--merged", out]):
        code, _, err = run_cli(["measure-video", str(video), *extra], capsys)
        line = one_error_line(err)
        assert code == 1 and ("would overwrite" in line or "same file" in line), extra
    assert all(p.read_bytes() == data for p, data in before.items())
    assert not (tmp_path / "m.csv").exists()


def open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="needs /proc")
def test_a_region_outside_the_frame_leaves_no_file_open(good_video):
    before = open_fds()
    for _ in range(3):
        with pytest.raises(VideoError, match="outside"):
            measure_video(good_video.path, MeasureOptions(rois=((1, (900, 900, 40, 40)),)))
    assert open_fds() == before


def test_decoder_thread_ends_when_the_consumer_gives_up(tmp_path):
    path = tmp_path / "one.avi"
    with VideoWriter(path, 30.0, (160, 120)) as w:
        w.write(np.full((120, 160, 3), 90, np.uint8))
    cap, _ = open_video(path)
    q: queue.Queue = queue.Queue(maxsize=1)
    stop = threading.Event()
    worker = threading.Thread(target=decode_ahead, args=(cap, q, stop), daemon=True)
    worker.start()
    # The one frame fills the queue; the end-of-video mark waits for room the consumer,
    # which has given up, never makes.
    deadline = time.monotonic() + 10.0
    while not q.full() and time.monotonic() < deadline:
        time.sleep(0.01)
    stop.set()
    worker.join(timeout=2.0)
    cap.release()
    assert not worker.is_alive()


@pytest.fixture(scope="module")
def reverse_video(tmp_path_factory):
    from mecanum_hil.vision.scenarios import scenario_recording

    path = tmp_path_factory.mktemp("rev") / "reverse.avi"
    return render_video(scenario_recording("reverse"), path, RenderSettings(noise_std=2.0))


def test_a_marker_really_lost_fails_in_one_line_at_the_lower_default(tmp_path, reverse_video,
                                                                     capsys):
    """The default --min-found of 30 % must not turn a lost marker into numbers."""
    out = tmp_path / "o.csv"
    base = ["measure-video", str(reverse_video.path), "--out", str(out)]
    # The wrong colour pinned (the dot is green): nothing of that colour moves.
    code, _, err = run_cli([*base, "--marker-hsv", "170,100,80:10,255,255"], capsys)
    line = one_error_line(err)
    assert code == 1 and "no marker" in line and "check --marker-hsv" in line, line
    # A search region over the wheel's left edge only: the dot passes through it on a fifth
    # of each turn, the rest of the time it is out of the region.
    p = reverse_video.placements[0]
    x, y = int(p.cx_px - 1.2 * p.radius_px), int(p.cy_px - 1.2 * p.radius_px)
    roi = f"{x},{y},{int(0.8 * p.radius_px)},{int(2.4 * p.radius_px)}"
    code, _, err = run_cli([*base, "--roi", roi], capsys)
    line = one_error_line(err)
    assert code == 1 and "marker found in only" in line and "need 30%" in line
    assert not out.exists()


@pytest.mark.parametrize(("option", "value", "fragment"), [
    ("--fps", "inf", "--fps must be within 0.1 .. 100000 frames per second"),
    ("--fps", "1e9", "--fps must be within 0.1 .. 100000 frames per second"),
    # below a time-lapse camera's rate: frame times of days (1e-300: t_s ~ 1e300), exit 0
    ("--fps", "1e-5", "--fps must be within 0.1 .. 100000 frames per second"),
    ("--fps", "1e-300", "--fps must be within 0.1 .. 100000 frames per second"),
    ("--window", "1e6", "--window must be > 0 s and at most 60 s"),
])
def test_options_that_size_the_work_are_bounded_before_decoding(tmp_path, capsys, good_video,
                                                                 option, value, fragment):
    # they overflowed or ran for minutes; checked before a frame is decoded
    code, _, err = run_cli(["measure-video", str(good_video.path), "--out",
                            str(tmp_path / "o.csv"), option, value], capsys)
    assert code == 1 and fragment in one_error_line(err)
    assert not (tmp_path / "o.csv").exists()


def test_render_video_refuses_a_camera_that_starts_after_the_recording(tmp_path, capsys, paper):
    rec_path = write_recording(paper("paper-step-60"), tmp_path / "r.csv")
    for extra, fragment in ((["--start", "100", "--duration", "1"], "before the camera starts"),
                            (["--duration", "-1"], "--duration must be > 0 s")):
        code, _, err = run_cli(["render-video", "--recording", str(rec_path), "--out",
                                str(tmp_path / "v.mp4"), *extra], capsys)
        assert code == 1 and fragment in one_error_line(err)
        assert not (tmp_path / "v.mp4").exists()
