"""Two decoders, each on every other part of a video (for speed): the frames, their
order, their times and the measurement are those of decoding in one piece; where the
decoders disagree, or the video ends early or is longer than its header says, the result
is still the same."""

from __future__ import annotations

import dataclasses
import os
import queue
import threading

import numpy as np
import pytest
from vision_cases import steady

import mecanum_hil.vision.measure as measure
import mecanum_hil.vision.video as video
from mecanum_hil.errors import VideoError
from mecanum_hil.vision import RenderSettings, render_video
from mecanum_hil.vision.scenarios import scenario_recording
from mecanum_hil.vision.video import (
    SegmentMismatchError,
    decoded_in_segments,
    iter_frames,
    keyframe_interval,
    open_video,
)


@pytest.fixture(scope="module", params=[".mp4", ".avi", ".webm"])
def clip(request, tmp_path_factory):
    """A 4-s clip (121 frames) and its frames decoded in one piece."""
    path = tmp_path_factory.mktemp("two") / f"clip{request.param}"
    render_video(steady(75.0, 4.0), path, RenderSettings(160, 120, fps=30.0, noise_std=3.0))
    cap, _ = open_video(path, decoder_threads=1)
    items = [(i, t, f.copy()) for i, t, f in iter_frames(cap)]
    cap.release()
    return path, items


@pytest.fixture
def modes(monkeypatch):
    """How each scan of measure-video ran: ``(decoders asked, "done" or "mismatch")``."""
    seen: list[tuple] = []
    real = measure._scan_video

    def scan(path, detectors_for, progress, decode_beside, decoders):
        try:
            out = real(path, detectors_for, progress, decode_beside, decoders)
        except SegmentMismatchError:
            seen.append((decoders, "mismatch"))
            raise
        seen.append((decoders, "done"))
        return out

    monkeypatch.setattr(measure, "_scan_video", scan)
    return seen


def in_segments(path, segment, batch=10):
    cap, _ = open_video(path, decoder_threads=1)
    runs = decoded_in_segments(path, cap, segment, batch)
    try:
        got = [[(i, t, f.copy()) for i, t, f in run] for run in runs]
    finally:
        runs.close()
        cap.release()
    return got


def assert_same_items(got, items):
    assert [i for i, _, _ in got] == [i for i, _, _ in items]
    assert [t for _, t, _ in got] == [t for _, t, _ in items]
    assert all(np.array_equal(a, b) for (_, _, a), (_, _, b) in zip(got, items, strict=True))


@pytest.mark.parametrize("segment", [20, 30, 60])
def test_two_decoders_give_every_frame_in_order_as_one_does(clip, segment):
    path, items = clip
    runs = in_segments(path, segment)
    assert_same_items([item for run in runs for item in run], items)
    # runs of the batch, never across a part's end: where one decoder would put them
    assert all(len(run) == 10 for run in runs[:-1])


def test_keyframe_interval_is_read_from_the_container(clip):
    path, _ = clip
    gop = keyframe_interval(path)
    assert gop is not None and 1 <= gop <= 121
    if path.suffix == ".avi":  # MJPG: every frame is a keyframe
        assert gop == 1


class Capture:
    """A cv2.VideoCapture with faults: a seek that lands ``seek_off`` frames late while it
    reports the frame asked for, or a decoding error at frame ``fail_at`` (after a seek)."""

    def __init__(self, cap, seek_off=0, fail_at=None):
        self.cap, self.seek_off, self.fail_at, self.pos = cap, seek_off, fail_at, 0

    def set(self, prop, value):
        import cv2

        assert prop == cv2.CAP_PROP_POS_FRAMES
        self.pos = int(value)
        return self.cap.set(prop, value + self.seek_off)

    def get(self, prop):
        import cv2

        if prop == cv2.CAP_PROP_POS_FRAMES:
            return float(self.pos)
        return self.cap.get(prop)

    def read(self, *buf):
        import cv2

        if self.fail_at is not None and self.pos == self.fail_at:
            raise cv2.error("injected decoding error")
        self.pos += 1
        return self.cap.read(*buf)

    def release(self):
        self.cap.release()


def second_decoder(monkeypatch, **faults):
    """Make the second decoder (the one decoded_in_segments opens) a faulty Capture."""
    real = video.open_video

    def opened(path, decoder_threads=None):
        cap, info = real(path, decoder_threads)
        return Capture(cap, **faults), info

    monkeypatch.setattr(video, "open_video", opened)


def test_a_seek_that_lands_elsewhere_is_caught_where_the_parts_meet(clip, monkeypatch):
    path, _ = clip
    second_decoder(monkeypatch, seek_off=1)
    with pytest.raises(SegmentMismatchError, match="disagree at frame 20"):
        in_segments(path, 20)


@pytest.mark.parametrize("fault", ["seek", "open"])
def test_measure_video_falls_back_to_one_decoder_when_the_second_fails(tmp_path, monkeypatch,
                                                                       modes, fault):
    res = render_video(steady(75.0, 4.0), tmp_path / "v.mp4", RenderSettings(
        320, 240, fps=30.0, noise_std=3.0))
    opts = measure.MeasureOptions(decode_beside=True, decoders=1)
    one = measure.measure_video(res.path, opts)
    if fault == "seek":  # lands three frames late
        second_decoder(monkeypatch, seek_off=3)
    else:  # out of file handles, say
        def refused(path, decoder_threads=None):
            raise VideoError(f"{path}: not a video OpenCV can decode")

        monkeypatch.setattr(video, "open_video", refused)
    modes.clear()
    two = measure.measure_video(res.path, dataclasses.replace(opts, decoders=2))
    assert modes == [(2, "mismatch"), (1, "done")]
    assert np.array_equal(one.recording.wheel_rpm, two.recording.wheel_rpm, equal_nan=True)
    assert one.summary == two.summary


def test_a_decoding_error_comes_after_every_frame_before_it(clip, monkeypatch):
    path, items = clip
    # the second decoder takes frames 20-39, 60-79 ...: it fails in its second part, after
    # the first decoder's 40-59 have been handed over
    second_decoder(monkeypatch, fail_at=65)
    got: list = []
    cap, _ = open_video(path, decoder_threads=1)
    runs = decoded_in_segments(path, cap, 20, 10)
    try:
        with pytest.raises(VideoError, match="decoding failed at frame 65:"):
            for run in runs:
                got.extend((i, t, f.copy()) for i, t, f in run)
    finally:
        runs.close()
        cap.release()
    assert_same_items(got, items[:65])


@pytest.mark.parametrize("declared", [-50, -1, +1, +80])
def test_a_header_that_miscounts_the_frames_changes_nothing(clip, monkeypatch, declared):
    """Too few: the last part reads on to the end; too many: a part that ends early ends the
    video, as decoding in one piece would."""
    path, items = clip
    real = video.open_video

    def opened(p, decoder_threads=None):
        cap, info = real(p, decoder_threads)
        return cap, dataclasses.replace(info, frame_count=info.frame_count + declared)

    monkeypatch.setattr(video, "open_video", opened)
    assert_same_items([item for run in in_segments(path, 20) for item in run], items)


@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="needs /proc")
def test_a_consumer_that_gives_up_leaves_no_thread_and_no_file_open(clip):
    path, _ = clip
    before_fds, before_threads = len(os.listdir("/proc/self/fd")), threading.active_count()
    for _ in range(3):
        cap, _ = open_video(path, decoder_threads=1)
        runs = decoded_in_segments(path, cap, 20, 10, free=queue.LifoQueue())
        next(runs)
        next(runs)
        runs.close()
        cap.release()
    assert threading.active_count() == before_threads
    assert len(os.listdir("/proc/self/fd")) == before_fds


def test_a_truncated_video_measures_the_same_with_two_decoders(tmp_path, modes):
    res = render_video(steady(60.0, 6.0), tmp_path / "v.avi", RenderSettings(
        320, 240, fps=30.0, noise_std=2.0))
    data = res.path.read_bytes()
    cut = tmp_path / "cut.avi"
    cut.write_bytes(data[: int(len(data) * 0.7)])
    opts = measure.MeasureOptions(decode_beside=True, decoders=1)
    one = measure.measure_video(cut, opts)
    two = measure.measure_video(cut, dataclasses.replace(opts, decoders=2))
    assert modes == [(1, "done"), (2, "done")]  # no fall back: the parts after the end
    assert any("truncated" in w for w in two.warnings)
    assert np.array_equal(one.recording.wheel_rpm, two.recording.wheel_rpm, equal_nan=True)
    assert one.summary == two.summary


def test_by_default_a_long_video_beside_the_analysis_takes_two_decoders_same_results(
        tmp_path, monkeypatch, modes):
    res = render_video(scenario_recording("slow-start"), tmp_path / "v.mp4", RenderSettings(
        320, 240, fps=30.0, duration_s=8.0, noise_std=3.0, fender=0.35, shake_px=1.5,
        flicker=0.2))
    _, info = open_video(res.path)
    part = measure.split_part_frames(res.path, info)
    assert part > 0 and part % measure.SCAN_BATCH == 0 and info.frame_count > part
    used: list[int] = []
    real = measure.decoded_in_segments

    def counted(path, cap, segment, *args, **kw):
        used.append(segment)
        return real(path, cap, segment, *args, **kw)

    monkeypatch.setattr(measure, "decoded_in_segments", counted)
    two = measure.measure_video(res.path, measure.MeasureOptions(decode_beside=True))
    assert used == [part] and modes == [(None, "done")]
    one = measure.measure_video(res.path, measure.MeasureOptions(decode_beside=True,
                                                                 decoders=1))
    turns = measure.measure_video(res.path, measure.MeasureOptions(decode_beside=False))
    assert used == [part]
    for other in (one, turns):
        assert np.array_equal(two.recording.wheel_rpm, other.recording.wheel_rpm,
                              equal_nan=True)
        assert two.summary == other.summary


def test_two_decoders_are_not_used_where_they_cannot_pay(tmp_path, monkeypatch):
    res = render_video(steady(60.0, 2.0), tmp_path / "short.mp4", RenderSettings(
        320, 240, fps=30.0))
    _, info = open_video(res.path)
    assert measure.split_part_frames(res.path, info) == 0  # 61 frames: too short
    long_gop = dataclasses.replace(info, frame_count=400)
    monkeypatch.setattr(measure, "keyframe_interval", lambda path: 300)
    assert measure.split_part_frames(res.path, long_gop) == 0  # keyframes too far apart
    monkeypatch.setattr(measure, "keyframe_interval", lambda path: 12)
    assert measure.split_ahead_frames(long_gop, 100) == 100  # a whole part ahead
    assert measure.split_part_frames(res.path, long_gop) == 100  # 400 frames: 4 parts
    # decoders=2 asked for: whatever the keyframe interval, parts of about 80 frames
    monkeypatch.setattr(measure, "keyframe_interval", lambda path: 300)
    assert measure.split_part_frames(res.path, long_gop, forced=True) == 100
    ten_minutes = dataclasses.replace(info, frame_count=18000, width_px=640, height_px=480)
    assert measure.split_part_frames(res.path, ten_minutes, forced=True) == 90  # not half
    # what the decoders hold stays within the budget: a whole part ahead at 640x480, 20
    # frames at 1280x720, none at 1920x1080 (one decoder)
    for (w, h), ahead in (((640, 480), 90), ((1280, 720), 20), ((1920, 1080), 0)):
        size = dataclasses.replace(ten_minutes, width_px=w, height_px=h)
        assert measure.split_ahead_frames(size, 90) == ahead
        held = (2 * ahead + 5 * measure.SCAN_BATCH + 2 * video.MEETING_FRAMES) * 3 * w * h
        assert (held <= measure.BESIDE_MAX_BYTES) is (ahead > 0)
    assert measure.split_part_frames(res.path, dataclasses.replace(
        ten_minutes, width_px=1280, height_px=720), forced=True) == 90
    assert measure.split_part_frames(res.path, dataclasses.replace(
        ten_minutes, width_px=1920, height_px=1080), forced=True) == 0
    monkeypatch.setattr(measure, "BESIDE_MAX_BYTES", 2 ** 20)
    assert measure.split_part_frames(res.path, long_gop) == 0  # not one run would fit
    assert measure.split_part_frames(res.path, long_gop, forced=True) == 0
    with pytest.raises(VideoError, match="decoders must be 1 or 2"):
        measure.MeasureOptions(decoders=3)


@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="needs /proc")
def test_an_analysis_stopped_by_ctrl_c_leaves_no_thread_and_no_file_open(tmp_path, monkeypatch):
    res = render_video(steady(75.0, 6.0), tmp_path / "v.mp4", RenderSettings(
        320, 240, fps=30.0, noise_std=3.0))
    before_fds, before_threads = len(os.listdir("/proc/self/fd")), threading.active_count()
    calls = []
    real = measure._WheelScan.candidates

    def interrupted(self, frame, hub):
        calls.append(1)
        if len(calls) == 100:  # in the second part, the other decoder's
            raise KeyboardInterrupt
        return real(self, frame, hub)

    monkeypatch.setattr(measure._WheelScan, "candidates", interrupted)
    with pytest.raises(KeyboardInterrupt):
        measure.measure_video(res.path, measure.MeasureOptions(decode_beside=True, decoders=2))
    assert len(calls) == 100
    assert threading.active_count() == before_threads
    assert len(os.listdir("/proc/self/fd")) == before_fds


@pytest.mark.parametrize("ahead", [10, 20])
def test_the_decoders_never_hold_more_frames_than_their_share_ahead(clip, ahead):
    """Counted as the frame buffers ever allocated, the consumer slower than the decoders (so
    that their queues fill): at most 2 ahead + 5 runs + the frames compared where parts meet."""
    import time

    path, items = clip
    free: queue.Queue = queue.LifoQueue()
    buffers: dict[int, np.ndarray] = {}  # kept alive: no id is reused
    cap, _ = open_video(path, decoder_threads=1)
    runs = decoded_in_segments(path, cap, 40, 10, free=free, ahead=ahead)
    got = []
    try:
        for run in runs:
            time.sleep(0.005)
            for i, t, f in run:
                buffers[id(f)] = f
                got.append((i, t, f.copy()))
            for _, _, f in run:
                free.put(f)
    finally:
        runs.close()
        cap.release()
    assert_same_items(got, items)
    assert len(buffers) <= 2 * ahead + 5 * 10 + 2 * video.MEETING_FRAMES
