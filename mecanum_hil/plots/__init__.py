"""PNG plots (matplotlib, no display): wheel speeds, path in the plane, heading."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from ..errors import MecanumHILError
from ..io.paths import replaced_when_whole
from ..io.recording import Recording


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: str | Path, dpi: int = 110) -> Path:
    """Lay out, write (creating the folder) and close a figure; a failure is one clear error."""
    plt = _pyplot()
    fig.tight_layout()
    p = Path(path)
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        with replaced_when_whole(p) as tmp:  # Ctrl-C leaves the previous plot, not half one
            fig.savefig(tmp, dpi=dpi, format=p.suffix.lstrip(".").lower() or "png")
    except OSError as err:
        raise MecanumHILError(f"{p}: cannot write plot: {err.strerror or err}") from err
    except ValueError as err:  # an extension matplotlib has no writer for
        raise MecanumHILError(f"{p}: cannot write plot: {err}; use .png") from err
    finally:
        plt.close(fig)
    return p


#: A path shorter than this in X and in Y [m] is drawn as a point: the robot turned in place.
IN_PLACE_M = 1e-3


def _mark_travel_in_place(ax, recordings: Mapping[str, Recording]) -> bool:
    """A path that stays within :data:`IN_PLACE_M` (a turn on the spot) is a line of zero
    length, invisible: mark where it stays and say so, with a view 0.2 m across. Returns
    whether it did."""
    pts = [r.pose[np.isfinite(r.pose[:, :2]).all(axis=1), :2] for r in recordings.values()]
    pts = [p for p in pts if p.size]
    if not pts:
        return False
    xy = np.concatenate(pts)
    if np.ptp(xy[:, 0]) > IN_PLACE_M or np.ptp(xy[:, 1]) > IN_PLACE_M:
        return False
    x0, y0 = xy.mean(axis=0)
    ax.plot([x0], [y0], "o", ms=9, mfc="none", mec="k")
    ax.annotate("in place: no travel in X-Y", (x0, y0), xytext=(0, 14),
                textcoords="offset points", ha="center", fontsize=9)
    ax.set_xlim(x0 - 0.1, x0 + 0.1)
    ax.locator_params(axis="x", nbins=5)
    ax.set_ylim(y0 - 0.1, y0 + 0.1)
    return True


def plot_recordings(recordings: Mapping[str, Recording], path: str | Path, title: str = "",
                    styles: Mapping[str, str] | None = None) -> Path:
    """Wheel speeds against time, path in the plane and heading against time.

    Parameters
    ----------
    recordings : Mapping[str, Recording]
        Label -> recording; each is drawn in every panel where it has data.
    path : str or Path
        PNG to write.
    title : str
        Figure title.
    styles : Mapping[str, str], optional
        Label -> matplotlib line style (``"-"``, ``"--"``, ``"."``).
    """
    plt = _pyplot()
    styles = dict(styles or {})
    has_pose = any(np.isfinite(r.pose[:, :2]).any() for r in recordings.values())
    ncols = 3 if has_pose else 1
    fig, axes = plt.subplots(1, ncols, figsize=(5.2 * ncols, 4.2), squeeze=False)
    ax_w = axes[0, 0]
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for label, rec in recordings.items():
        style = styles.get(label, "-")
        for i in range(4):
            y = rec.wheel_rpm[:, i]
            if np.isfinite(y).any():
                ax_w.plot(rec.t_s, y, style, color=colours[i], ms=2, lw=1.2,
                          label=f"{label} wheel {i + 1}")
    ax_w.set_xlabel("t [s]")
    ax_w.set_ylabel("wheel speed [rpm]")
    ax_w.grid(True, alpha=0.3)
    ax_w.legend(fontsize=7)
    if has_pose:
        ax_p, ax_h = axes[0, 1], axes[0, 2]
        for label, rec in recordings.items():
            style = styles.get(label, "-")
            if np.isfinite(rec.pose[:, :2]).any():
                ax_p.plot(rec.pose[:, 0], rec.pose[:, 1], style, label=label, ms=2)
                ax_h.plot(rec.t_s, rec.pose[:, 2], style, label=label, ms=2)
        ax_p.set_xlabel("X [m]")
        ax_p.set_ylabel("Y [m]")
        if not _mark_travel_in_place(ax_p, recordings):
            ax_p.set_aspect("equal", adjustable="datalim")
        ax_p.grid(True, alpha=0.3)
        ax_p.legend(fontsize=7)
        ax_h.set_xlabel("t [s]")
        ax_h.set_ylabel("heading phi [deg]")
        ax_h.grid(True, alpha=0.3)
    if title:
        fig.suptitle(title)
    return save_figure(fig, path, dpi=110)
