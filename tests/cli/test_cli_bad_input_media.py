"""render-video, train and calibrate-camera on bad input: one ``error: ...`` line, exit 1, at
once (before a writer is opened, a network allocated or a board built), nothing written.

The output is captured at the file descriptors (``capfd``): what FFmpeg or OpenCV print from C
would show there too.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from mecanum_hil.cli import main


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """``simulate --profile paper-step-60``: 5.000 s with wheel and pose columns."""
    path = tmp_path_factory.mktemp("sim") / "sim.csv"
    assert main(["simulate", "--profile", "paper-step-60", "--out", str(path)]) == 0
    return path


@pytest.fixture
def rec(simulated, tmp_path):
    """The simulated recording beside its sidecar, copied into ``tmp_path`` as run.csv."""
    for ext in (".csv", ".json"):
        shutil.copy(simulated.with_suffix(ext), tmp_path / f"run{ext}")
    return tmp_path / "run.csv"


def one_line(argv, capfd) -> str:
    """Run the CLI: exit 1 and exactly one ``error:`` line on stderr; the line."""
    code = main([str(a) for a in argv])
    err = capfd.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 1, err
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert "internal error" not in err and "Traceback" not in err
    return lines[0]


def files(folder) -> set[str]:
    return {p.name for p in folder.iterdir()}


# --- render-video -----------------------------------------------------------------------------

@pytest.mark.parametrize("overhead", [False, True])
@pytest.mark.parametrize("rows", [0, 1])
def test_a_recording_without_two_samples_is_one_line(tmp_path, rec, capfd, overhead, rows):
    short = tmp_path / "short.csv"
    short.write_text("\n".join(rec.read_text().splitlines()[:1 + rows]) + "\n")
    before = files(tmp_path)
    line = one_line(["render-video", "--recording", short, "--out", tmp_path / "v.mp4",
                     *(["--overhead"] if overhead else [])], capfd)
    assert "nothing to render" in line and f"has {rows} sample" in line
    assert files(tmp_path) == before


@pytest.mark.parametrize("overhead", [False, True])
@pytest.mark.parametrize(("extra", "fragment"), [
    (["--duration", "1e9"], "runs past the recording's end: it has 5.000 s"),
    (["--start", "1", "--duration", "4.5"], "it has 4.000 s after --start 1 s"),
    (["--duration", "inf"], "--duration must be > 0 s and finite"),
    (["--start", "-1e9"], "--start must be a finite number of seconds >= 0"),
    (["--start", "nan"], "--start must be a finite number of seconds >= 0"),
    (["--noise", "nan"], "--noise) must be within 0..255"),
    (["--noise", "-1"], "--noise) must be within 0..255"),
    (["--fps", "1e6"], "--fps must be within 0.1 .. 1000 frames per second"),
    (["--fps", "nan"], "--fps must be within 0.1 .. 1000 frames per second"),
    (["--fps", "0"], "--fps must be within 0.1 .. 1000 frames per second"),
    (["--size", "100000x100000"], "(--size) must be at most 4096 px a side"),
    (["--size", "4096x4096"], "(--size) must be at most 4096 px a side"),
    (["--size", "10x10"], "(--size) must be at least"),
    (["--seed", "-1"], "--seed must be within 0..2147483647"),
    (["--seed", "99999999999"], "--seed must be within 0..2147483647"),
    (["--tilt", "nan"], "tilt must be within"),
])
def test_numbers_out_of_bounds_are_refused_before_anything_is_written(
        tmp_path, rec, capfd, overhead, extra, fragment):
    # --duration 1e9 allocated 224 GiB; --noise nan wrote a black video and exit 0; --fps 1e6
    # and --size 100000x100000 printed FFmpeg's lines before the error
    before = files(tmp_path)
    line = one_line(["render-video", "--recording", rec, "--out", tmp_path / "v.mp4", *extra,
                     *(["--overhead"] if overhead else [])], capfd)
    assert fragment in line
    assert files(tmp_path) == before


@pytest.mark.parametrize(("extra", "fragment"), [
    (["--lighting-drift", "nan"], "(--lighting-drift) must be within 0..1"),
    (["--lighting-drift", "-0.2"], "(--lighting-drift) must be within 0..1"),
    (["--blur", "nan"], "(--blur) must be within 0..1"),
    (["--tilt-axis", "inf"], "(--tilt-axis) must be a finite angle"),
    (["--fender", "nan"], "fender must be within 0..1"),
    (["--shake", "1e300"], "(--shake) must be at most the frame's smaller side (240 px)"),
    (["--drift", "nan"], "drift_px must be >= 0"),
    (["--flicker", "nan"], "flicker must be >= 0"),
    (["--flicker", "0.2", "--flicker-hz", "inf"], "(--flicker-hz) a finite number > 0 Hz"),
    (["--hue-shift", "1e300"], "(--hue-shift) must be within 0..180 deg"),
    (["--hue-shift", "-5"], "hue_shift_deg must be >= 0"),
    (["--distractors", "1000000000"], "(--distractors) must be within 0..100"),
])
def test_the_wheel_renderers_other_numbers_are_bounded(tmp_path, rec, capfd, extra, fragment):
    before = files(tmp_path)
    line = one_line(["render-video", "--recording", rec, "--out", tmp_path / "v.mp4", *extra],
                    capfd)
    assert fragment in line
    assert files(tmp_path) == before


@pytest.mark.parametrize("distortion", ["nan,0,0,0,0", "0,inf,0,0,0", "0,0,0,0,-inf"])
def test_a_non_finite_lens_is_refused_by_name(tmp_path, rec, capfd, distortion):
    # was "the robot's path does not fit in the picture at any distance"
    line = one_line(["render-video", "--overhead", "--recording", rec, "--out",
                     tmp_path / "v.mp4", "--distortion", distortion], capfd)
    assert "(--distortion) must be five finite numbers" in line
    assert not (tmp_path / "v.mp4").exists()


@pytest.mark.parametrize("overhead", [False, True])
def test_a_truth_that_cannot_be_written_is_refused_before_rendering(tmp_path, rec, capfd,
                                                                   overhead):
    (tmp_path / "afile").write_text("not a folder\n")
    line = one_line(["render-video", "--recording", rec, "--out", tmp_path / "v.mp4",
                     "--truth", tmp_path / "afile" / "truth.csv",
                     *(["--overhead"] if overhead else [])], capfd)
    assert "--truth" in line and "afile" in line and "truth.csv" in line
    assert not (tmp_path / "v.mp4").exists()


def test_the_overhead_truth_never_overwrites_the_recording(tmp_path, rec, capfd):
    # --out v.mp4 writes v.truth.csv (and v.truth.json) by default: here the recording's name
    named = tmp_path / "v.truth.csv"
    rec.rename(named)
    rec.with_suffix(".json").rename(named.with_suffix(".json"))
    before = {p: p.read_bytes() for p in (named, named.with_suffix(".json"))}
    for extra in ([], ["--truth", named.with_suffix(".json")]):
        line = one_line(["render-video", "--overhead", "--recording", named, "--out",
                         tmp_path / "v.mp4", *extra], capfd)
        assert "would overwrite the recording given with --recording" in line
    assert {p: p.read_bytes() for p in before} == before
    assert files(tmp_path) == {"v.truth.csv", "v.truth.json"}


def test_a_duration_to_the_recordings_end_still_renders(tmp_path, rec, capfd):
    # the bound is the recording: its whole length (a hair of rounding included) is fine
    out = tmp_path / "v.avi"
    assert main(["render-video", "--recording", str(rec), "--out", str(out), "--size", "64x48",
                 "--fps", "2", "--duration", "5", "--truth", str(tmp_path / "t.csv")]) == 0
    assert "wrote" in capfd.readouterr().out and out.stat().st_size > 0
    assert not [n for n in files(tmp_path) if n.startswith(".mecanum-hil-probe")]


# --- train ------------------------------------------------------------------------------------

@pytest.fixture
def no_training(monkeypatch):
    """Training fails the test: every refusal here comes before it."""
    import mecanum_hil.policy.train as train_module

    def refuse(*args, **kwargs):
        raise AssertionError("training started")

    monkeypatch.setattr(train_module, "train", refuse)


@pytest.mark.parametrize(("extra", "fragment"), [
    (["--hidden", "100000"], "--hidden must be within 0..128 units"),  # was 16 TiB
    (["--hidden", "129"], "--hidden must be within 0..128 units"),
    (["--episodes", "1000000000"], "--episodes must be within 1..4096"),
    (["--seed", "99999999999999999"], "--seed must be within 0..4294967294"),
])
def test_train_refuses_a_network_or_run_too_big_at_once(tmp_path, capfd, no_training, extra,
                                                        fragment):
    line = one_line(["train", "--out", tmp_path / "t.npz", "--no-progress", *extra], capfd)
    assert fragment in line
    assert files(tmp_path) == set()


def test_train_checks_its_output_before_training(tmp_path, capfd, no_training):
    # /proc/t.npz failed only after the whole training budget
    (tmp_path / "afile").write_text("not a folder\n")
    line = one_line(["train", "--out", tmp_path / "afile" / "t.npz", "--no-progress",
                     "--budget-s", "15"], capfd)
    assert "afile" in line and "t.npz" in line
    line = one_line(["train", "--out", tmp_path, "--no-progress"], capfd)
    assert "--out" in line and "folder" in line
    assert files(tmp_path) == {"afile"}


def test_the_output_probe_leaves_no_file(tmp_path, capfd, no_training):
    # the folder is writable (probed), then the task is refused: no stray file is left
    line = one_line(["train", "--out", tmp_path / "new" / "t.npz", "--task", "parry",
                     "--no-progress"], capfd)
    assert "unknown task" in line
    assert files(tmp_path) == set()


def test_the_library_refuses_a_network_too_big_to_search():
    from mecanum_hil.errors import ConfigError
    from mecanum_hil.policy.train import MAX_PARAMS, check_training

    check_training(MAX_PARAMS, 48, 0)
    with pytest.raises(ConfigError, match="CMA-ES trains at most"):
        check_training(MAX_PARAMS + 1, 48, 0)


# --- calibrate-camera -------------------------------------------------------------------------

@pytest.fixture
def views(tmp_path):
    import cv2

    folder = tmp_path / "board"
    folder.mkdir()
    cv2.imwrite(str(folder / "a.png"), np.full((120, 160), 128, np.uint8))
    return folder


@pytest.mark.parametrize(("board", "fragment"), [
    ("charuco:100000x100000:0.04:0.03", "at most 100 squares across and down"),  # was 22 GB
    ("charuco:1000x1000:0.04:0.03", "at most 100 squares across and down"),  # was > 60 s
    ("charuco:15x14:0.04:0.03", "has 105 markers, more than the 100 of the dictionary "
                                "DICT_5X5_100"),
    ("charuco:45x45:0.04:0.03:DICT_4X4_1000", "has 1012 markers, more than the 1000"),
])
def test_a_board_beyond_its_dictionary_is_refused_at_once(tmp_path, views, capfd, board,
                                                          fragment):
    line = one_line(["calibrate-camera", views, "--board", board, "--out", tmp_path / "c.toml"],
                    capfd)
    assert fragment in line
    assert not (tmp_path / "c.toml").exists()


def test_a_board_the_dictionary_can_fill_is_accepted():
    from mecanum_hil.vision.calibrate import parse_board

    assert parse_board("charuco:14x14:0.04:0.03").markers == 98
    assert parse_board("charuco:44x44:0.04:0.03:DICT_4X4_1000").markers == 968


def test_calibrate_camera_bounds_max_views(tmp_path, views, capfd):
    line = one_line(["calibrate-camera", views, "--board", "charuco:7x5:0.04:0.03", "--out",
                     tmp_path / "c.toml", "--max-views", "100000"], capfd)
    assert "--max-views must be within 5..500" in line


def test_a_webm_render_prints_nothing_on_stderr(rec, capfd):
    # FFmpeg said "tag 'VP80' is not supported ... format 'webm'" on every WebM, then wrote it
    out = rec.with_name("v.webm")
    assert main(["render-video", "--recording", str(rec), "--out", str(out),
                 "--duration", "0.5"]) == 0
    assert capfd.readouterr().err == ""
    assert out.stat().st_size > 1000
