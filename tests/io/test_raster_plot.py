"""The Pillow chart behind fit's report (mecanum_hil.plots.raster): ticks, what is drawn where,
gaps, empty panels, and a write that fails as one clear error."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from mecanum_hil.errors import MecanumHILError
from mecanum_hil.plots.raster import COLOURS, Panel, Series, nice_ticks, write_chart

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize(("lo", "hi", "expected", "decimals"), [
    (0.0, 1.88, [0.0, 0.5, 1.0, 1.5], 1),
    (-15.0, 345.0, [0, 50, 100, 150, 200, 250, 300], 0),
    (0.0, 0.01, [0.0, 0.002, 0.004, 0.006, 0.008, 0.01], 3),
    (0.3, 0.9, [0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9], 1),
    (-2.6, 2.6, [-2.0, -1.0, 0.0, 1.0, 2.0], 0),
    (0.0, 15.0, [0.0, 2.5, 5.0, 7.5, 10.0, 12.5, 15.0], 1),
])
def test_nice_ticks_are_round_and_inside(lo, hi, expected, decimals):
    ticks, dec = nice_ticks(lo, hi)
    assert ticks == pytest.approx(expected, abs=1e-12)
    assert dec == decimals
    assert len({f"{v:.{dec}f}" for v in ticks}) == len(ticks)  # labels tell ticks apart


def test_nice_ticks_of_an_empty_span():
    ticks, _ = nice_ticks(3.0, 3.0)
    assert ticks.tolist() == [3.0]
    ticks, _ = nice_ticks(5e-324, 1e-323)  # a span that underflows when divided
    assert ticks.tolist() == [5e-324]


def test_values_near_the_float_limit_are_drawn(tmp_path):
    """A diverged model's huge but finite values are drawn, not a traceback."""
    t = np.linspace(0.0, 1.0, 50)
    for dots in (False, True):
        panel = Panel((Series(t, np.sin(7 * t) * 1.7e308, COLOURS[0], "a", dots=dots),), "x")
        path = write_chart(tmp_path / f"h{dots}.png", [panel], ncols=1, panel_px=(200, 150))
        assert Image.open(path).size == (200, 150)


def _colour_columns(img: np.ndarray, colour, tol: int = 40) -> np.ndarray:
    near = (np.abs(img.astype(int) - np.asarray(colour)).sum(axis=2) < tol)
    return np.flatnonzero(near.any(axis=0))


def test_chart_draws_dots_and_lines_where_the_data_are(tmp_path):
    t = np.linspace(0.0, 2.0, 400)
    y = np.where(t < 1.0, 0.0, 100.0)
    gap = y.copy()
    gap[(t > 1.4) & (t < 1.6)] = np.nan  # no line drawn there
    panels = [Panel((Series(t, y + 5.0, COLOURS[1], "measured", dots=True, alpha=1.0),
                     Series(t, gap, COLOURS[0], "model")), "one", "t [s]", "speed [rpm]")]
    path = write_chart(tmp_path / "sub" / "c.png", panels, ncols=1, title="title",
                       panel_px=(400, 300))
    img = np.asarray(Image.open(path).convert("RGB"))
    assert img.shape == (300 + 26, 400, 3)
    blue, orange = _colour_columns(img, COLOURS[0]), _colour_columns(img, COLOURS[1])
    assert blue.size > 150 and orange.size > 150
    # the model's line stops for the gap (the legend's key sits in a corner, not there)
    left, right = blue.min(), blue.max()
    gap_px = (left + (right - left) * np.array([1.45, 1.55]) / 2.0).astype(int)
    rows = np.abs(img[:, gap_px[0]:gap_px[1]].astype(int) - COLOURS[0]).sum(axis=2) < 40
    assert not rows.any()


def test_grid_of_panels_and_an_empty_one(tmp_path):
    t = np.arange(10.0)
    full = Panel((Series(t, t ** 2, COLOURS[2], "a"),), "full")
    empty = Panel((Series(t, np.full(10, np.nan), COLOURS[3], "none"),), "empty")
    path = write_chart(tmp_path / "g.png", [full, empty, full, full], ncols=3,
                       panel_px=(200, 150))
    with Image.open(path) as im:
        assert im.size == (600, 300)  # 2 rows of 3, no title band


def test_unwritable_path_is_one_clear_error(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    t = np.arange(3.0)
    with pytest.raises(MecanumHILError, match="cannot write plot"):
        write_chart(blocker / "c.png", [Panel((Series(t, t, COLOURS[0]),))], ncols=1)


def test_fit_with_its_report_loads_neither_matplotlib_nor_pydantic(tmp_path):
    """fit writes its report on every run: matplotlib's import alone would double its time,
    and typer >= 0.29 brings pydantic into every command."""
    # the modules are listed by an exit handler: fit ends with os._exit once its handlers ran
    # (mecanum_hil/cli: run), and the exit code is checked below
    code = (
        "import atexit, json, sys\n"
        "atexit.register(lambda: print(json.dumps(sorted({m.split('.')[0] "
        "for m in sys.modules}))))\n"
        "from mecanum_hil.cli import run\n"
        f"sys.argv = ['mecanum-hil', 'fit', {str(ROOT / 'recordings/samples/paper-step-60.csv')!r},"
        f" '--out', {str(tmp_path / 'c.toml')!r}]\n"
        "run()\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          check=True, cwd=tmp_path)
    loaded = set(json.loads(done.stdout.strip().splitlines()[-1]))
    assert (tmp_path / "c.png").stat().st_size > 10_000
    assert not loaded & {"matplotlib", "pydantic"}
