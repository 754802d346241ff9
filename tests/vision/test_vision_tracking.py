"""The per-frame shortcuts of measure-video measure what the long way does:
the hub from its edges, the marker followed in a window, frames handed over in runs."""

from __future__ import annotations

import dataclasses
import queue
import threading

import numpy as np
import pytest
from vision_cases import steady

import mecanum_hil.vision.detect as detect
import mecanum_hil.vision.measure as measure
from mecanum_hil.vision import RenderSettings, render_video
from mecanum_hil.vision.detect import BlobDetector, MarkerSpec
from mecanum_hil.vision.geometry import Ellipse
from mecanum_hil.vision.hub import HubTracker, camera_offsets
from mecanum_hil.vision.scenarios import scenario_recording
from mecanum_hil.vision.video import decode_ahead, frame_times, iter_frames, open_video


def frames_of(path) -> list[np.ndarray]:
    cap, _ = open_video(path)
    frames = [f for _, _, f in iter_frames(cap)]
    cap.release()
    return frames


@pytest.fixture(scope="module")
def shaking(tmp_path_factory):
    """A wheel filmed by a camera that shakes by 1.5 px and drifts by 15 px, flickering light."""
    path = tmp_path_factory.mktemp("track") / "shake.avi"
    res = render_video(scenario_recording("reverse"), path, RenderSettings(
        640, 480, fps=30.0, duration_s=4.0, noise_std=3.0, exposure=0.5, shake_px=1.5,
        drift_px=15.0, flicker=0.2, fender=0.35))
    return res, frames_of(path)


def offset_error_px(res, hub: np.ndarray) -> np.ndarray:
    """RMS error per axis of the hub's offsets against the renderer's camera offset [px]."""
    off, _ = camera_offsets(hub)
    err = off - (res.camera_offset_px - res.camera_offset_px[0])
    err -= err.mean(axis=0)
    return np.sqrt(np.mean(err ** 2, axis=0))


def test_hub_from_its_edges_follows_the_camera_to_a_tenth_of_a_pixel(shaking):
    res, frames = shaking
    one = HubTracker(None, (640, 480))
    hub_one = np.array([one(f) for f in frames])
    runs = HubTracker(None, (640, 480))
    hub_runs = np.array([h for k in range(0, len(frames), 10)
                         for h in runs.many(frames[k:k + 10])])
    centroid = HubTracker(None, (640, 480))
    hub_centroid = np.array([centroid.centroid(f) for f in frames])
    assert one.edge_frames >= len(frames) - 2 and runs.edge_frames >= len(frames) - 2
    assert (offset_error_px(res, hub_one) < 0.1).all()
    assert (offset_error_px(res, hub_runs) < 0.1).all()
    # The whole region's centroid, which the edges replaced, is several times further off.
    assert (offset_error_px(res, hub_centroid) > 2 * offset_error_px(res, hub_one)).all()


def test_hub_falls_back_to_the_centroid_when_the_view_jumps(shaking):
    res, frames = shaking
    hub = HubTracker(None, (640, 480))
    x0, y0, _ = hub(frames[0])
    jumped = np.roll(frames[1], 40, axis=1)  # 40 px: beyond the edge profiles' reach
    x, _, _ = hub(jumped)
    assert hub.centroid_frames == 2
    assert x == pytest.approx(hub.centroid(jumped)[0])
    # From there on its edges again, from the centroid's guess.
    x2, y2, _ = hub(np.roll(frames[2], 40, axis=1))
    assert hub.edge_frames == 1
    truth = res.camera_offset_px[2] - res.camera_offset_px[0]
    assert x2 - x0 == pytest.approx(40.0 + truth[0], abs=0.5)
    assert y2 - y0 == pytest.approx(truth[1], abs=0.5)


def test_following_the_marker_finds_what_the_whole_search_finds(tmp_path, monkeypatch):
    res = render_video(steady(90.0, 3.0), tmp_path / "d.avi", RenderSettings(
        640, 480, fps=30.0, noise_std=3.0, exposure=0.5, distractors=3))
    frames = frames_of(res.path)
    p = res.placements[0]
    path = Ellipse(p.cx_px, p.cy_px, 0.7 * p.radius_px, 0.7 * p.radius_px, 0.0)

    def candidates(follow: bool) -> list[np.ndarray]:
        monkeypatch.setattr(detect, "FOLLOW_FULL_EVERY", 8 if follow else 0)
        det = BlobDetector(MarkerSpec(), None, (640, 480))
        out = [det(f) for f in frames[:40]]
        det.focus(path)
        return out + [det(f) for f in frames[40:]]

    whole, followed = candidates(False), candidates(True)
    assert all(len(c) >= 1 for c in whole)
    assert all(np.array_equal(a, b) for a, b in zip(whole, followed, strict=True))


def _count_scan_runs(monkeypatch) -> list[int]:
    """Patch ``measure._scan_run`` to note each run's length [frames]; return that list."""
    runs: list[int] = []
    scan_run = measure._scan_run

    def counted(run, *args):
        runs.append(len(run))
        return scan_run(run, *args)

    monkeypatch.setattr(measure, "_scan_run", counted)
    return runs


def test_frames_one_at_a_time_in_runs_or_decoded_beside_measure_the_same(tmp_path,
                                                                          monkeypatch):
    res = render_video(steady(90.0, 3.2), tmp_path / "still.avi", RenderSettings(
        640, 480, fps=30.0, noise_std=3.0, exposure=0.5, distractors=2))
    runs = _count_scan_runs(monkeypatch)
    done: list[int] = []
    for hub in (True, False):
        runs.clear()
        done.clear()
        opts = measure.MeasureOptions(track_hub=hub, decode_beside=False)
        single = measure.measure_video(res.path, opts, lambda k, _: done.append(k))
        assert done[-1] == single.summary["frames"] and done == sorted(set(done))
        # A still camera: runs of SCAN_BATCH while the hub is watched, then one frame at a
        # time; no hub: one at a time from the start.
        first = measure.STILL_CHECK_AFTER if hub else 0
        assert runs == ([measure.SCAN_BATCH] * (first // measure.SCAN_BATCH)
                        + [1] * (single.summary["frames"] - first))
        with monkeypatch.context() as m:
            m.setattr(measure._WheelScan, "single_frames", property(lambda self: False))
            in_runs = measure.measure_video(res.path, opts)
        assert np.array_equal(single.recording.wheel_rpm, in_runs.recording.wheel_rpm,
                              equal_nan=True)
        assert single.summary == in_runs.summary
        # decoded in a helper thread beside the analysis: runs of SCAN_BATCH, same results
        runs.clear()
        done.clear()
        beside = measure.measure_video(res.path, dataclasses.replace(opts, decode_beside=True),
                                       lambda k, _: done.append(k))
        n = single.summary["frames"]
        assert runs == [measure.SCAN_BATCH] * (n // measure.SCAN_BATCH) + (
            [n % measure.SCAN_BATCH] if n % measure.SCAN_BATCH else [])
        assert done[-1] == n and done == sorted(set(done))
        assert np.array_equal(single.recording.wheel_rpm, beside.recording.wheel_rpm,
                              equal_nan=True)
        assert single.summary == beside.summary


def test_frames_are_handed_over_in_runs_and_their_buffers_reused(shaking, tmp_path):
    res, frames = shaking
    cap, _ = open_video(res.path, decoder_threads=1)
    out: queue.Queue = queue.Queue()
    free: queue.Queue = queue.Queue()
    for _ in range(3):
        free.put(np.zeros_like(frames[0]))
    pool = {id(b) for b in list(free.queue)}
    worker = threading.Thread(target=decode_ahead, args=(cap, out, threading.Event(), 7, free))
    worker.start()
    worker.join(timeout=60)
    cap.release()
    runs = []
    while (item := out.get_nowait()) is not None:
        runs.append(item)
    assert [len(r) for r in runs] == [7] * (len(frames) // 7) + [len(frames) % 7]
    got = [f for r in runs for _, _, f in r]
    assert all(np.array_equal(a, b) for a, b in zip(got[3:], frames[3:], strict=True))
    assert {id(f) for f in got[:3]} == pool  # decoded into the buffers given back


def test_millisecond_timestamps_of_a_constant_rate_give_its_exact_times():
    exact = np.arange(50) / 30.0
    timing = frame_times(np.round(exact, 3), 30.0)  # a WebM's clock: 33, 33, 34 ms ...
    np.testing.assert_array_equal(timing.t_s, exact)
    assert not timing.variable and timing.source == "timestamps"
    # Exact timestamps stay as they are; a real variable rate is still flagged.
    np.testing.assert_array_equal(frame_times(exact + 0.5, 30.0).t_s, (exact + 0.5) - 0.5)
    stamps = np.cumsum(np.r_[0.0, np.tile([1 / 30, 1 / 20], 10)])
    assert frame_times(stamps, 30.0).variable


@pytest.mark.parametrize(("idle", "max_bytes", "beside"), [
    (1.0, measure.BESIDE_MAX_BYTES, True),   # a second core free
    (0.8, measure.BESIDE_MAX_BYTES, True),   # an idle desktop's load average of 0.2
    (0.2, measure.BESIDE_MAX_BYTES, False),  # another job busy on it (load average)
    (1.0, 4 * 2 ** 20, False),               # four runs of frames would not fit
])
def test_decoding_beside_by_default_only_with_a_core_and_the_memory_free(
        tmp_path, monkeypatch, idle, max_bytes, beside):
    res = render_video(steady(60.0, 1.0), tmp_path / "v.avi", RenderSettings(
        320, 240, fps=30.0, noise_std=2.0))
    runs = _count_scan_runs(monkeypatch)
    monkeypatch.setattr(measure, "_idle_cores", lambda: idle)
    monkeypatch.setattr(measure, "BESIDE_MAX_BYTES", max_bytes)
    measure.measure_video(res.path, measure.MeasureOptions(track_hub=False))
    # in turns without a hub: one frame at a time; beside: runs of SCAN_BATCH
    assert (max(runs) == measure.SCAN_BATCH) is beside
