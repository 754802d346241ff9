"""The demo: the paper's experiments through the whole loop, on the simulated robot."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from .io.recording import empty_like_times, write_recording
from .model import load_calibration, load_robot_profile
from .plots import plot_recordings
from .prediction import predict
from .profiles import PAPER_EXPERIMENTS


def run_demo(out_dir: str | Path, echo: Callable[[str], None] = print) -> dict[str, Path]:
    """Run the demo into ``out_dir``; return the files written by name."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    echo(f"mecanum-hil demo: writing into {out.resolve()}")
    robot = load_robot_profile()
    cal = load_calibration()
    written: dict[str, Path] = {}
    echo(f"1. model: {robot.name}, A={cal.A:g} B={cal.B:g} C={cal.C:g} ({cal.source})")
    for name, prof in PAPER_EXPERIMENTS.items():
        t, cmd = prof.sample(100.0)
        robot.check_commands(cmd, name)
        rec = predict(empty_like_times(t).with_values(commands=cmd), cal, robot, source=name)
        path = write_recording(rec, out / "model" / f"{name}.csv")
        png = plot_recordings({"model": rec}, out / "model" / f"{name}.png", title=name)
        written[f"model/{name}"] = path
        echo(f"   {name:16s} {prof.duration_s:5.1f} s -> {path} , {png.name}")
    return written
