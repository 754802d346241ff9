"""PNG charts of curves against time without matplotlib: drawn with Pillow, for a fast path.

``mecanum-hil fit`` writes its report PNG on every run, and a user runs it dozens of times an
afternoon. matplotlib's import alone costs ~0.45 s on a 2-core machine, more than the rest of
the command; Pillow, which matplotlib itself depends on, loads in ~0.02 s. This
module draws what that report needs and nothing else: panels of measured dots and model lines
against time, with ticks, grid, axis labels, titles and a legend, anti-aliased by drawing at
twice the size and reducing. Every other plot of the package stays matplotlib
(:mod:`mecanum_hil.plots`).

Colours are matplotlib's default cycle, so the two kinds of plot read alike.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np

from ..errors import MecanumHILError

#: matplotlib's default colour cycle ("tab10").
COLOURS = ((31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
           (140, 86, 75), (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207))

_SCALE = 2  # drawn at twice the size, then reduced: anti-aliasing of lines, dots and text
_INK = (0, 0, 0)
_GRID = (222, 222, 222)
_WHITE = (255, 255, 255)


@dataclass(frozen=True)
class Series:
    """One curve of a panel.

    Attributes
    ----------
    x, y : numpy.ndarray
        Abscissa and ordinate, same length; non-finite values leave a gap.
    colour : tuple of int
        RGB, 0-255.
    label : str
        Legend entry ("" for none).
    dots : bool
        Dots (a measurement) rather than a line (a model).
    alpha : float
        Opacity of the dots, 0-1.
    """

    x: np.ndarray
    y: np.ndarray
    colour: tuple[int, int, int]
    label: str = ""
    dots: bool = False
    alpha: float = 0.6


@dataclass(frozen=True)
class Panel:
    """One set of axes: its curves, title and axis labels (units in brackets)."""

    series: tuple[Series, ...]
    title: str = ""
    xlabel: str = ""
    ylabel: str = ""


@dataclass(frozen=True)
class _Frame:
    """A panel's plot area in canvas pixels and its data limits."""

    left: int
    top: int
    right: int
    bottom: int
    xlim: tuple[float, float]
    ylim: tuple[float, float]

    def px(self, x: np.ndarray) -> np.ndarray:
        lo, hi = self.xlim
        return self.left + (np.asarray(x, dtype=float) - lo) * ((self.right - self.left)
                                                                / (hi - lo))

    def py(self, y: np.ndarray) -> np.ndarray:
        lo, hi = self.ylim
        return self.bottom - (np.asarray(y, dtype=float) - lo) * ((self.bottom - self.top)
                                                                  / (hi - lo))


def nice_ticks(lo: float, hi: float, most: int = 7) -> tuple[np.ndarray, int]:
    """Round tick values inside ``[lo, hi]`` (steps of 1, 2, 2.5 or 5 times a power of ten).

    Returns
    -------
    ticks : numpy.ndarray
        At most ``most`` values, at least two when the span allows.
    decimals : int
        Digits after the point that print every tick exactly.
    """
    span = hi - lo
    raw = span / max(most - 1, 1)
    if not (math.isfinite(span) and raw > 0):  # also a span that underflows when divided
        return np.array([lo]), 0
    power = 10.0 ** math.floor(math.log10(raw))
    for mult in (1.0, 2.0, 2.5, 5.0, 10.0):
        step = mult * power
        first = math.ceil(lo / step - 1e-9)
        last = math.floor(hi / step + 1e-9)
        if last - first + 1 <= most:
            break
    ticks = np.arange(first, last + 1) * step
    decimals = max(0, -math.floor(math.log10(step) + 1e-9)) + (1 if mult == 2.5 else 0)
    return ticks, decimals


def _limits(values: list[np.ndarray], margin: float) -> tuple[float, float]:
    finite = [v[np.isfinite(v)] for v in values]
    finite = [v for v in finite if v.size]
    if not finite:
        return 0.0, 1.0
    # a diverged model's values near the float limit would overflow the span: the axis stops
    # at +-1e300 and such points are drawn at its edge
    lo = max(min(float(v.min()) for v in finite), -1e300)
    hi = min(max(float(v.max()) for v in finite), 1e300)
    if hi - lo <= 1e-12 * max(abs(lo), abs(hi), 1.0):
        pad = max(abs(lo) * 0.05, 0.5)
        return lo - pad, hi + pad
    pad = (hi - lo) * margin
    return lo - pad, hi + pad


def _panel_image(panel: Panel, panel_px: tuple[int, int]):
    """One panel drawn at :data:`_SCALE` times its size, then reduced (Pillow image)."""
    from PIL import Image, ImageDraw

    s = _SCALE
    pw, ph = panel_px[0] * s, panel_px[1] * s
    image = Image.new("RGB", (pw, ph), _WHITE)
    frame = _frame(panel, 66 * s, 24 * s, pw - 12 * s, ph - 40 * s)
    ticks = _ticks(frame)
    _grid(ImageDraw.Draw(image), frame, ticks)
    canvas = np.array(image)
    for series in panel.series:
        if series.dots:
            _stamp_dots(canvas, frame, series, 1.9 * s)
    image = Image.fromarray(canvas)
    draw = ImageDraw.Draw(image)
    for series in panel.series:
        if not series.dots:
            _draw_line(draw, frame, series, round(1.3 * s))
    _axes(draw, image, frame, panel, ticks, s)
    _legend(draw, frame, panel.series, s)
    return image.reduce(s)


@cache
def _font(size_px: int):
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size_px)  # FreeType (Pillow >= 10.1)
    except (TypeError, OSError, ImportError):  # without FreeType: the fixed bitmap font
        return ImageFont.load_default()


def _text_size(draw, text: str, font) -> tuple[int, int]:
    left, top, right, bottom = draw.textbbox((0, 0), text, font=font)
    return right - left, bottom - top


def _text(draw, xy: tuple[float, float], text: str, font, align: str = "left",
          valign: str = "top", fill=_INK) -> None:
    """Draw ``text`` with its box's ``align``/``valign`` edge (or centre) at ``xy``."""
    left, top, right, bottom = draw.textbbox((0, 0), text, font=font)
    w, h = right - left, bottom - top
    x = xy[0] - {"left": 0, "centre": w / 2, "right": w}[align] - left
    y = xy[1] - {"top": 0, "centre": h / 2, "bottom": h}[valign] - top
    draw.text((x, y), text, font=font, fill=fill)


def _vertical_text(image, centre: tuple[float, float], text: str, font) -> None:
    """Text turned 90 degrees (a y-axis label), centred at ``centre``."""
    from PIL import Image, ImageDraw

    probe = ImageDraw.Draw(image)
    left, top, right, bottom = probe.textbbox((0, 0), text, font=font)
    mask = Image.new("L", (right - left + 2, bottom - top + 2), 0)
    ImageDraw.Draw(mask).text((1 - left, 1 - top), text, font=font, fill=255)
    mask = mask.rotate(90, expand=True)
    box = (int(centre[0] - mask.width / 2), int(centre[1] - mask.height / 2))
    image.paste(_INK, (*box, box[0] + mask.width, box[1] + mask.height), mask)


def _disc(radius: float) -> tuple[np.ndarray, np.ndarray]:
    r = math.ceil(radius)
    dy, dx = np.mgrid[-r:r + 1, -r:r + 1]
    inside = dx * dx + dy * dy <= radius * radius
    return dx[inside], dy[inside]


def _stamp_dots(canvas: np.ndarray, frame: _Frame, s: Series, radius: float) -> None:
    """Blend discs of ``s.colour`` at ``s.alpha`` into ``canvas`` (H x W x 3, uint8) in place."""
    keep = np.isfinite(s.x) & np.isfinite(s.y)
    if not keep.any():
        return
    cx = np.rint(frame.px(s.x[keep])).astype(np.int64)
    cy = np.rint(frame.py(s.y[keep])).astype(np.int64)
    dx, dy = _disc(radius)
    xs = (cx[:, None] + dx[None, :]).ravel()
    ys = (cy[:, None] + dy[None, :]).ravel()
    inside = (xs >= frame.left) & (xs <= frame.right) & (ys >= frame.top) & (ys <= frame.bottom)
    flat = np.unique(ys[inside] * canvas.shape[1] + xs[inside])  # overlapping discs: once
    pixels = canvas.reshape(-1, 3)
    blended = pixels[flat] * (1.0 - s.alpha) + np.asarray(s.colour, dtype=float) * s.alpha
    pixels[flat] = np.rint(blended).astype(np.uint8)


def _runs(keep: np.ndarray) -> list[tuple[int, int]]:
    """``(start, stop)`` of each run of True in ``keep``."""
    edges = np.flatnonzero(np.diff(np.concatenate(([0], keep.astype(np.int8), [0]))))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True))


def _draw_line(draw, frame: _Frame, s: Series, width: int) -> None:
    keep = np.isfinite(s.x) & np.isfinite(s.y)
    xs, ys = frame.px(s.x), frame.py(s.y)
    for a, b in _runs(keep):
        pts = np.column_stack((xs[a:b], ys[a:b])).ravel().tolist()
        if b - a == 1:
            draw.point(pts, fill=s.colour)
        else:
            draw.line(pts, fill=s.colour, width=width)


def _legend_corner(frame: _Frame, series: Sequence[Series], size: tuple[int, int],
                   pad: int) -> tuple[int, int]:
    """Top-left of the legend box: the plot corner that hides the fewest data points."""
    w, h = size
    corners = [(frame.right - pad - w, frame.top + pad), (frame.left + pad, frame.top + pad),
               (frame.right - pad - w, frame.bottom - pad - h),
               (frame.left + pad, frame.bottom - pad - h)]
    xs = np.concatenate([frame.px(s.x) for s in series]) if series else np.zeros(0)
    ys = np.concatenate([frame.py(s.y) for s in series]) if series else np.zeros(0)
    hidden = [int(np.count_nonzero((xs >= x) & (xs <= x + w) & (ys >= y) & (ys <= y + h)))
              for x, y in corners]
    return corners[int(np.argmin(hidden))]  # first of the least covered: upper right first


def _legend(draw, frame: _Frame, series: Sequence[Series], scale: int) -> None:
    entries = [s for s in series if s.label]
    if not entries:
        return
    font = _font(7 * scale)
    line_h = max(_text_size(draw, s.label, font)[1] for s in entries) + 3 * scale
    key_w, pad, gap = 18 * scale, 4 * scale, 4 * scale
    text_w = max(_text_size(draw, s.label, font)[0] for s in entries)
    size = (pad * 2 + key_w + gap + text_w, pad * 2 + line_h * len(entries))
    x, y = _legend_corner(frame, series, size, 4 * scale)
    draw.rectangle((x, y, x + size[0], y + size[1]), fill=_WHITE, outline=(204, 204, 204),
                   width=max(1, scale // 2))
    for k, s in enumerate(entries):
        cy = y + pad + line_h * k + line_h / 2
        if s.dots:
            r = 1.8 * scale
            faded = tuple(round(c * s.alpha + 255 * (1 - s.alpha)) for c in s.colour)
            draw.ellipse((x + pad + key_w / 2 - r, cy - r, x + pad + key_w / 2 + r, cy + r),
                         fill=faded)
        else:
            draw.line((x + pad, cy, x + pad + key_w, cy), fill=s.colour, width=int(1.3 * scale))
        _text(draw, (x + pad + key_w + gap, cy), s.label, font, valign="centre")


def _frame(panel: Panel, left: int, top: int, right: int, bottom: int) -> _Frame:
    xlim = _limits([s.x for s in panel.series], 0.0)
    ylim = _limits([np.where(np.isfinite(s.x), s.y, np.nan) for s in panel.series], 0.05)
    return _Frame(left, top, right, bottom, xlim, ylim)


def _ticks(frame: _Frame) -> tuple[np.ndarray, int, np.ndarray, int]:
    """Tick values and their decimals: ``(x, x decimals, y, y decimals)``."""
    return (*nice_ticks(*frame.xlim), *nice_ticks(*frame.ylim))


def _grid(draw, frame: _Frame, ticks) -> None:
    xticks, _, yticks, _ = ticks
    for v in xticks:
        x = float(frame.px(v))
        draw.line((x, frame.top, x, frame.bottom), fill=_GRID, width=1)
    for v in yticks:
        y = float(frame.py(v))
        draw.line((frame.left, y, frame.right, y), fill=_GRID, width=1)


def _axes(draw, image, frame: _Frame, panel: Panel, ticks, scale: int) -> None:
    """Frame, ticks with their values, axis labels and the panel title."""
    xticks, xdec, yticks, ydec = ticks
    tick_font, label_font = _font(8 * scale), _font(9 * scale)
    tick = 3 * scale
    draw.rectangle((frame.left, frame.top, frame.right, frame.bottom), outline=_INK,
                   width=max(1, int(0.8 * scale)))
    widest = 0
    for v in xticks:
        x = float(frame.px(v))
        draw.line((x, frame.bottom, x, frame.bottom + tick), fill=_INK, width=max(1, scale // 2))
        _text(draw, (x, frame.bottom + tick + 2 * scale), f"{v + 0.0:.{xdec}f}", tick_font,
              align="centre")
    for v in yticks:
        y = float(frame.py(v))
        draw.line((frame.left - tick, y, frame.left, y), fill=_INK, width=max(1, scale // 2))
        text = f"{v + 0.0:.{ydec}f}"
        widest = max(widest, _text_size(draw, text, tick_font)[0])
        _text(draw, (frame.left - tick - 2 * scale, y), text, tick_font, align="right",
              valign="centre")
    if panel.xlabel:
        _text(draw, ((frame.left + frame.right) / 2, frame.bottom + tick + 14 * scale),
              panel.xlabel, label_font, align="centre")
    if panel.ylabel:
        _vertical_text(image, (frame.left - tick - 2 * scale - widest - 8 * scale,
                               (frame.top + frame.bottom) / 2), panel.ylabel, label_font)
    if panel.title:
        _text(draw, ((frame.left + frame.right) / 2, frame.top - 5 * scale), panel.title,
              label_font, align="centre", valign="bottom")


def write_chart(path: str | Path, panels: Sequence[Panel], ncols: int, title: str = "",
                panel_px: tuple[int, int] = (594, 429)) -> Path:
    """Draw ``panels`` in a grid of ``ncols`` columns and write them as a PNG.

    Parameters
    ----------
    path : str or Path
        PNG to write (its folder is created).
    panels : sequence of Panel
        Row by row.
    ncols : int
        Panels per row.
    title : str
        Title above all panels.
    panel_px : (int, int)
        Width and height of one panel [px].

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    MecanumHILError
        The file cannot be written.
    """
    from PIL import Image, ImageDraw

    ncols = max(1, min(ncols, len(panels) or 1))
    nrows = max(1, math.ceil(len(panels) / ncols))
    head = 26 if title else 0
    image = Image.new("RGB", (panel_px[0] * ncols, panel_px[1] * nrows + head), _WHITE)
    # each panel drawn supersampled on its own and reduced into place: memory stays one
    # panel's, however many recordings (the whole grid at twice the size was ~10 MB a panel)
    for k, panel in enumerate(panels):
        image.paste(_panel_image(panel, panel_px),
                    ((k % ncols) * panel_px[0], head + (k // ncols) * panel_px[1]))
    if title:
        s = _SCALE
        band = Image.new("RGB", (image.width * s, head * s), _WHITE)
        _text(ImageDraw.Draw(band), (band.width / 2, 6 * s), title, _font(10 * s),
              align="centre")
        image.paste(band.reduce(s), (0, 0))
    p = Path(path)
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        image.save(p, format="PNG", compress_level=1)
    except OSError as err:
        raise MecanumHILError(f"{p}: cannot write plot: {err.strerror or err}") from err
    return p
